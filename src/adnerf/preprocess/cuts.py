"""Shot cuts and reframings: where the picture jumps between two frames of a static-camera clip.

A talking head filmed by a static camera changes little from one frame to the next: the mouth,
the eyes, a slight turn of the head. An edit changes everything at once: a cut to another shot,
or a reframing (broadcast footage often splices takes zoomed or shifted by a few per cent), where
every edge of the background moves. Trained on such a clip, one camera and one background plate
would have to explain two framings.

:func:`find_cuts` measures, for each pair of consecutive frames, the fraction of the frame's top
and side strips (:data:`BORDER`; where the background of a talking head is, and where the person
seldom reaches) that changed (grey levels, on a copy 96 pixels wide and blurred, so that noise
and compression do not count), and calls a pair a cut where that fraction is both large
(:data:`MIN_CHANGED`) and a spike: many times the clip's typical change (:data:`SPIKE`) and its
neighbours' (a camera that moves all the time changes every pair and is another problem, which
the parse step measures).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BORDER", "Cuts", "MIN_CHANGED", "SPIKE", "find_cuts"]

MIN_CHANGED = 0.08  # fraction of the picture a cut changes at least
SPIKE = 6.0  # a cut changes this many times the clip's median pair and both neighbours
LEVEL = 12.0  # grey levels (0-255) a pixel must change by to count
WIDTH = 96  # pixels across the copy that is compared
BORDER = 0.15  # width of the top and side strips compared, as a fraction of the frame's width


@dataclass(frozen=True)
class Cuts:
    """The cuts of a clip.

    Attributes:
        changed: ``(N - 1,)`` fraction of the top and side strips that changed from frame ``k``
            to ``k + 1``.
        frames: Frames that begin a new shot (``k + 1`` for a cut between ``k`` and ``k + 1``),
            increasing.
    """

    changed: np.ndarray
    frames: list[int]

    def stretches(self, n: int) -> list[tuple[int, int]]:
        """The clean stretches ``[start, stop)`` of an ``n``-frame clip between the cuts."""
        edges = [0, *self.frames, n]
        return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def longest(self, n: int) -> tuple[int, int]:
        """The longest clean stretch ``[start, stop)`` (the first of equals)."""
        return max(self.stretches(n), key=lambda s: s[1] - s[0])


def _small(frame: np.ndarray) -> np.ndarray:
    h, w = frame.shape[:2]
    size = (WIDTH, max(1, round(h * WIDTH / w)))
    grey = cv2.cvtColor(cv2.resize(frame, size, interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(grey, (3, 3), 0).astype(np.float32)


def find_cuts(frames: np.ndarray) -> Cuts:
    """The cuts and reframings of a clip (see the module docstring).

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB (or any sequence of such frames).

    Returns:
        :class:`Cuts`.
    """
    n = len(frames)
    if n < 2:
        return Cuts(np.zeros(0), [])
    changed = np.empty(n - 1)
    prev = _small(frames[0])
    h, w = prev.shape
    band = np.zeros((h, w), bool)  # the top and side strips, where a talking head's background is
    b = max(1, round(BORDER * w))
    band[:b] = band[:, :b] = band[:, -b:] = True
    for k in range(1, n):
        cur = _small(frames[k])
        changed[k - 1] = float((np.abs(cur - prev)[band] > LEVEL).mean())
        prev = cur
    typical = float(np.median(changed))
    padded = np.concatenate([[0.0], changed, [0.0]])
    neighbours = np.maximum(padded[:-2], padded[2:])
    spike = (changed >= MIN_CHANGED) & (changed > SPIKE * typical) & (changed > SPIKE * neighbours)
    return Cuts(changed, [int(k) + 1 for k in np.flatnonzero(spike)])
