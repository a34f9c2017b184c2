"""How the torso moves in the image: each frame's affine map from a reference torso.

AD-NeRF's torso field reads the head pose and the audio code, and nothing in them says where the
shoulders are: a speaker's shoulders rise and fall with breath, shrug and sway, and on the 50 s
real clip their outline moves by about 2 px (256 px frames) from frame to frame about its mean.
A field that cannot tell where they are learns their average, a soft outline that misses every
frame's. The torso's own motion is measured here, as the head pose is measured, and the torso
layer follows it (:class:`adnerf.model.layers.RadianceLayer`'s ``warp``): its field learns the
reference torso and each frame's rays are moved to it.

The reference is the median picture of frames spread over the clip; the region compared is every
pixel the parsing calls torso in any of those frames, grown by a margin so that the outline's
background side is in, less every pixel it calls head in any of them (the head moves on its own).
Each frame is registered to the reference by OpenCV's enhanced correlation coefficient
(``findTransformECC``, an affine map, from the identity) on the grey picture, scaled down to at
most ``work_width`` pixels across (a 512 px frame costs four times a 256 px one, and five minutes
of footage would spend minutes on it). The maps use the camera's pixel convention: a pixel's
centre at ``+0.5`` (:mod:`adnerf.cameras`), in which a map measured on a picture scaled by ``s`` is
the full frame's with its shift scaled by ``1 / s`` (each axis by its own scale).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from ..formats.dataset import LABEL_HEAD, LABEL_TORSO
from ..threads import in_threads

__all__ = ["TorsoMotion", "torso_motion", "IDENTITY"]

IDENTITY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# A map further than this from the identity (linear part) or moving the frame's centre by more
# than this share of the frame's width is a failed registration, not a torso's motion.
MAX_LINEAR, MAX_SHIFT = 0.15, 0.15


@dataclass
class TorsoMotion:
    """The torso's motion over a clip.

    Attributes:
        maps: ``(N, 2, 3)`` float64: frame ``i``'s affine map ``x' = A x + b`` from the reference
            torso's pixels to its own (pixel centres at ``+0.5``).
        failed: Frames whose registration failed or was implausible: given their nearest good
            neighbour's map (the identity when none succeeded).
        region_px: Pixels of the region compared.
        centre: ``(2,)`` the region's centroid (pixels).
    """

    maps: np.ndarray
    failed: list[int]
    region_px: int
    centre: np.ndarray

    def report(self) -> dict:
        """What the preprocessing report says of it: the frames, the failures, and how far the
        torso moves (how far each frame's map moves the region's centroid, 50th / 95th
        percentile over the frames, in pixels)."""
        moved = self.maps[:, :, :2] @ self.centre + self.maps[:, :, 2]
        shift = np.linalg.norm(moved - self.centre, axis=-1)
        return {
            "frames": int(len(self.maps)),
            "failed": len(self.failed),
            "failed_frames": self.failed[:20],
            "region_px": self.region_px,
            "shift_px_p50": round(float(np.percentile(shift, 50)), 3),
            "shift_px_p95": round(float(np.percentile(shift, 95)), 3),
        }


def _grey(frame: np.ndarray, scale: float = 1.0) -> np.ndarray:
    grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY).astype(np.float32)
    if scale == 1.0:
        return grey
    return cv2.resize(grey, (round(grey.shape[1] * scale), round(grey.shape[0] * scale)), interpolation=cv2.INTER_AREA)


def _region(labels: np.ndarray, margin: int) -> np.ndarray:
    """Pixels called torso in any of ``labels`` ``(M, H, W)``, grown by ``margin``, less those
    called head in any: ``(H, W)`` uint8 (1 inside)."""
    torso = (labels == LABEL_TORSO).any(0).astype(np.uint8)
    region = cv2.dilate(torso, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8))
    region[(labels == LABEL_HEAD).any(0)] = 0
    return region


def _plausible(warp: np.ndarray, width: int) -> bool:
    linear = np.abs(warp[:, :2] - np.eye(2)).max()
    return bool(np.isfinite(warp).all() and linear <= MAX_LINEAR and np.abs(warp[:, 2]).max() <= MAX_SHIFT * width)


def torso_motion(
    frames: np.ndarray,
    labels: np.ndarray,
    *,
    references: int = 64,
    iterations: int = 50,
    work_width: int = 256,
    progress: Callable[[int, int], None] | None = None,
) -> TorsoMotion:
    """Each frame's affine map from the reference torso (see the module docstring).

    Args:
        frames: ``(N, H, W, 3)`` uint8 RGB (an array or a memory map).
        labels: ``(N, H, W)`` parsing (0 background, 1 head, 2 torso).
        references: Frames, spread over the clip, whose median is the reference and whose labels
            make the region.
        iterations: The most ECC iterations a frame.
        work_width: Frames wider than this are registered scaled down to it.
        progress: ``progress(done, total)`` after each frame, or ``None``.

    Returns:
        The :class:`TorsoMotion`; a clip without torso pixels gets identity maps, every frame
        counted as failed.

    Raises:
        ValueError: Frames and labels of different counts or sizes.
    """
    frames, labels = np.asarray(frames), np.asarray(labels)
    if frames.ndim != 4 or labels.shape != frames.shape[:3]:
        raise ValueError(f"frames (N, H, W, 3) and labels (N, H, W) must match; got {frames.shape} and {labels.shape}")
    n, h, w = labels.shape
    pick = np.unique(np.linspace(0, n - 1, min(references, n)).round().astype(int))
    full_region = _region(labels[pick], margin=max(2, round(0.02 * w)))
    if not full_region.any():
        return TorsoMotion(np.repeat(IDENTITY[None], n, 0), list(range(n)), 0, np.array([w / 2, h / 2]))
    scale = min(1.0, work_width / w)
    reference = np.median(np.stack([_grey(frames[i], scale) for i in pick]), axis=0).astype(np.float32)
    size = (reference.shape[1], reference.shape[0])
    region = full_region if scale == 1.0 else (cv2.resize(full_region.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5).astype(np.uint8)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, 1e-4)

    def register(i: int) -> np.ndarray | None:
        warp = np.eye(2, 3, dtype=np.float32)
        try:
            # No Gaussian prefilter (size 1): on exact moved pictures a 5-pixel one biased the maps
            # by up to 0.8 px, where none found them within 0.08 px.
            _, warp = cv2.findTransformECC(reference, _grey(frames[i], scale), warp, cv2.MOTION_AFFINE, criteria, region, 1)
        except cv2.error:
            return None
        return warp.astype(np.float64) if _plausible(warp, size[0]) else None

    found: list[np.ndarray | None] = []
    for i, warp in enumerate(in_threads(register, range(n))):
        found.append(warp)
        if progress is not None:
            progress(i + 1, n)
    good = np.array([m is not None for m in found])
    failed = [int(i) for i in np.nonzero(~good)[0]]
    maps = np.repeat(IDENTITY[None], n, 0)
    if good.any():
        ok = np.nonzero(good)[0]
        right = np.clip(np.searchsorted(ok, np.arange(n)), 0, len(ok) - 1)
        left = np.clip(right - 1, 0, len(ok) - 1)
        nearest = np.where(np.abs(ok[left] - np.arange(n)) <= np.abs(ok[right] - np.arange(n)), ok[left], ok[right])
        maps = np.stack([found[j] for j in nearest])  # type: ignore[misc]
    # OpenCV's pixel centres are at integers; the camera's at +0.5: x_c = x + 0.5 on both sides;
    # then from the scaled picture's pixels to the frame's.
    linear = maps[:, :, :2]
    maps[:, :, 2] += 0.5 * (1.0 - linear.sum(-1))
    if scale != 1.0:  # x_small = D x (D: each axis's scale), so x' = D^-1 A D x + D^-1 b
        d = np.array([size[0] / w, size[1] / h])
        maps = np.concatenate([maps[:, :, :2] * d[None, None, :] / d[None, :, None], maps[:, :, 2:] / d[None, :, None]], axis=2)
    rows, cols = np.nonzero(full_region)
    return TorsoMotion(maps, failed, int(full_region.sum()), np.array([cols.mean() + 0.5, rows.mean() + 0.5]))
