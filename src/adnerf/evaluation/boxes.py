"""The pixel boxes the metrics read: the square crop around the mouth and the squares around the
eyes, where the dataset's canonical points fall under a frame's head pose."""

from __future__ import annotations

import numpy as np

from ..formats.dataset import EYE_CROP, MOUTH_CROP, SceneMeta, TalkingHeadDataset
from ..pose import HeadPose

__all__ = ["eye_boxes_at", "mouth_boxes", "mouth_boxes_at"]


def mouth_boxes(ds: TalkingHeadDataset, frames: list[int], crop: float = MOUTH_CROP) -> np.ndarray:
    """Square pixel boxes ``(n, 4)`` as ``(x0, y0, x1, y1)`` (end exclusive) around the mouth of
    the dataset's frames ``frames`` (:func:`mouth_boxes_at` of their poses)."""
    return mouth_boxes_at(ds.meta, ds.head_pose(frames), crop)


def mouth_boxes_at(meta: SceneMeta, pose: HeadPose, crop: float = MOUTH_CROP) -> np.ndarray:
    """Square pixel boxes ``(n, 4)`` as ``(x0, y0, x1, y1)`` (end exclusive) around the mouth
    under head poses ``pose`` (batch ``(n,)``): :meth:`SceneMeta.mouth_boxes
    <adnerf.formats.dataset.SceneMeta.mouth_boxes>` (training's pose refit reads it there)."""
    return meta.mouth_boxes(pose, crop)


def eye_boxes_at(meta: SceneMeta, pose: HeadPose, crop: float = EYE_CROP) -> np.ndarray:
    """Square pixel boxes ``(2, 4)`` as ``(x0, y0, x1, y1)`` (end exclusive, clipped to the
    image, possibly empty) around both eyes under one head pose ``pose``: side ``crop`` scene
    units at each eye's depth, as the trainer's eye rays (:meth:`SceneMeta.eyes_in_image`).

    Raises:
        ValueError: The dataset has no eye points.
    """
    uv_t, depth = meta.eyes_in_image(pose)
    uv, depth = uv_t.numpy(), depth.numpy()
    half = 0.5 * crop * meta.intrinsics[0] / depth  # (2,)
    # Pixel j's centre is j + 0.5: the pixels whose centre lies within the square.
    lo = np.ceil(uv - half[:, None] - 0.5).astype(int)
    hi = np.floor(uv + half[:, None] - 0.5).astype(int) + 1
    lo = np.clip(lo, 0, [meta.width, meta.height])
    hi = np.clip(hi, lo, [meta.width, meta.height])
    return np.concatenate([lo, hi], axis=1)
