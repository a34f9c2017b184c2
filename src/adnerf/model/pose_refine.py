"""Per-frame head-pose corrections fitted to the frames' pixels through the head field.

The tracked head poses (:mod:`adnerf.preprocess.headpose`) carry an error of a fraction of a
degree that drifts slowly from frame to frame. A field trained under them averages each feature
over its misplaced copies: on real footage the eyes, brows and lips of a training frame render as
soft as those of a held-out one. A correction ``delta = (omega, tau)`` per frame, in the head's
canonical frame, moves the tracked pose ``(R, t)`` to

``R' = R exp(omega)``, ``t' = t + R tau``

(``exp``: the rotation of axis-angle ``omega``, radians; ``tau`` in scene units along the head's
own axes; zero: the tracked pose, exactly). Training learns one per training frame with the
field (:class:`PoseCorrections`); frames the field did not learn from (a held-out tail) get theirs
from :func:`fit_corrections`, with the field frozen, on the rigid part of the head: the inside of
its label, without the outline (hair and the jaw line move on their own) or the mouth box (the
fit cannot explain a mouth by moving the head).
"""

from __future__ import annotations

from typing import Callable, Mapping

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle
from torch import Tensor, nn
from tqdm.auto import tqdm

from ..cameras import Camera
from ..formats.dataset import LABEL_HEAD, MOUTH_CROP, TalkingHeadDataset
from ..pose import HeadPose
from .conditions import FrameCondition

__all__ = ["POSE_DOF", "PoseCorrections", "batch_loss", "composed", "corrected", "corrected_matrices", "fit_corrections", "fit_frames"]

POSE_DOF = 6
"""Numbers of a correction: axis-angle ``omega`` (3, radians), then ``tau`` (3, scene units)."""

FIT_CHUNK = 256
"""Frames :func:`fit_frames` copies out of a dataset at a time."""


def corrected(pose: HeadPose, delta: Tensor) -> HeadPose:
    """The tracked pose ``pose`` (batch ``(...)``) moved by corrections ``delta`` ``(..., 6)``
    (see the module docs): ``R exp(omega)``, ``t + R tau``; differentiable in ``delta``."""
    if delta.shape[-1] != POSE_DOF or delta.shape[:-1] != pose.t.shape[:-1]:
        raise ValueError(f"corrections must be {(*pose.t.shape[:-1], POSE_DOF)} for poses of batch {tuple(pose.t.shape[:-1])}; got {tuple(delta.shape)}")
    delta = delta.to(pose.R)
    turn = axis_angle_to_rotation_matrix(delta[..., :3].reshape(-1, 3)).reshape(*delta.shape[:-1], 3, 3)
    return HeadPose(pose.R @ turn, pose.t + torch.einsum("...ij,...j->...i", pose.R, delta[..., 3:]))


def corrected_matrices(poses: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """:func:`corrected` on pose matrices ``(N, 4, 4)`` and corrections ``(N, 6)`` (numpy, float64)."""
    pose = HeadPose.from_matrix(torch.as_tensor(np.asarray(poses, dtype=np.float64)))
    return corrected(pose, torch.as_tensor(np.asarray(delta, dtype=np.float64))).matrix().numpy()


def composed(first: Tensor, then: Tensor) -> Tensor:
    """The one correction ``(..., 6)`` that moves a pose as ``first`` and then ``then`` do
    (``(..., 6)`` each, ``then`` applied to the pose ``first`` made):
    ``corrected(corrected(pose, first), then) == corrected(pose, composed(first, then))``. Turns
    compose as ``exp(omega) = exp(omega_1) exp(omega_2)``, shifts as ``tau = tau_1 + exp(omega_1)
    tau_2`` (``tau_2`` lies along the once-corrected head's axes). Float64; turns below pi."""
    if first.shape != then.shape or first.shape[-1] != POSE_DOF:
        raise ValueError(f"corrections must both be (..., {POSE_DOF}) alike; got {tuple(first.shape)} and {tuple(then.shape)}")
    first, then = first.to(torch.float64), then.to(first.device, torch.float64)
    batch = first.shape[:-1]
    turn_1 = axis_angle_to_rotation_matrix(first[..., :3].reshape(-1, 3))
    turn_2 = axis_angle_to_rotation_matrix(then[..., :3].reshape(-1, 3))
    omega = rotation_matrix_to_axis_angle(turn_1 @ turn_2).reshape(*batch, 3)
    tau = first[..., 3:] + (turn_1 @ then[..., 3:].reshape(-1, 3, 1)).reshape(*batch, 3)
    return torch.cat([omega, tau], dim=-1)


class PoseCorrections(nn.Module):
    """One learnt correction per frame of a clip, ``delta (n_frames, 6)`` float64, all zero at first.

    A frame never drawn keeps zero: its correction has no gradient but zeros, and Adam moves a
    number only once it had a gradient.
    """

    def __init__(self, n_frames: int) -> None:
        super().__init__()
        self.delta = nn.Parameter(torch.zeros(n_frames, POSE_DOF, dtype=torch.float64))

    def forward(self, frame: int, pose: HeadPose) -> HeadPose:
        """Frame ``frame``'s tracked pose ``pose`` (one) moved by its correction (with gradients)."""
        return corrected(pose, self.delta[frame])


def batch_loss(out, target: Tensor, mask: Tensor, mask_weight: float, held: Tensor | None = None) -> tuple[Tensor, Tensor]:  # noqa: ANN001
    """A batch's training loss: the MSE of the coarse and fine colours against ``target``
    ``(R, 3)``, plus ``mask_weight`` times the MSE of their opacities against ``mask`` ``(R,)``
    (on the rays ``held`` holds; the others count 0); returns ``(loss, fine colour MSE)``.

    Args:
        out: A :class:`~adnerf.renderer.RenderOutput` of the rays.
    """
    fine = F.mse_loss(out.final.rgb.float(), target)
    loss = F.mse_loss(out.coarse.rgb.float(), target) + fine
    if mask_weight > 0:
        m = mask.float()
        for composite in (out.coarse, out.final):
            error = (composite.opacity.float() - m).square()
            loss = loss + mask_weight * (error.mean() if held is None else (error * held).mean())
    return loss, fine


def _inside(is_head: Tensor, margin: int) -> Tensor:
    """Pixels ``(H, W)`` of the head label at least ``margin`` pixels (a square's half side) from
    any pixel outside it."""
    outside = (~is_head).float()[None, None]
    return F.max_pool2d(outside, 2 * margin + 1, stride=1, padding=margin)[0, 0] == 0


def fit_corrections(
    model,  # noqa: ANN001 (a TalkingHead: imported lazily by its module's users)
    camera: Camera,
    plate: Tensor,
    images: np.ndarray,
    labels: np.ndarray,
    poses: np.ndarray,
    codes: Tensor,
    *,
    eye: np.ndarray | None = None,
    signals: Mapping[str, np.ndarray] | None = None,
    exclude: np.ndarray | None = None,
    steps: int = 120,
    rays: int = 128,
    group: int = 16,
    lr: float = 2e-3,
    mask_weight: float = 0.0,
    rim: float = 0.03,
    amp: str = "auto",
    seed: int = 0,
    progress: bool = False,
    condition: Callable[[Tensor, HeadPose, float | None, dict], FrameCondition] | None = None,
) -> np.ndarray:
    """Fit each frame's pose correction to its pixels with the head field frozen.

    Frames are fitted ``group`` at a time: each of ``steps`` Adam steps (learning rate ``lr``,
    decaying to a tenth) renders ``rays`` random pixels of every frame of the group through the
    head, under the frame's own audio code, and follows the gradient of the stage-1 loss
    (:func:`batch_loss`) in the corrections only. By default the pixels are the inside of the
    head label (``rim``), outside the ``exclude`` box, and the loss is their colour's: the face's
    rigid part, not its outline (hair and the jaw line move on their own, and the parsing's edge
    is uncertain), which on real footage kept the eyes and the landmarks better aligned than
    fitting the whole head box with its opacity (``docs/decisions.md``, *The head poses are
    fitted to the pixels*).

    Args:
        model: The trained :class:`~adnerf.model.talking_head.TalkingHead` (not changed).
        camera: The static camera.
        plate: Background ``(H, W, 3)`` float in ``[0, 1]``, on the model's device.
        images: The frames ``(N, H, W, 3)`` uint8.
        labels: Their parsing ``(N, H, W)`` uint8 (:data:`~adnerf.formats.dataset.LABEL_HEAD`).
        poses: Their tracked head poses ``(N, 4, 4)``.
        codes: Their audio codes ``(N, audio_dim)``.
        eye: Their eye openness ``(N,)`` for heads that read it (``None``: open).
        signals: Their values ``(N, k)`` of the model's frame signals by name.
        exclude: Pixel boxes ``(N, 4)`` ``(x0, y0, x1, y1)`` (end exclusive) left out of the fit
            (the mouth's, :func:`~adnerf.evaluation.boxes.mouth_boxes_at`).
        steps: Adam steps per group of frames.
        rays: Pixels of each frame per step.
        group: Frames fitted together (one render call a step).
        lr: Initial learning rate (radians and scene units a step, at most).
        mask_weight: Weight of the opacity term against the head label (0: colour only).
        rim: Only pixels of the head label farther than ``rim`` times its height from its
            outline are fitted; 0: every pixel whose ray crosses the head box (the target is the
            plate off the head).
        amp: Mixed precision of the fields (:func:`~adnerf.model.talking_head.mixed_precision`).
        seed: Seed of the pixel and sample draws.
        progress: Show a progress bar.
        condition: ``condition(code, pose, eye, signals) -> FrameCondition`` (default: the
            model's own :meth:`~adnerf.model.talking_head.TalkingHead.condition`).

    Returns:
        Corrections ``(N, 6)`` float64 (:func:`corrected_matrices` applies them).
    """
    from .talking_head import mixed_precision

    n, H, W = labels.shape
    if images.shape != (n, H, W, 3) or poses.shape != (n, 4, 4) or len(codes) != n:
        raise ValueError(f"fit_corrections needs N frames, labels, poses and codes alike; got {images.shape}, {labels.shape}, {poses.shape}, {tuple(codes.shape)}")
    if (H, W) != (camera.height, camera.width):
        raise ValueError(f"frames of {W}x{H} for a {camera.width}x{camera.height} camera")
    dev = plate.device
    head = model.layers["head"]
    cond_of = condition or (lambda code, pose, e, s: model.condition(code, pose, e, signals=s))
    signals = dict(signals or {})
    all_rays = camera.rays().flatten()
    flat_plate = plate.reshape(-1, 3).float()
    cols = torch.arange(W, device=dev).repeat(H)
    rows = torch.arange(H, device=dev).repeat_interleave(W)
    generator = torch.Generator(device="cpu").manual_seed(seed)
    out = np.zeros((n, POSE_DOF), dtype=np.float64)
    was_training, trained = model.training, [(p, p.requires_grad) for p in model.parameters()]
    model.eval()
    for p, _ in trained:
        p.requires_grad_(False)
    bar = tqdm(total=n, desc="fit poses", unit="frame", disable=not progress, dynamic_ncols=True)
    try:
        for start in range(0, n, group):
            idx = list(range(start, min(start + group, n)))
            tracked = HeadPose.from_matrix(torch.as_tensor(poses[idx], dtype=torch.float64, device=dev))
            heads_t = torch.as_tensor(labels[idx], device=dev).reshape(len(idx), -1) == LABEL_HEAD
            inside = None
            if rim > 0:
                heights = [int(r.any(dim=1).sum()) for r in heads_t.reshape(len(idx), H, W)]
                inside = [_inside(heads_t[k].reshape(H, W), max(1, round(rim * heights[k]))).reshape(-1) for k in range(len(idx))]
            pools = []
            for k, i in enumerate(idx):
                near, far = head.crossing(all_rays, tracked[k])
                keep = far > near
                if inside is not None:
                    keep &= inside[k]
                if exclude is not None:
                    x0, y0, x1, y1 = (int(v) for v in exclude[i])
                    keep &= ~((cols >= x0) & (cols < x1) & (rows >= y0) & (rows < y1))
                pools.append(torch.nonzero(keep)[:, 0])
            frames_t = torch.as_tensor(images[idx], device=dev).reshape(len(idx), -1, 3)
            delta = torch.zeros(len(idx), POSE_DOF, dtype=torch.float64, device=dev, requires_grad=True)
            opt = torch.optim.Adam([delta], lr=lr)
            live = [k for k, pool in enumerate(pools) if pool.numel()]
            for step in range(steps if live else 0):
                for g in opt.param_groups:
                    g["lr"] = lr * 0.1 ** (step / max(steps - 1, 1))
                pose = corrected(tracked[live], delta[live])
                picks = [pools[k][torch.randint(pools[k].numel(), (rays,), generator=generator).to(dev)] for k in live]
                which = torch.arange(len(live), device=dev).repeat_interleave(rays)
                pix = torch.cat(picks)
                conds = [
                    cond_of(codes[idx[k]], pose[j], None if eye is None else float(eye[idx[k]]), {name: values[idx[k]] for name, values in signals.items()})
                    for j, k in enumerate(live)
                ]  # fmt: skip
                cond = conds[0] if len(conds) == 1 else FrameCondition.of_rays(conds, which)
                with mixed_precision(dev, amp):
                    rendered = head.render(all_rays[pix], cond, background=flat_plate[pix], jitter=True, generator=generator)
                local = torch.as_tensor(live, device=dev)[which]
                is_head = heads_t[local, pix]
                target = torch.where(is_head[:, None], frames_t[local, pix].float() / 255.0, flat_plate[pix])
                loss, _ = batch_loss(rendered, target, is_head, mask_weight)
                opt.zero_grad(set_to_none=True)
                if loss.requires_grad:  # False when empty-space skipping left no sample on any ray
                    loss.backward()
                    opt.step()
            out[idx] = delta.detach().cpu().numpy()
            bar.update(len(idx))
    finally:
        bar.close()
        for p, flag in trained:
            p.requires_grad_(flag)
        model.train(was_training)
    return out


def fit_frames(
    model,  # noqa: ANN001 (a TalkingHead)
    camera: Camera,
    plate: Tensor,
    ds: TalkingHeadDataset,
    frames: np.ndarray,
    start: np.ndarray,
    codes: Tensor,
    *,
    eye: np.ndarray | None = None,
    signals: Mapping[str, np.ndarray] | None = None,
    seed: int = 0,
    chunk: int = FIT_CHUNK,
    bar: tqdm | None = None,
    **fit,  # noqa: ANN003 (fit_corrections' keywords)
) -> np.ndarray:
    """:func:`fit_corrections` of frames ``frames`` of ``ds`` from poses ``start``, each without
    the box of side ``MOUTH_CROP`` about its mouth under its start pose: what training's pose
    refit and the judged poses of held-out frames both fit.

    The frames are fitted ``chunk`` at a time, so a clip's frames and labels are not copied out of
    the dataset at once; chunk ``k``'s draws are seeded ``seed + k * chunk``.

    Args:
        model: The trained :class:`~adnerf.model.talking_head.TalkingHead` (not changed).
        camera: The static camera.
        plate: Background ``(H, W, 3)`` float in ``[0, 1]``, on the model's device.
        ds: The dataset whose frames, labels and mouth points are read.
        frames: Frame indices ``(N,)`` of ``ds``.
        start: Their head poses ``(N, 4, 4)`` to fit from.
        codes: Their audio codes ``(N, audio_dim)``.
        eye: Their eye openness ``(N,)`` (``None``: open).
        signals: Their frame signals ``(N, k)`` by name.
        seed: Seed of the first chunk's draws.
        chunk: Frames per call of :func:`fit_corrections`.
        bar: A progress bar advanced by each chunk's frames.
        **fit: Further keywords of :func:`fit_corrections` (steps, rays, group, lr, amp, progress).

    Returns:
        Corrections ``(N, 6)`` float64 from ``start``.
    """
    frames = np.asarray(frames, dtype=np.int64)
    boxes = ds.meta.mouth_boxes(HeadPose.from_matrix(torch.as_tensor(start)), MOUTH_CROP)
    move = np.zeros((len(frames), POSE_DOF), dtype=np.float64)
    for lo in range(0, len(frames), chunk):
        part = slice(lo, lo + chunk)
        move[part] = fit_corrections(
            model, camera, plate, ds.frames[frames[part]], ds.parsing[frames[part]], start[part], codes[part], eye=None if eye is None else eye[part],
            signals=None if signals is None else {name: values[part] for name, values in signals.items()}, exclude=boxes[part], seed=seed + lo, **fit,
        )  # fmt: skip
        if bar is not None:
            bar.update(len(frames[part]))
    return move
