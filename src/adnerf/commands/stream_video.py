"""``adnerf stream``: render a run frame by frame as its speech arrives, into an mp4 (or PNGs).

The speech is a file played as if it were arriving, ``chunk`` seconds at a time, or raw 16 kHz
mono signed 16-bit PCM on standard input (``-``: what ``arecord -f S16_LE -r 16000 -c 1`` or a
text-to-speech engine writes). Frames are encoded as they become final
(:class:`~adnerf.model.stream.Streamer`); the sound is muxed with them when the stream ends.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import cv2
import numpy as np

from ..audio.features import MODEL_RATE
from ..io import VideoWriter
from ..model.render_clip import RenderError
from ..model.run_folder import Run
from ..model.stream import Streamer, stream_file_chunks
from .render_video import frame_name, load_background

__all__ = ["pcm_chunks", "stream_to_video"]


def pcm_chunks(source: BinaryIO, chunk_s: float) -> Iterator[np.ndarray]:
    """Float samples from raw 16 kHz mono signed 16-bit little-endian PCM, ``chunk_s`` seconds at a
    time (the last piece may be shorter; an odd trailing byte is dropped)."""
    size = max(2, 2 * int(round(chunk_s * MODEL_RATE)))
    carry = b""
    while True:
        block = source.read(size)
        if not block:
            break
        block = carry + block
        cut = len(block) - len(block) % 2
        carry = block[cut:]
        if cut:
            yield np.frombuffer(block[:cut], dtype="<i2").astype(np.float32) / 32768.0


def stream_to_video(
    run: Run,
    source: str | Path,
    out: str | Path,
    *,
    chunk_s: float = 0.04,
    yaw: float = 0.0,
    pitch: float = 0.0,
    roll: float = 0.0,
    blink: str = "auto",
    background: str | Path | None = None,
    frames_dir: str | Path | None = None,
    progress: Callable[[int], None] | None = None,
    stdin: BinaryIO | None = None,
    causal: bool = False,
) -> dict:
    """Stream ``source`` (a file, or ``"-"`` for PCM on standard input) through a :class:`Streamer`
    into the mp4 ``out`` (and PNGs in ``frames_dir``); ``causal`` is the Streamer's low-latency mode.

    Returns:
        A summary: frames, seconds of audio, the look-ahead, the wall seconds from the first piece of
        audio to the first frame, the wall time and the real-time factor (audio seconds per wall second).
    """
    meta = run.meta
    plate = None if background is None else load_background(background, meta["height"], meta["width"])
    live = str(source) == "-"
    if live:
        start, pieces = 0.0, pcm_chunks(stdin if stdin is not None else sys.stdin.buffer, chunk_s)
        sound = np.zeros(0, np.float32)
    else:
        start, chunks = stream_file_chunks(source, chunk_s)
        pieces, sound = iter(chunks), np.concatenate(chunks) if chunks else np.zeros(0, np.float32)
    streamer = Streamer(run, plate=plate, yaw=yaw, pitch=pitch, roll=roll, blink=blink, start=start, causal=causal)
    folder = None if frames_dir is None else Path(frames_dir)
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
    n = 0
    samples = 0
    t0 = time.perf_counter()
    with VideoWriter(out, streamer.fps, sound, MODEL_RATE) as writer:

        def emit(frames: list[np.ndarray]) -> None:
            nonlocal n
            for frame in frames:
                writer.write(frame)
                if folder is not None and not cv2.imwrite(str(folder / frame_name(n)), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)):
                    raise RenderError(f"{folder}: could not write frame {n}")
                n += 1
                if progress is not None:
                    progress(n)

        for piece in pieces:
            if live:
                writer.append_audio(piece)
            samples += len(piece)
            emit(streamer.push(piece))
        emit(streamer.finish())
        if n == 0:
            raise RenderError(f"{source}: the speech is shorter than one frame at {streamer.fps:g} fps")
    wall = time.perf_counter() - t0
    seconds = samples / MODEL_RATE
    return {
        "output": str(out),
        "frames": n,
        "audio_seconds": seconds,
        "lookahead_s": streamer.lookahead_s,
        "causal": causal,
        "first_frame_s": streamer.first_frame_s,
        "wall_seconds": wall,
        "realtime_factor": seconds / max(wall, 1e-9),
    }
