"""Frames on a constant clock: variable-frame-rate footage (phones, webcams) placed on a regular grid.

Phones and webcams write variable frame rate: the gap between frames follows the exposure and
the encoder's load, and frames go missing under load. A dataset, its audio windows and the
rendered video assume one frame every ``1 / fps`` seconds, so preprocessing places the decoded
frames on the grid ``t_k = t_0 + k / fps`` (``k = 0 .. K``): slot ``k`` shows the frame on screen
nearest to ``t_k``. Where the footage skipped a frame, a slot repeats its neighbour
(*duplicated*); where two frames fall in one slot, one is left out (*dropped*). Constant-rate
footage maps onto the grid one to one.

The grid's rate is the clip's nominal rate: the container's average rate, snapped to the standard
rate within 3 % of it (a phone's "30 fps" clip averages 29.4-30.1), or the rate a user gives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FrameGrid", "STANDARD_RATES", "nominal_rate", "regular_grid"]

STANDARD_RATES = (24000 / 1001, 24.0, 25.0, 30000 / 1001, 30.0, 48.0, 50.0, 60000 / 1001, 60.0, 120.0)
"""Frame rates a camera's nominal rate is snapped to (frames per second)."""


@dataclass(frozen=True)
class FrameGrid:
    """Where each slot of a constant-rate grid takes its frame from.

    Attributes:
        index: Source frame shown in each slot, int64, shape ``(K,)``, non-decreasing.
        times: Slot times in seconds from the first frame, float64, shape ``(K,)``: ``k / fps``.
        fps: The grid's rate in frames per second.
        duplicated: Slots that repeat the previous slot's frame.
        dropped: Source frames no slot shows.
    """

    index: np.ndarray
    times: np.ndarray
    fps: float
    duplicated: int
    dropped: int

    @property
    def identity(self) -> bool:
        """The grid shows every source frame once, in order (constant-rate footage)."""
        return self.duplicated == 0 and self.dropped == 0


def nominal_rate(timestamps: np.ndarray, average_rate: float | None) -> float:
    """The clip's nominal frame rate.

    Args:
        timestamps: Presentation times of the decoded frames in seconds, shape ``(N,)``, sorted.
        average_rate: The container's average rate (frames per second), or ``None`` / 0 when it
            gives none; then the median frame gap decides.

    Returns:
        The standard rate within 3 % of the measured one, or the measured one.
    """
    rate = float(average_rate or 0.0)
    if not rate > 0 and len(timestamps) > 1:
        rate = 1.0 / float(np.median(np.diff(timestamps)))
    if not rate > 0:
        return 25.0
    best = min(STANDARD_RATES, key=lambda r: abs(r - rate))
    return best if abs(best - rate) <= 0.03 * rate else rate


def regular_grid(timestamps: np.ndarray, fps: float) -> FrameGrid:
    """Place frames with the given presentation times on a grid of ``fps`` frames a second.

    Args:
        timestamps: Presentation times in seconds, shape ``(N,)``, ``N >= 1``, sorted.
        fps: The grid's rate, > 0.

    Returns:
        The :class:`FrameGrid`; the grid spans the first frame's time to the last one's.

    Raises:
        ValueError: ``timestamps`` is empty or unsorted, or ``fps`` is not a positive number.
    """
    t = np.asarray(timestamps, dtype=np.float64)
    if t.ndim != 1 or len(t) == 0 or not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise ValueError("timestamps must be a non-empty sorted 1-D array of finite seconds")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"the frame rate must be a positive number; got {fps}")
    t = t - t[0]
    slots = int(np.floor(t[-1] * fps + 0.5)) + 1
    times = np.arange(slots, dtype=np.float64) / fps
    # The nearest frame to each slot time (ties to the earlier frame).
    right = np.clip(np.searchsorted(t, times, side="left"), 0, len(t) - 1)
    left = np.clip(right - 1, 0, len(t) - 1)
    index = np.where(np.abs(t[left] - times) <= np.abs(t[right] - times), left, right).astype(np.int64)
    shown = np.unique(index)
    return FrameGrid(index=index, times=times, fps=float(fps), duplicated=int(slots - len(shown)), dropped=int(len(t) - len(shown)))
