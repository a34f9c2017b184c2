"""Eye blinks: natural blink tracks and the choices ``adnerf render --blink`` offers.

An eye-openness track is one value per frame: 1 the eyes as open as usual, 0 closed (the scale of
a dataset's ``eye.npy``, see :mod:`adnerf.formats.dataset`). :func:`blink_track` makes natural blinks (one
every 2-6 s, 0.2 s long, as people blink while talking); the synthetic scene blinks with it and
``render --blink auto`` plays it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["BLINKING", "BLINK_GAP", "BLINK_SECONDS", "BLINK_CHOICES", "blink_track", "blinks_in", "count_blinks", "eye_track"]

BLINKING = 0.75  # eye openness below which a frame counts as blinking
BLINK_SECONDS = 0.2
BLINK_GAP = (2.0, 6.0)  # seconds between blinks
BLINK_CHOICES = ("auto", "none", "FILE.npy")


def blink_track(times: np.ndarray, seed: int = 0, gap: tuple[float, float] = BLINK_GAP, duration: float = BLINK_SECONDS) -> np.ndarray:
    """Eye openness in ``[0, 1]`` at ``times`` (seconds) with natural blinks.

    Blinks start at random times (the first within ``gap[1]`` seconds, then every ``gap[0]`` to
    ``gap[1]`` seconds, from their own random stream: independent of speech and pose) and close
    the eyes as ``sin^2(pi u)`` over ``u = (t - start) / duration`` in ``[0, 1]``: fully closed
    halfway, open again at the end.
    """
    if not (0 < gap[0] <= gap[1]) or not duration > 0:
        raise ValueError(f"blinks need 0 < gap[0] <= gap[1] and a positive duration; got {gap}, {duration}")
    times = np.asarray(times, dtype=np.float64)
    rng = np.random.default_rng([seed, 0xB11A])
    closed = np.zeros_like(times)
    start = rng.uniform(0.0, gap[1])
    end = float(times.max()) if times.size else 0.0
    while start <= end:
        u = (times - start) / duration
        closed = np.maximum(closed, np.where((u >= 0) & (u <= 1), np.sin(np.pi * u) ** 2, 0.0))
        start += rng.uniform(*gap)
    return 1.0 - closed


def blinks_in(eye: np.ndarray | None, frames: Sequence[int]) -> bool:
    """Whether an eye-openness track ``(N,)`` (``None``: none) blinks in any of ``frames``: only
    then is there anything for a head to learn from it. A clip that never blinks (the shared real
    clip's openness stays within 0.81-1.23) gives a per-frame value that carries no blink, only
    a number the head could tell frames apart by instead of by their speech."""
    return eye is not None and bool((np.asarray(eye)[list(frames)] < BLINKING).any())


def count_blinks(eye: np.ndarray, closed: float = 0.5) -> int:
    """How many times an eye-openness track ``(n,)`` falls below ``closed`` (a blink each)."""
    eye = np.asarray(eye)
    return int(((eye[1:] < closed) & (eye[:-1] >= closed)).sum())


def eye_track(blink: str | Path, n: int, fps: float, seed: int = 0) -> np.ndarray:
    """The eye openness of ``n`` frames ``(n,)`` float32 for a ``--blink`` choice.

    Args:
        blink: ``"auto"`` (natural blinks, :func:`blink_track`), ``"none"`` (eyes open) or the path
            of an ``.npy`` with one value per frame (at least ``n``; the first ``n`` are used).
        n: Frames.
        fps: Frame rate.
        seed: Seed of the natural blinks.

    Raises:
        ValueError: A file that cannot be read, with too few or non-finite values.
    """
    if blink == "auto":
        return blink_track(np.arange(n) / fps, seed).astype(np.float32)
    if blink == "none":
        return np.ones(n, np.float32)
    path = Path(blink)
    try:
        values = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--blink {blink}: not auto, none or a readable .npy of eye openness ({exc})") from exc
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(values) < n or not np.isfinite(values[:n]).all():
        raise ValueError(f"--blink {blink}: needs {n} finite eye-openness values (one per frame, 1 open, 0 closed); got {len(values)}")
    return values[:n].astype(np.float32)
