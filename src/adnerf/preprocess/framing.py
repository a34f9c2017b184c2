"""Where the dataset's square sits in the user's footage: the crop, the scale and the trim.

Phones and webcams film 1280x720 or 1920x1080 with the person in the middle third; the model works
in a square of a few hundred pixels around the head and shoulders. :class:`Framing` records the
map between the two, so that the crop can be undone (the render pasted back into the source
frames) and the camera follows it:

* a dataset pixel ``(u, v)`` (pixel centres at ``+0.5``) is the source point
  ``(x0 + u / scale, y0 + v / scale)``, with ``(x0, y0, w, h)`` the crop in source pixels and
  ``scale`` the dataset's pixels per source pixel;
* the focal length scales by ``scale`` and the principal point (the source frame's centre) moves
  with the crop (:meth:`Framing.intrinsics`).

The crop is one fixed rectangle for the whole clip (a crop that moved would be a moving camera).
``--crop auto`` (:func:`auto_crop`) takes a square around the face's range over the clip, with
room for the hair above and the shoulders below, as AD-NeRF's datasets are framed; a frame whose
longer side is already within ``--size`` is used whole.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = ["AUTO_SIDE", "FOCAL_GUESS", "Framing", "auto_crop", "parse_crop", "plan_framing", "square_around"]

FOCAL_GUESS = 1.33  # focal length over the source frame's longer side when none is given (a 41 degree field of view)
AUTO_SIDE = 3.2  # the auto crop's side over the face box's width (head, hair, neck and shoulders)
AUTO_CENTRE = 0.45  # the face's centre sits this far down the auto crop
SAMPLES_PER_SECOND = 2.0  # frames of the clip the auto crop looks at (at most MAX_SAMPLES)
MAX_SAMPLES = 120
DETECT_SIDE = 960  # longer side the sampled frames are scaled to for the face detector (enlarged at most 2x: HOG misses faces under ~80 px)


@dataclass(frozen=True)
class Framing:
    """The dataset's frames as a crop of the source video's, scaled, from a start time.

    Attributes:
        source_size: ``(width, height)`` of the source's upright frames, pixels.
        crop: ``(x0, y0, w, h)`` of the crop in source pixels (the whole frame when not cropped).
        size: ``(width, height)`` of the dataset's frames, pixels.
        start_s: Seconds into the source (from its first frame) of the dataset's frame 0.
        video: The source file's absolute path when preprocessed (where ``render --paste-back``
            finds the frames to paste into; ``""``: not recorded).
    """

    source_size: tuple[int, int]
    crop: tuple[int, int, int, int]
    size: tuple[int, int]
    start_s: float = 0.0
    video: str = ""

    @property
    def scale(self) -> float:
        """Dataset pixels per source pixel."""
        return self.size[0] / self.crop[2]

    @property
    def cropped(self) -> bool:
        """The dataset shows less than the whole source frame, or another size of it."""
        return tuple(self.crop) != (0, 0, *self.source_size) or tuple(self.size) != tuple(self.source_size)

    def transform(self, frame: np.ndarray) -> np.ndarray:
        """A source frame ``(H, W, 3)`` as the dataset's: cropped, then resized (area averaging)."""
        x0, y0, w, h = self.crop
        part = frame[y0 : y0 + h, x0 : x0 + w]
        if (w, h) == tuple(self.size):
            return part
        return cv2.resize(part, tuple(self.size), interpolation=cv2.INTER_AREA if self.scale < 1 else cv2.INTER_LINEAR)

    def intrinsics(self, focal: float | None = None) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` of the dataset's camera, pixels.

        Args:
            focal: The source camera's focal length in source pixels (default
                :data:`FOCAL_GUESS` times the source frame's longer side); its principal point is
                the source frame's centre.
        """
        W, H = self.source_size
        f = (focal if focal is not None else FOCAL_GUESS * max(W, H)) * self.scale
        x0, y0 = self.crop[:2]
        return (float(f), float(f), (W / 2.0 - x0) * self.scale, (H / 2.0 - y0) * self.scale)

    def to_dict(self) -> dict:
        """JSON-ready fields (lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, doc: dict) -> "Framing":
        return cls(tuple(doc["source_size"]), tuple(doc["crop"]), tuple(doc["size"]), float(doc.get("start_s", 0.0)), str(doc.get("video", "")))


def parse_crop(text: str) -> str | tuple[int, int, int, int]:
    """``"auto"``, ``"none"`` or ``"X,Y,W,H"`` (source pixels, W and H > 0) as the crop setting.

    Raises:
        ValueError: Anything else.
    """
    t = str(text).strip().lower()
    if t in ("auto", "none"):
        return t
    try:
        x, y, w, h = (int(v) for v in t.split(","))
    except ValueError:
        raise ValueError(f"a crop is auto, none or X,Y,W,H in the source's pixels; got {text!r}") from None
    if x < 0 or y < 0 or w <= 0 or h <= 0:
        raise ValueError(f"a crop X,Y,W,H needs X, Y >= 0 and W, H > 0; got {text!r}")
    return (x, y, w, h)


def square_around(face: tuple[float, float, float, float], face_width: float, source_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """The square crop ``(x0, y0, side, side)`` around a face's range: side :data:`AUTO_SIDE` face
    widths plus the range's own extent, the face's centre :data:`AUTO_CENTRE` of the way down,
    shifted (and if need be shrunk) to lie inside the source frame.

    Args:
        face: ``(x0, y0, x1, y1)``: the union of the face boxes over the clip, source pixels.
        face_width: The face box's typical (median) width, source pixels.
        source_size: ``(width, height)`` of the source frames.
    """
    W, H = source_size
    x0, y0, x1, y1 = face
    side = AUTO_SIDE * face_width + max(x1 - x0, y1 - y0) - face_width
    side = int(min(round(side), W, H))
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    left = int(np.clip(round(cx - side / 2), 0, W - side))
    top = int(np.clip(round(cy - AUTO_CENTRE * side), 0, H - side))
    return (left, top, side, side)


def auto_crop(video: str | Path, detector, source_size: tuple[int, int], start: float = 0.0, end: float | None = None) -> tuple[tuple[int, int, int, int], dict]:  # noqa: ANN001
    """The fixed square around the face's range over the clip (:func:`square_around`).

    The clip is sampled :data:`SAMPLES_PER_SECOND` times a second (at most :data:`MAX_SAMPLES`
    frames), scaled to :data:`DETECT_SIDE` pixels, and the face detector runs on each sample.

    Args:
        video: The source video.
        detector: A :class:`~adnerf.preprocess.landmarks.FaceDetector`.
        source_size: ``(width, height)`` of the video's upright frames.
        start: Trim start, seconds from the first frame.
        end: Trim end (``None``: the clip's end).

    Returns:
        The crop ``(x0, y0, side, side)`` in source pixels and a report
        ``{"sampled", "found", "face_box", "face_width_px"}``.

    Raises:
        ValueError: No sampled frame shows a face.
    """
    from ..io import probe, read_video

    meta = probe(video)
    fps = float(meta.get("fps") or 25.0)
    span = (end if end is not None else float(meta.get("duration") or 0.0)) - start
    every = max(1, int(round(fps / SAMPLES_PER_SECOND)), int(np.ceil(span * fps / MAX_SAMPLES)))
    W, H = source_size
    scale = min(2.0, DETECT_SIDE / max(W, H))
    size = (round(W * scale), round(H * scale))

    def shrink(frame: np.ndarray) -> np.ndarray:
        return frame if scale == 1.0 else cv2.resize(frame, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)

    sample = read_video(video, audio=False, start=start, end=end, transform=shrink, every=every)
    boxes = []
    for frame in sample.frames:
        found = detector.detect(frame)
        if found:
            best = max(found, key=lambda d: d.score)
            boxes.append(np.asarray(best.box, dtype=np.float64) / scale)
    if not boxes:
        raise ValueError(f"{video}: --crop auto found no face in the {len(sample.frames)} frames it sampled; give the crop as --crop X,Y,W,H (source pixels) or --crop none")
    b = np.stack(boxes)
    face = (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max()))
    width = float(np.median(b[:, 2] - b[:, 0]))
    crop = square_around(face, width, source_size)
    return crop, {"sampled": len(sample.frames), "found": len(boxes), "face_box": [round(v, 1) for v in face], "face_width_px": round(width, 1)}


def plan_framing(source_size: tuple[int, int], crop: tuple[int, int, int, int] | str, size: int | None, start: float = 0.0) -> Framing:
    """The :class:`Framing` of a crop rectangle (or ``"none"``: the whole frame) scaled so that its
    longer side is at most ``size`` pixels (``None``: not scaled; never enlarged).

    Raises:
        ValueError: A crop that does not lie inside the source frame.
    """
    W, H = source_size
    if crop == "none":
        crop = (0, 0, W, H)
    if not isinstance(crop, tuple):
        raise ValueError(f"plan_framing takes a crop rectangle or 'none'; got {crop!r}")
    x0, y0, w, h = crop
    if x0 + w > W or y0 + h > H:
        raise ValueError(f"the crop {x0},{y0},{w},{h} reaches past the {W}x{H} source frame")
    s = 1.0 if size is None or max(w, h) <= size else size / max(w, h)
    out = (max(1, int(math.floor(w * s + 0.5))), max(1, int(math.floor(h * s + 0.5))))
    return Framing((W, H), (x0, y0, w, h), out, float(start))
