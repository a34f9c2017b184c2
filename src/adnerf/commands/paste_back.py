"""Paste rendered squares back into the source video's frames (``adnerf render --paste-back``).

A dataset cropped and scaled from its source (:class:`~adnerf.preprocess.framing.Framing`)
renders the square the model works in. Pasting back scales each rendered square to the crop's
size in source pixels and blends it into a full-size frame over a feathered border, so the output
has the source's resolution and the person's surroundings as filmed:

- the frame is the training clip's own source frame whose head pose the render used (the
  dataset's frames in order, ping-ponged when the audio is longer, as ``render`` takes the
  training poses: :func:`~adnerf.commands.render_video.pingpong`), read a chunk at a time (:class:`~adnerf.io.FrameReader`), or one still image for every frame;
- outside the crop the frame is left exactly as it was; inside, more than ``feather`` pixels from
  the crop's edges, it is the render (scaled); across those pixels the two are blended linearly.
  Edges of the crop that lie on the frame's border need no blend and get none.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from ..io import AudioTrack, FrameReader, MediaError, VideoWriter, frame_times
from ..preprocess.frame_grid import regular_grid
from ..preprocess.framing import Framing

__all__ = ["FEATHER", "PasteBackError", "feather_mask", "paste", "paste_back_frames", "source_frames_of_dataset", "write_pasted"]

FEATHER = 0.04  # the blend's width, as a fraction of the crop's width


class PasteBackError(ValueError):
    """A paste-back that cannot be done (no source frames, a frame of another size)."""


def feather_mask(framing: Framing, feather: float = FEATHER) -> np.ndarray:
    """The render's weight over the crop, ``(h, w)`` float32 in ``[0, 1]``.

    1 from ``feather * w`` pixels inside each edge of the crop, falling linearly to 0 at the edge
    itself (``1 / (n + 1)`` steps over ``n`` pixels, so the render never fully vanishes inside the
    crop nor fully takes over at its edge); an edge that lies on the source frame's border keeps 1.
    """
    x0, y0, w, h = framing.crop
    W, H = framing.source_size
    n = max(1, int(round(feather * w)))
    ramp = np.minimum(np.arange(1, max(w, h) + 1, dtype=np.float32) / (n + 1), 1.0)

    def side(length: int, at_start: bool, at_end: bool) -> np.ndarray:
        rise = ramp[:length] if not at_start else np.ones(length, np.float32)
        fall = ramp[:length][::-1] if not at_end else np.ones(length, np.float32)
        return np.minimum(rise, fall)

    cols = side(w, x0 == 0, x0 + w == W)
    rows = side(h, y0 == 0, y0 + h == H)
    return np.minimum(rows[:, None], cols[None, :]).astype(np.float32)


def paste(square: np.ndarray, frame: np.ndarray, framing: Framing, mask: np.ndarray) -> np.ndarray:
    """One rendered square ``(h', w', 3)`` uint8 pasted into a full-size frame ``(H, W, 3)`` uint8.

    Returns:
        A new ``(H, W, 3)`` uint8 frame: ``frame`` outside the crop, the square scaled to the crop
        blended by ``mask`` (:func:`feather_mask`) inside it.
    """
    W, H = framing.source_size
    if frame.shape != (H, W, 3):
        raise PasteBackError(f"a frame to paste into must be {W}x{H} (the source's size); got {frame.shape[1]}x{frame.shape[0]}")
    x0, y0, w, h = framing.crop
    if (square.shape[1], square.shape[0]) == (w, h):
        up = square
    else:
        up = cv2.resize(square, (w, h), interpolation=cv2.INTER_LINEAR if w >= square.shape[1] else cv2.INTER_AREA)
    out = frame.copy()
    region = out[y0 : y0 + h, x0 : x0 + w].astype(np.float32)
    a = mask[..., None]
    out[y0 : y0 + h, x0 : x0 + w] = np.clip(np.rint(a * up.astype(np.float32) + (1.0 - a) * region), 0, 255).astype(np.uint8)
    return out


def source_frames_of_dataset(framing: Framing, video: str | Path, n_frames: int, fps: float) -> np.ndarray:
    """The source frame index of each of the dataset's ``n_frames`` frames, ``(n_frames,)`` int.

    Preprocessing kept the frames from ``framing.start_s`` on and placed them on a grid of ``fps``
    frames a second by their timestamps (:func:`~adnerf.preprocess.frame_grid.regular_grid`); the
    same grid over the same timestamps gives the same frames.

    Raises:
        PasteBackError: The video has fewer frames after the start than the dataset.
    """
    try:
        times = frame_times(video)
    except MediaError as exc:
        raise PasteBackError(str(exc)) from exc
    kept = np.flatnonzero(times - times[0] >= framing.start_s - 1e-6)
    if len(kept) == 0:
        raise PasteBackError(f"{video}: no frame {framing.start_s:g} s or later: is it the video this dataset was made from?")
    index = kept[regular_grid(times[kept], fps).index]
    if len(index) < n_frames:
        raise PasteBackError(f"{video}: {len(index)} frames from {framing.start_s:g} s on, the dataset has {n_frames}: is it the video this dataset was made from?")
    return index[:n_frames]


def paste_back_frames(
    squares: Sequence[np.ndarray],
    framing: Framing,
    *,
    video: str | Path | None = None,
    source_index: np.ndarray | None = None,
    still: np.ndarray | None = None,
    feather: float = FEATHER,
) -> Iterator[np.ndarray]:
    """Full-size frames, one per rendered square, streamed (the source is never held whole).

    Args:
        squares: Rendered squares ``(h', w', 3)`` uint8, the dataset's size.
        framing: The dataset's framing.
        video: The source video (with ``source_index``).
        source_index: The source frame index of each output frame, ``(len(squares),)``.
        still: One full-size ``(H, W, 3)`` uint8 image to paste every square into, instead.
    """
    mask = feather_mask(framing, feather)
    if still is not None:
        for square in squares:
            yield paste(square, still, framing, mask)
        return
    if video is None or source_index is None or len(source_index) != len(squares):
        raise PasteBackError("paste-back needs the source video and one source frame index per rendered frame, or a still image")
    with FrameReader(video) as reader:
        for square, k in zip(squares, source_index):
            yield paste(square, reader[int(k)], framing, mask)


def write_pasted(out: str | Path, frames: Iterator[np.ndarray], fps: float, audio: AudioTrack) -> int:
    """Write streamed full-size frames as an mp4 with ``audio`` (atomically); returns the count."""
    n = 0
    with VideoWriter(out, fps, audio) as writer:
        for frame in frames:
            writer.write(frame)
            n += 1
    return n
