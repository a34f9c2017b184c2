"""The background plate of a static camera: robust per-pixel median of the background, hole filled.

Every pixel of the plate is the median of its colour over the frames where parsing calls it
background (a margin around the person is excluded: edges are mixed colours). Pixels that were
never background (always behind the person) are filled from their surroundings by OpenCV
inpainting (Telea's fast marching method), and their fraction is reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

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


def median_plate(frames: np.ndarray, person: np.ndarray, margin: int = 2, rows_per_chunk: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel median over the frames where the pixel is background.

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB.
        person: ``(N, H, W)`` bool, True where the person (head or torso) is.
        margin: Pixels around the person also excluded.
        rows_per_chunk: Rows processed at a time (bounds the float copy to ``N * rows * W * 3``).

    Returns:
        ``(plate (H, W, 3) uint8 with zeros where never seen, count (H, W) int)``.
    """
    n, h, w, _ = frames.shape
    if margin > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        person = np.stack([cv2.dilate(p.astype(np.uint8), kernel) > 0 for p in person])
    count = (~person).sum(0)
    plate = np.zeros((h, w, 3), np.uint8)
    for y0 in range(0, h, rows_per_chunk):
        rows = slice(y0, min(h, y0 + rows_per_chunk))
        block = frames[:, rows].astype(np.float32)
        block[person[:, rows]] = np.nan
        seen = count[rows] > 0
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: never seen, filled later
                med = np.nanmedian(block, axis=0)
        plate[rows][seen] = np.round(med[seen]).astype(np.uint8)
    return plate, count


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
