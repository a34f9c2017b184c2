"""Peak signal-to-noise ratio, the one formula every PSNR in adnerf goes through.

``PSNR = 10 log10(peak^2 / MSE)`` decibels, with colours in ``[0, peak]``. Identical images
(MSE 0) report :data:`PSNR_CAP_DB`, a finite number JSON can carry, and no value exceeds it.
The training log, ``bench fields``, ``check-preprocess`` and ``evaluate`` all use it; the test
suite checks it against kornia's ``psnr`` and against images with a known noise level.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["PSNR_CAP_DB", "psnr_from_mse", "psnr"]

PSNR_CAP_DB = 100.0


def psnr_from_mse(mse: float, peak: float = 1.0) -> float:
    """PSNR in dB of a mean squared error ``mse`` of colours in ``[0, peak]``.

    Raises:
        ValueError: ``mse`` negative or not a number, or ``peak`` not positive.
    """
    mse = float(mse)
    if not mse >= 0.0 or not peak > 0.0:
        raise ValueError(f"PSNR needs a mean squared error >= 0 and a peak > 0; got {mse} and {peak}")
    if mse == 0.0:
        return PSNR_CAP_DB
    return min(PSNR_CAP_DB, 10.0 * math.log10(peak * peak / mse))


def psnr(pred: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor, peak: float | None = None) -> float:
    """PSNR in dB between two images (or any same-shape arrays); MSE in float64.

    Args:
        pred: Image, e.g. ``(H, W, 3)``.
        target: Image of the same shape.
        peak: The colour range's top; default 255 for uint8 arrays and 1 otherwise.
    """
    a = pred.detach().cpu().numpy() if isinstance(pred, torch.Tensor) else np.asarray(pred)
    b = target.detach().cpu().numpy() if isinstance(target, torch.Tensor) else np.asarray(target)
    if a.shape != b.shape:
        raise ValueError(f"PSNR of arrays of different shapes {a.shape} and {b.shape}")
    if peak is None:
        peak = 255.0 if a.dtype == np.uint8 and b.dtype == np.uint8 else 1.0
    return psnr_from_mse(float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)), peak)
