"""The background plate of a static camera: robust per-pixel median of the background, hole filled.

Every pixel of the plate is the median of its colour over the frames where parsing calls it
background (a margin around the person is excluded: edges are mixed colours). Pixels that were
never background (always behind the person) are filled from their surroundings by OpenCV
inpainting (Telea's fast marching method), and their fraction is reported.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np
import torch

__all__ = ["BackgroundPlate", "median_plate", "background_plate"]


@dataclass
class BackgroundPlate:
    """A background plate and how it was made.

    Attributes:
        image: ``(H, W, 3)`` uint8 RGB plate.
        seen: ``(H, W)`` number of frames each pixel was seen as background.
        filled_fraction: Fraction of pixels never seen and filled by inpainting.
    """

    image: np.ndarray
    seen: np.ndarray
    filled_fraction: float


def median_plate(frames: np.ndarray, person: np.ndarray, margin: int = 2, rows_per_chunk: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel median over the frames where the pixel is background.

    The median of an even number of values is the mean of the middle two, rounded half to even
    (as :func:`numpy.nanmedian` with the person masked out, then :func:`numpy.round`).

    It is exact and linear in the clip's length: each pixel's person frames are replaced by
    values outside the colour range, half below (-1) and half above (256), which leaves the
    median of the whole column at the median of its background values and puts it at one of
    three ranks that do not depend on the pixel; one partition of each column at those ranks
    finds it.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        person: ``(N, H, W)`` bool, True where the person (head or torso) is.
        margin: Pixels around the person also excluded.
        rows_per_chunk: Rows processed at a time (bounds the int16 copy to ``N * rows * W * 3``).

    Returns:
        ``(plate (H, W, 3) uint8 with zeros where never seen, count (H, W) int)``.
    """
    n, h, w, _ = frames.shape
    if margin > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        person = np.stack([cv2.dilate(p.astype(np.uint8), kernel) > 0 for p in person])
    count = n - person.sum(0)
    plate = np.zeros((h, w, 3), np.uint8)
    # With L = (n - c) // 2 of a column's n - c person frames below every colour and the rest
    # above, the middle of its c background values lies at ranks L + (c - 1) // 2 and L + c // 2:
    # (n - 1) // 2 - 1, (n - 1) // 2 or n // 2 whatever c is.
    ranks = sorted({(n - 1) // 2 - 1, (n - 1) // 2, n // 2} - {-1})
    for y0 in range(0, h, rows_per_chunk):
        rows = slice(y0, min(h, y0 + rows_per_chunk))
        # Frames last, so each column's partition runs over contiguous memory (torch's permute
        # copies a strided block several times faster than numpy's).
        block = _tensor(frames[:, rows]).permute(1, 2, 3, 0).to(torch.int16).contiguous().numpy()  # (r, W, 3, N)
        hidden = _tensor(person[:, rows]).permute(1, 2, 0).contiguous().numpy()  # (r, W, N)
        c = count[rows]
        below = (n - c) // 2
        fill = np.where(np.cumsum(hidden, axis=-1, dtype=np.int32) <= below[..., None], np.int16(-1), np.int16(256))
        block = np.where(hidden[:, :, None], fill[:, :, None], block)
        block.partition(ranks, axis=-1)
        middle = [np.take_along_axis(block, np.broadcast_to(k[..., None, None], block.shape[:3] + (1,)), -1)[..., 0] for k in (below + (c - 1) // 2, below + c // 2)]
        med = (middle[0].astype(np.float32) + middle[1]) / 2
        seen = c > 0
        plate[rows][seen] = np.round(med[seen]).astype(np.uint8)
    return plate, count


def _tensor(a: np.ndarray) -> torch.Tensor:
    """``a`` as a tensor sharing its memory, read-only arrays (the frames memory-mapped from the
    work folder) included: :func:`median_plate` only reads it (copies it, permuted), and torch
    warns of undefined behaviour on any read-only array it wraps."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
        return torch.from_numpy(a)


def background_plate(frames: np.ndarray, labels: np.ndarray, margin: int = 2, inpaint_radius: int = 5) -> BackgroundPlate:
    """The plate from frames and their parsing; never-seen pixels inpainted.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        labels: ``(N, H, W)`` uint8 parsing (0 is background).
        margin: Pixels around the person excluded from the median.
        inpaint_radius: Neighbourhood radius of the inpainting in pixels.

    Returns:
        A :class:`BackgroundPlate`.
    """
    plate, count = median_plate(frames, labels != 0, margin=margin)
    hole = count == 0
    if hole.all():
        raise ValueError("no pixel was ever background: the person covers the whole frame in every frame")
    if hole.any():
        plate = cv2.inpaint(plate, hole.astype(np.uint8), inpaint_radius, cv2.INPAINT_TELEA)
    return BackgroundPlate(image=plate, seen=count, filled_fraction=float(hole.mean()))
