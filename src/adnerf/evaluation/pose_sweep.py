"""How rendering holds up as the head is turned away from the poses the run was taught.

An edited pose has no true frame to compare with, so the sweep measures what stays comparable
between a frame rendered with its own pose and the same frame (same audio code) with its head
turned by a yaw ``y`` about the head centre (:func:`adnerf.pose.perturb_pose`):

- ``identity_px``: the face's geometry. dlib's landmarks on the un-edited render (brows, nose,
  eyes and mouth, 17-67: the jaw line is a silhouette, not a point on the head) are lifted to 3D
  with the head layer's depth at them, turned with the head and projected; the mean distance in
  pixels to dlib's landmarks on the edited render. A field that draws the same face turned rigidly
  scores the detector's noise; one that smears or doubles features scores more.
- ``sharpness``: the variance of the Laplacian over the face's box on the edited render over that
  on the un-edited one (below 1: the face softened).
- ``neck_gap``: the share of the neck band (under the chin, between the jaw's landmarks 4 and 12)
  where neither layer is opaque (person opacity below 0.5): the plate shows through the neck.
- ``torso_change``: the mean absolute change (0-255) of the torso, where the torso layer is opaque
  and the head layer clear in both renders; turning the head should leave the shoulders as they
  were, and a torso that reads a pose it never saw changes there.

:func:`pose_sweep` renders held-out frames at each yaw and returns the rows and the renders;
:func:`sweep_sheet` draws them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
import torch

from ..cameras import Camera
from ..formats.dataset import LABEL_HEAD, TalkingHeadDataset
from ..model.pose_range import torso_reads
from ..model.render_clip import frame_signals
from ..model.run_folder import Run
from ..model.talking_head import render_frame
from ..pose import HeadPose

__all__ = ["SWEEP_YAWS", "pose_sweep", "spread", "sweep_sheet"]

SWEEP_YAWS = (0.0, 5.0, 10.0, 15.0, 20.0)
"""The yaw edits of the sweep, degrees."""

_FACE = np.arange(17, 68)  # brows, nose, eyes, mouth: points on the head (the jaw line 0-16 is a silhouette)


def _landmarks(image: np.ndarray, head_opacity: np.ndarray) -> np.ndarray | None:
    """dlib's 68 landmarks ``(68, 2)`` on one render, searched around its head layer (``None``: no face)."""
    from ..preprocess.landmarks import DlibFaceDetector, FaceTrackConfig, track_faces  # dlib's model loads on first use

    labels = np.where(head_opacity > 0.5, LABEL_HEAD, 0).astype(np.uint8)
    track = track_faces(image[None], DlibFaceDetector(), labels[None], FaceTrackConfig(smooth_sigma=0.0))
    return track.landmarks[0] if track.detected[0] else None


def _lifted(camera: Camera, landmarks: np.ndarray, depth: np.ndarray, opacity: np.ndarray, pose: HeadPose) -> tuple[np.ndarray, np.ndarray]:
    """The face landmarks as canonical points ``(K, 3)`` (with the indices ``(K,)`` kept: those on
    the opaque head), from their pixels and the head layer's depth along the unit pixel ray."""
    h, w = depth.shape
    pix = np.floor(landmarks[_FACE]).astype(np.int64)  # (column, row) of each landmark's pixel
    on = (pix[:, 0] >= 0) & (pix[:, 0] < w) & (pix[:, 1] >= 0) & (pix[:, 1] < h)
    on[on] = opacity[pix[on, 1], pix[on, 0]] >= 0.5
    kept, pix = _FACE[on], pix[on]
    rays = camera.rays_at(torch.as_tensor(landmarks[kept], dtype=torch.float64))
    cam = rays.origins + torch.as_tensor(depth[pix[:, 1], pix[:, 0]], dtype=torch.float64)[:, None] * rays.directions
    return pose.to_canonical(cam).numpy(), kept


def _project(camera: Camera, points: np.ndarray, pose: HeadPose) -> np.ndarray:
    """Pixels ``(K, 2)`` of canonical points ``(K, 3)`` under ``pose``."""
    return camera.project(pose.from_canonical(torch.as_tensor(points))).numpy()


def _box(points: np.ndarray, h: int, w: int, grow: float = 0.15) -> tuple[int, int, int, int]:
    (x0, y0), (x1, y1) = points.min(0), points.max(0)
    gx, gy = grow * (x1 - x0), grow * (y1 - y0)
    return max(0, int(x0 - gx)), max(0, int(y0 - gy)), min(w, int(math.ceil(x1 + gx))), min(h, int(math.ceil(y1 + gy)))


def _sharpness(image: np.ndarray, box: tuple[int, int, int, int]) -> float:
    x0, y0, x1, y1 = box
    grey = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_RGB2GRAY).astype(np.float64)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _neck_band(landmarks: np.ndarray, h: int, w: int) -> tuple[int, int, int, int]:
    """Under the chin (landmark 8) for a quarter of the face's height, between the jaw's landmarks 4 and 12."""
    face_h = landmarks[8, 1] - landmarks[19, 1]
    y0 = int(math.ceil(landmarks[8, 1]))
    return max(0, int(landmarks[4, 0])), min(h, y0), min(w, int(math.ceil(landmarks[12, 0]))), min(h, y0 + max(2, int(0.25 * face_h)))


def spread(frames: Sequence[int], count: int) -> list[int]:
    """``count`` of ``frames`` spread evenly from the first to the last (all of them when fewer)."""
    frames = list(frames)
    return [frames[k] for k in np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)] if frames else []


def pose_sweep(
    run: Run,
    ds: TalkingHeadDataset,
    frames: Sequence[int],
    yaws: Sequence[float] = SWEEP_YAWS,
    torso_pose: str = "track",
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[dict], np.ndarray]:
    """Render ``frames`` of ``ds`` at each yaw edit and measure them against the un-edited render.

    Args:
        run: A trained run (both stages for the neck and torso figures).
        ds: Its dataset (poses, audio windows, plate).
        frames: The frames to render (held-out ones: the sweep is of a run's generalisation).
        yaws: Degrees; the first should be 0 (the reference of every figure).
        torso_pose: What the torso reads under the edit (:func:`~adnerf.model.pose_range.torso_reads`).
        progress: Called as ``progress(done, total)`` over the renders.

    Returns:
        ``(rows, renders)``: a dict per yaw (``yaw``, ``yaw_past_range``: degrees past the taught
        yaw range at the frames' mean yaw, the means over frames of the figures in the module
        docs, and ``faces_found``), and the renders ``(len(frames), len(yaws), H, W, 3)`` uint8.

    Raises:
        ValueError: No frames, or ``yaws`` does not start at 0.
    """
    if not len(frames):
        raise ValueError("the sweep needs at least one frame")
    if not yaws or yaws[0] != 0.0:
        raise ValueError(f"the sweep's first yaw is its reference and must be 0; got {list(yaws)}")
    model = run.model
    dev = next(model.parameters()).device
    camera = ds.meta.camera(device=dev)
    plate = torch.as_tensor(ds.background, dtype=torch.float32, device=dev) / 255.0
    with torch.no_grad():
        codes = model.frame_codes(torch.as_tensor(ds.features, device=dev), list(frames))
    h, w = ds.meta.height, ds.meta.width
    signals = frame_signals(run, ds, frames)  # the torso's motion in each frame, as its evaluation
    renders = np.empty((len(frames), len(yaws), h, w, 3), np.uint8)
    per: dict[str, list[list[float]]] = {k: [[] for _ in yaws] for k in ("identity_px", "sharpness", "neck_gap", "torso_change")}
    found = [0] * len(yaws)
    total, done = len(frames) * len(yaws), 0
    for f, frame in enumerate(frames):
        base = ds.head_pose(frame, device=dev)
        eye = None if ds.eye is None or not model.reads_eye else float(ds.eye[frame])
        ref = None
        for y, yaw in enumerate(yaws):
            pose = base.perturbed(yaw=math.radians(yaw))
            reads = torso_reads(torso_pose, base.matrix()[None].cpu().numpy(), pose.matrix()[None].cpu().numpy(), run.pose_range)
            read = None if reads is None else HeadPose.from_matrix(torch.as_tensor(reads[0], device=dev))
            mine = {name: values[f] for name, values in signals.items()}
            out = render_frame(model, camera, pose, codes[f], plate, eye=eye, layers=run.trained_layers, amp=run.train_config.amp, read_pose=read, signals=mine)
            rgb = np.round(out.rgb.cpu().numpy() * 255.0).astype(np.uint8)
            head_a, torso_a = out.head_opacity.cpu().numpy(), out.torso_opacity.cpu().numpy()
            renders[f, y] = rgb
            lm = _landmarks(rgb, head_a)
            if y == 0:
                if lm is None:  # nothing to compare this frame's edits with
                    done += len(yaws)
                    break
                points, kept = _lifted(camera, lm, out.depth["head"].cpu().numpy(), head_a, pose)
                ref = (lm, points, kept, _box(lm[_FACE], h, w), rgb, head_a, torso_a)
            lm0, points, kept, box, rgb0, head0, torso0 = ref
            if lm is not None:
                found[y] += 1
                per["identity_px"][y].append(float(np.linalg.norm(_project(camera, points, pose) - lm[kept], axis=1).mean()))
                per["sharpness"][y].append(_sharpness(rgb, _box(lm[_FACE], h, w)) / max(_sharpness(rgb0, box), 1e-12))
                x0, y0, x1, y1 = _neck_band(lm, h, w)
                person = 1.0 - (1.0 - head_a[y0:y1, x0:x1]) * (1.0 - torso_a[y0:y1, x0:x1])
                if person.size:
                    per["neck_gap"][y].append(float((person < 0.5).mean()))
            torso_only = (torso_a > 0.5) & (torso0 > 0.5) & (head_a < 0.05) & (head0 < 0.05)
            if torso_only.any():
                per["torso_change"][y].append(float(np.abs(rgb[torso_only].astype(np.float64) - rgb0[torso_only]).mean()))
            done += 1
            if progress is not None:
                progress(done, total)
    taught = run.pose_range
    mean_yaw = float(np.mean(taught.angles(ds.poses[list(frames)])[:, 0])) if taught is not None else None
    rows = []
    for y, yaw in enumerate(yaws):
        row: dict = {"yaw": float(yaw), "faces_found": found[y], "frames": len(frames)}
        if taught is not None:
            row["yaw_past_range"] = round(max(0.0, mean_yaw + yaw - float(taught.rotation[0, 1])), 3)
        for key, values in per.items():
            row[key] = float(np.mean(values[y])) if values[y] else None
        rows.append(row)
    return rows, renders


def sweep_sheet(path: str | Path, renders: np.ndarray, yaws: Sequence[float], labels: Sequence[str], zoom: tuple[int, int, int, int] | None = None) -> Path:
    """A contact sheet of a sweep's renders ``(F, Y, H, W, 3)``: a row per frame, a column per yaw;
    ``zoom`` ``(x0, y0, x1, y1)`` adds, under each row, the same crop enlarged."""
    from .sheets import contact_sheet

    rows = []
    row_labels = []
    h, w = renders.shape[2:4]
    for f, label in enumerate(labels):
        rows.append(renders[f])
        row_labels.append(label)
        if zoom is not None:
            x0, y0, x1, y1 = zoom
            rows.append(np.stack([cv2.resize(img[y0:y1, x0:x1], (w, h), interpolation=cv2.INTER_LINEAR) for img in renders[f]]))
            row_labels.append(f"{label}, enlarged")
    return contact_sheet(Path(path), rows, [f"yaw {y:+g} deg" for y in yaws], row_labels)
