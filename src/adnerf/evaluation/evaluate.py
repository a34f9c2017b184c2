"""Image metrics of a trained run against a dataset's held-out frames.

* PSNR and SSIM (kornia) on full frames, on the head (PSNR over the true frame's head-label
  pixels, SSIM on the head label's box) and on a square crop around the mouth (the canonical mouth
  point of the dataset projected with each frame's pose; side ``mouth_crop`` scene units).
* PSNR over the eyes (``psnr_eyes``; datasets with eye points): the pixels of two squares of side
  ``EYE_CROP`` scene units around the canonical eye points projected with each frame's pose, the
  squares stage 1 draws its eye rays from. The head reads the eyes' openness but not the gaze or
  the brows, so the eyes are a region to watch beside the mouth.
* With ``landmarks``: LMD, the inner-lip opening's correlation between render and truth and the
  audio-visual offset (:mod:`adnerf.evaluation.landmark_metrics`), from the dlib landmarks of both.
* With an :class:`~adnerf.evaluation.lpips.LPIPS` model: LPIPS on full frames.
* With a :class:`~adnerf.evaluation.syncnet.SyncNet` model: LSE-D, LSE-C and SyncNet's offset of the renders
  against the dataset's audio, and the same scores of the true frames (``*_true``), the value a
  perfect render would get (:func:`syncnet_evaluation`).
* The mouth opening seen in an image: the mean darkness of the mouth crop (luminance 0.5 and
  above counts 0, 0.1 and below counts 1; the open mouth's interior is dark, lips and skin are not). On synthetic data, the Pearson
  correlation over the test frames between this measure on the renders and the true jaw opening
  (``mouth_open_corr``); the same measure on the ground-truth frames is reported as
  ``mouth_open_corr_gt``, the ceiling the measure itself allows.
"""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch
from kornia.metrics import ssim

from ..model.render_clip import RenderedClip, frame_signals, render_frames
from ..metrics import psnr
from ..formats.dataset import LABEL_HEAD, DatasetError, TalkingHeadDataset
from ..model.run_folder import Run
from .boxes import eye_boxes_at, mouth_boxes, mouth_boxes_at  # re-exported: the crops the metrics read
from .fitted_poses import judged_poses
from .landmark_metrics import pearson

if TYPE_CHECKING:
    from ..preprocess.landmarks import FaceTrack
    from .lpips import LPIPS
    from .syncnet import SyncNet

__all__ = ["mouth_darkness", "evaluate_clip", "evaluate_run", "eye_boxes_at", "eye_psnr", "head_metrics", "image_metrics", "landmark_evaluation", "mouth_boxes", "mouth_boxes_at", "syncnet_evaluation"]



def eye_psnr(pred: np.ndarray, target: np.ndarray, boxes: np.ndarray) -> float | None:
    """PSNR over the pixels of each frame's eye boxes (their union), the mean over the frames
    where they hold a pixel (``None`` when none does); frames ``(n, H, W, 3)`` uint8, boxes
    ``(n, 2, 4)`` (:func:`eye_boxes_at`)."""
    values = []
    for p, t, frame_boxes in zip(pred, target, boxes):
        inside = np.zeros(p.shape[:2], dtype=bool)
        for x0, y0, x1, y1 in frame_boxes:
            inside[y0:y1, x0:x1] = True
        if inside.any():
            values.append(psnr(p[inside], t[inside]))
    return float(np.mean(values)) if values else None


def mouth_darkness(crop: np.ndarray, light: float = 0.5, dark: float = 0.1) -> float:
    """Mean darkness of an RGB crop (uint8 or float in [0, 1]): per pixel, 0 at luminance ``light``
    or above (lips, skin), 1 at ``dark`` or below (the open mouth's interior), linear between, so
    that a slightly blurred mouth still counts in proportion."""
    x = crop.astype(np.float64) / (255.0 if crop.dtype == np.uint8 else 1.0)
    lum = x @ np.array([0.299, 0.587, 0.114])
    return float(np.clip((light - lum) / (light - dark), 0.0, 1.0).mean())


def _to_tensor(frames: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(frames).permute(0, 3, 1, 2).float() / 255.0


def image_metrics(pred: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """Mean PSNR (dB) and SSIM (11-pixel window) over frames ``(n, H, W, 3)`` uint8."""
    p, t = _to_tensor(pred), _to_tensor(target)
    per_frame = [psnr(pred[i], target[i]) for i in range(len(pred))]
    window = min(11, p.shape[-1] // 2 * 2 - 1, p.shape[-2] // 2 * 2 - 1)
    s = float(ssim(p, t, window).mean())
    return float(np.mean(per_frame)), s


def crops(frames: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    return np.stack([f[y0:y1, x0:x1] for f, (x0, y0, x1, y1) in zip(frames, boxes)])


def head_metrics(pred: np.ndarray, target: np.ndarray, labels: np.ndarray) -> tuple[float | None, float | None]:
    """PSNR over the head-label pixels and SSIM on the head label's box, means over the frames
    that have a head (``None`` when none has); frames ``(n, H, W, 3)`` uint8, labels ``(n, H, W)``."""
    psnrs, ssims = [], []
    for p, t, lab in zip(pred, target, labels):
        head = lab == LABEL_HEAD
        if not head.any():
            continue
        psnrs.append(psnr(p[head], t[head]))
        ys, xs = np.nonzero(head)
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        if min(y1 - y0, x1 - x0) >= 7:
            ssims.append(image_metrics(p[None, y0:y1, x0:x1], t[None, y0:y1, x0:x1])[1])
    return (float(np.mean(psnrs)) if psnrs else None, float(np.mean(ssims)) if ssims else None)


def true_faces(ds: TalkingHeadDataset, frames: list[int]) -> "FaceTrack":
    """dlib's faces in the dataset's frames ``frames`` (searched around the true head label)."""
    from ..preprocess.landmarks import DlibFaceDetector, track_faces

    return track_faces(ds.frames[frames], DlibFaceDetector(), ds.parsing[frames])


def landmark_evaluation(ds: TalkingHeadDataset, frames: list[int], rendered: np.ndarray, true: "FaceTrack | None" = None) -> dict:
    """Landmark metrics (:func:`adnerf.evaluation.landmark_metrics.landmark_metrics`) of rendered frames,
    from dlib's landmarks on them and on the true frames (:func:`true_faces`, or ``true`` when
    already found). Frames where the detector misses a face take interpolated landmarks; their
    counts are reported, and with a face in fewer than half of the frames the metrics are ``None``."""
    from ..preprocess.landmarks import DlibFaceDetector, track_faces
    from .landmark_metrics import landmark_metrics, mouth_opening

    true = true if true is not None else true_faces(ds, frames)
    pred = track_faces(rendered, DlibFaceDetector(), ds.parsing[frames])
    out: dict = {"landmarks_found_true": int(true.detected.sum()), "landmarks_found_render": int(pred.detected.sum())}
    if min(out["landmarks_found_true"], out["landmarks_found_render"]) < 0.5 * len(frames):
        return out
    series = {"mouth_opening_true_px": mouth_opening(true.landmarks).round(2).tolist(), "mouth_opening_render_px": mouth_opening(pred.landmarks).round(2).tolist()}
    return {**out, **landmark_metrics(pred.landmarks, true.landmarks).as_dict(), **series}


def syncnet_evaluation(ds: TalkingHeadDataset, frames: list[int], rendered: np.ndarray, model: "SyncNet", true: "FaceTrack | None" = None) -> dict:
    """SyncNet's scores (:func:`adnerf.evaluation.syncnet.sync_scores`) of rendered frames and of the true
    ones, against the dataset's audio under them.

    Both are cropped around the same smoothed dlib face boxes of the true frames (``true``, or
    :func:`true_faces`), so the two scores differ only by what the render changed.

    Returns:
        ``lse_d``, ``lse_c``, ``syncnet_offset_frames``, ``syncnet_windows``, ``syncnet_curve``
        of the renders and ``lse_d_true``, ``lse_c_true``, ``syncnet_offset_frames_true`` of the
        true frames; or ``{"syncnet": reason}`` when the clip cannot be scored (not 25 frames per
        second, frames not consecutive, no face found).
    """
    from ..audio.features import resample
    from .syncnet import SAMPLE_RATE, SYNCNET_FPS, face_crops, sync_scores

    if abs(ds.meta.fps - SYNCNET_FPS) > 1e-6:
        return {"syncnet": f"needs 25 frames per second (the dataset has {ds.meta.fps:g})"}
    if np.any(np.diff(frames) != 1):
        return {"syncnet": "needs consecutive frames"}
    track = true if true is not None else true_faces(ds, frames)
    if not track.detected.any():
        return {"syncnet": "no face found in the true frames"}
    samples = resample(ds.audio_of(frames[0], frames[-1] + 1), SAMPLE_RATE)
    out = sync_scores(model, face_crops(rendered, track.boxes), samples).as_dict()
    true = sync_scores(model, face_crops(ds.frames[frames], track.boxes), samples)
    return {**out, "lse_d_true": true.lse_d, "lse_c_true": true.lse_c, "syncnet_offset_frames_true": true.offset_frames}


def evaluate_clip(ds: TalkingHeadDataset, frames: list[int], clip: RenderedClip, *, landmarks: bool = False, lpips: "LPIPS | None" = None, syncnet: "SyncNet | None" = None) -> dict:
    """Metrics of rendered frames against the dataset's frames ``frames`` (in the same order).

    Args:
        ds: The dataset.
        frames: Its frame indices that ``clip`` renders.
        clip: The rendered frames.
        landmarks: Also the landmark metrics (dlib on renders and truth).
        lpips: Also LPIPS with this model (:func:`adnerf.evaluation.lpips.load_lpips`).
        syncnet: Also SyncNet's LSE-D / LSE-C with this model (:func:`syncnet_evaluation`).
    """
    gt = ds.frames[frames]
    full_psnr, full_ssim = image_metrics(clip.frames, gt)
    boxes = mouth_boxes(ds, frames)
    pred_mouth, gt_mouth = crops(clip.frames, boxes), crops(gt, boxes)
    mouth_psnr, mouth_ssim = image_metrics(pred_mouth, gt_mouth)
    out = {
        "frames": len(frames),
        "psnr": full_psnr,
        "ssim": full_ssim,
        "psnr_mouth": mouth_psnr,
        "ssim_mouth": mouth_ssim,
        "render_fps": len(frames) / max(clip.seconds, 1e-9),
    }
    out["psnr_head"], out["ssim_head"] = head_metrics(clip.frames, gt, ds.parsing[frames])
    if ds.meta.eyes is not None:
        eyes = np.stack([eye_boxes_at(ds.meta, ds.head_pose(frame)) for frame in frames])
        out["psnr_eyes"] = eye_psnr(clip.frames, gt, eyes)
    true = true_faces(ds, frames) if landmarks or syncnet is not None else None  # found once for both
    if landmarks:
        out.update(landmark_evaluation(ds, frames, clip.frames, true))
    if lpips is not None:
        device = next(lpips.buffers()).device
        out["lpips"] = float(np.mean([float(lpips(_to_tensor(clip.frames[i : i + 1]).to(device), _to_tensor(gt[i : i + 1]).to(device))[0]) for i in range(len(frames))]))
    if syncnet is not None:
        out.update({"syncnet": "scored", **syncnet_evaluation(ds, frames, clip.frames, syncnet, true)})  # or the reason it could not be
    else:
        out["syncnet"] = "no weights"
    if ds.truth is not None:
        jaw = ds.truth.jaw[frames]
        rendered = [mouth_darkness(c) for c in pred_mouth]
        truth_seen = [mouth_darkness(c) for c in gt_mouth]
        out["mouth_open_corr"] = pearson(rendered, jaw)
        out["mouth_open_corr_gt"] = pearson(truth_seen, jaw)
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in out.items()}


# What a dataset must share with a run's training data to be evaluated against it.
_SAME_SCENE = ("width", "height", "intrinsics", "fps", "feature_kind", "feature_dim")


def check_matches_run(run: Run, ds: TalkingHeadDataset) -> None:
    """Raise :class:`~adnerf.formats.dataset.DatasetError` unless ``ds`` has the camera (size, intrinsics),
    frame rate and audio features the run was trained with."""
    found = {k: getattr(ds.meta, k) for k in _SAME_SCENE}
    differ = [f"{k} {run.meta[k]!r} vs {found[k]!r}" for k in _SAME_SCENE if json.loads(json.dumps(found[k])) != run.meta.get(k)]
    if differ:
        raise DatasetError(f"{ds.root} does not match the run's training data ({'; '.join(differ)}); evaluate a run on a dataset of its own camera, frame rate and features")


def evaluate_run(
    run: Run,
    ds: TalkingHeadDataset,
    split: str = "test",
    *,
    landmarks: bool = False,
    lpips: "LPIPS | None" = None,
    syncnet: "SyncNet | None" = None,
    backgrounds: Sequence[np.ndarray] = (),
    keep: Sequence[str] = (),
    poses: str = "fitted",
    progress: bool = False,
) -> tuple[dict, RenderedClip]:
    """Render a split with its own head poses and audio windows and measure it (see the module
    docs; ``landmarks``, ``lpips`` and ``syncnet`` as in :func:`evaluate_clip`; ``backgrounds``: the
    frames are also composited over these, and ``keep``: these layers are kept, as
    :func:`~adnerf.model.render_clip.render_frames` does; ``poses``: the tracked poses or those
    fitted to the frames, :func:`~adnerf.evaluation.fitted_poses.judged_poses`, named in the
    metrics' ``poses``: ``"exact"`` for a synthetic scene's; ``progress``: the pose fit's progress bar).

    Raises:
        DatasetError: ``ds`` has another camera, frame rate or feature kind than the run's data.
    """
    if split not in ("train", "test"):
        raise ValueError(f"split must be train or test; got {split!r}")
    check_matches_run(run, ds)
    frames = list(getattr(ds.meta, split))
    if not frames:
        raise ValueError(f"the dataset's {split} split is empty")
    plate = ds.background.astype(np.float32) / 255.0
    eye = ds.eye[frames] if ds.eye is not None and run.model.reads_eye else None  # the dataset's own blinks
    # The frames' own signals, as their own poses: the torso's motion measured in them.
    signals = frame_signals(run, ds, frames)
    judged = judged_poses(run, ds, frames, poses, progress=progress)
    clip = render_frames(run, ds.features[frames], judged, plate, eye=eye, backgrounds=backgrounds, keep=keep, signals=signals)
    metrics = evaluate_clip(ds, frames, clip, landmarks=landmarks, lpips=lpips, syncnet=syncnet)
    metrics["split"], metrics["poses"] = split, "exact" if ds.truth is not None else poses
    return metrics, clip
