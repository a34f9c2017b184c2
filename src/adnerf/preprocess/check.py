"""``adnerf check-preprocess``: a preprocessed synthetic video against the scene's exact truth.

* **Poses**: estimated and true poses share the camera but not the canonical frame nor the scale,
  so they are compared after the best similarity: a canonical rotation ``G``, offset ``g`` and
  scale ``s`` with ``R_true ~ R_est G`` and ``s t_true ~ R_est g + t_est`` (:func:`align_poses`).
  Rotation error is the angle of ``R_est G R_true^T``; translation error is the distance of the
  aligned translation from the true one, in units of the true head width.
* **Parsing**: intersection over union per class (background, head, torso), averaged over frames.
* **Plate**: PSNR against the true background on pixels the video ever shows as background.
* **Mouth point**: where the dataset's canonical mouth point appears under the estimated poses,
  against where the true mouth point appears under the true poses, in pixels (the mouth crop of
  training and evaluation is centred there); the same for the two eye points (where heads that
  blink draw their eye rays).
* **Eye openness**: the correlation of the dataset's eye openness (from the landmarks' eye aspect
  ratio) with the true one, over all frames.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..ridge import pearson
from ..metrics import psnr
from ..formats.dataset import load_dataset
from .headpose import align_poses, project_points
from .parsing import layer_check, torso_check
from .pipeline import LIP_IN_HEAD_MIN, MIDPOINT_IN_HEAD_MIN, PERSON_AT_BOTTOM_MIN

__all__ = ["align_poses", "parsing_iou", "check_preprocess", "BARS"]

BARS = {
    "rotation_median_deg": 1.0,
    "translation_median_head_widths": 0.02,
    "iou_mean": 0.90,
    "plate_psnr_seen": 30.0,
    "layers_lip_in_head": LIP_IN_HEAD_MIN,
    "layers_chin_lip_midpoint_in_head": MIDPOINT_IN_HEAD_MIN,
    "torso_person_at_bottom": PERSON_AT_BOTTOM_MIN,
}
TRUE_HEAD_WIDTH = 1.6  # the synthetic head's width in its scene units


def parsing_iou(pred: np.ndarray, true: np.ndarray, classes: tuple[int, ...] = (0, 1, 2)) -> dict[int, float]:
    """Mean over frames of the intersection over union of each class (frames where a class is
    absent from both maps are skipped for that class)."""
    out = {}
    for c in classes:
        a, b = pred == c, true == c
        inter = (a & b).sum((1, 2))
        union = (a | b).sum((1, 2))
        valid = union > 0
        out[c] = float((inter[valid] / union[valid]).mean()) if valid.any() else float("nan")
    return out


def _canonical_pixels(point: tuple[float, float, float], poses: np.ndarray, K: tuple[float, float, float, float]) -> np.ndarray:
    """``(N, 2)`` pixel positions of the canonical point ``point`` (the mouth's, an eye's) under ``poses``."""
    return project_points(poses[:, :3, :3] @ np.asarray(point, dtype=np.float64) + poses[:, :3, 3], K)


def check_preprocess(dataset: str | Path, truth: str | Path) -> dict:
    """Compare a preprocessed dataset with a synthetic scene's truth; see the module docstring.

    Args:
        dataset: Folder written by ``adnerf preprocess`` from the synthetic scene's ``video.mp4``.
        truth: The synthetic scene's folder (with ``truth/``).

    Returns:
        A dict of figures, the bars, and ``passed`` per bar.

    Raises:
        adnerf.formats.dataset.DatasetError: A folder is not a dataset, the truth folder has no ``truth/``, or
            the two have different frame counts or sizes.
    """
    from ..formats.dataset import DatasetError

    est = load_dataset(dataset, truth=False)
    ref = load_dataset(truth)
    if ref.truth is None:
        raise DatasetError(f"{truth}: has no truth/ folder (use the folder adnerf synth wrote)")
    if est.frames.shape != ref.frames.shape:
        raise DatasetError(f"{dataset}: frames {tuple(est.frames.shape)} do not match the truth's {tuple(ref.frames.shape)}")
    rot, trans, sim = align_poses(est.poses, ref.truth.poses)
    iou = parsing_iou(est.parsing, ref.truth.parsing)
    seen = (ref.truth.parsing == 0).any(0)
    plate_psnr = psnr(est.background[seen], ref.background[seen])
    mouth_err = np.linalg.norm(_canonical_pixels(est.meta.mouth, est.poses, est.meta.intrinsics) - _canonical_pixels(ref.meta.mouth, ref.truth.poses, ref.meta.intrinsics), axis=1)
    out = {
        "frames": int(len(est.poses)),
        "rotation_median_deg": float(np.median(rot)),
        "rotation_max_deg": float(rot.max()),
        "translation_median_head_widths": float(np.median(trans) / TRUE_HEAD_WIDTH),
        "translation_max_head_widths": float(trans.max() / TRUE_HEAD_WIDTH),
        "scale": sim["scale"],
        "iou_background": iou[0],
        "iou_head": iou[1],
        "iou_torso": iou[2],
        "iou_mean": float(np.mean(list(iou.values()))),
        "plate_psnr_seen": plate_psnr,
        "plate_psnr_all": psnr(est.background, ref.background),
        "mouth_error_median_px": float(np.median(mouth_err)),
        "mouth_error_max_px": float(mouth_err.max()),
        "bars": BARS,
    }
    if est.meta.eyes is not None and ref.meta.eyes is not None:  # the eye points, as the mouth's
        eye_err = np.concatenate([
            np.linalg.norm(_canonical_pixels(e, est.poses, est.meta.intrinsics) - _canonical_pixels(r, ref.truth.poses, ref.meta.intrinsics), axis=1)
            for e, r in zip(est.meta.eyes, ref.meta.eyes)
        ])  # fmt: skip
        out["eye_error_median_px"] = float(np.median(eye_err))
    if est.eye is not None and ref.truth.eye is not None:
        out["eye_openness_corr"] = pearson(est.eye, ref.truth.eye)
    if est.landmarks is not None:  # the mouth in the head layer: in the written parsing and in the truth's
        landmarks = est.landmarks
        out.update({f"layers_{k}": v for k, v in layer_check(est.parsing, landmarks).items()})
        out.update({f"layers_truth_{k}": v for k, v in layer_check(ref.truth.parsing, landmarks).items()})
        # the clothes in the person: the bottom edge under the face, in the written parsing and the truth's
        out.update({f"torso_{k}": v for k, v in torso_check(est.parsing, landmarks).items()})
        out.update({f"torso_truth_{k}": v for k, v in torso_check(ref.truth.parsing, landmarks).items()})
    out["passed"] = {
        "rotation": out["rotation_median_deg"] <= BARS["rotation_median_deg"],
        "translation": out["translation_median_head_widths"] <= BARS["translation_median_head_widths"],
        "parsing": out["iou_mean"] >= BARS["iou_mean"],
        "plate": out["plate_psnr_seen"] >= BARS["plate_psnr_seen"],
    }
    if "layers_lip_in_head" in out:
        out["passed"]["layers"] = out["layers_lip_in_head"] >= BARS["layers_lip_in_head"] and out["layers_chin_lip_midpoint_in_head"] >= BARS["layers_chin_lip_midpoint_in_head"]
    if out.get("torso_person_at_bottom") is not None:
        out["passed"]["torso"] = out["torso_person_at_bottom"] >= BARS["torso_person_at_bottom"]
    return out
