"""Two-stage training, as in AD-NeRF, with atomic resumable checkpoints.

Stage 1 (``head``) trains the audio encoders and the coarse/fine head fields. The target of a
pixel is the frame where the parsing says *head* and the background plate elsewhere; the plate is
the background of the volume rendering (through the residual transmittance). Each iteration takes
one training frame (its pose and audio window, as in the paper; or ``frames`` of them, whose rays
are rendered in one call, each ray under its own frame's condition) and draws rays among the
pixels whose ray crosses the head box, a quarter of them around the mouth (where the audio matters
and which is a small part of the head). AudioAttNet is switched on after ``att_start`` of the
iterations.

Losses: the MSE of the coarse and fine colours, plus ``mask_weight`` times the MSE of their
opacities against the parsing mask of the layer being trained; in stage 1, when the dataset has
landmarks, plus ``lip_weight`` times the error of a linear read-out of the audio codes predicting
the lip landmarks' opening and width (:mod:`adnerf.model.mouth_target`), so that the audio code
carries how open the mouth is and not only what the few mouth rays of a step teach it.

Stage 1 also aligns the tracked head poses to the head it learns: from ``pose_start`` of the
stage on, each drawn frame's pose correction (:mod:`adnerf.model.pose_refine`) follows the same
loss with its own optimizer (``pose_lr``), and every later use of a training frame's pose (stage 2,
the run's renders of its dataset) takes the corrected one.

Stage 2 (``torso``) freezes the head and the audio encoders and trains the torso fields on the full
frames, composited with the stage-1 head in the model's order: the head in front (the default,
:attr:`~adnerf.model.talking_head.ModelConfig.head_in_front`), or, in AD-NeRF's order, the head
over the plate as the torso's background.

The stages are data (:mod:`adnerf.model.stages`: the layer a stage trains, its parameter groups,
its iterations, the layers it draws frozen); :meth:`Trainer.fit` runs them in order. Training
writes a run folder (:mod:`adnerf.model.run_folder` describes it and reads it back), with a
checkpoint (each stage's step and optimizer under its name) every ``checkpoint_every`` iterations
and at the end of each stage. The schedule is :class:`adnerf.model.train_config.TrainConfig`.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import threading
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import Callable, Iterator, Literal, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from ..atomic import atomic_path
from ..audio.features import BUILTIN_KINDS
from ..compositor import Composite, Layer, over
from ..lock import FolderLock
from ..memory import require
from ..subnormals import flush_subnormals
from ..metrics import psnr_from_mse
from ..formats.dataset import (
    EYE_CROP,
    LABEL_HEAD,
    LABEL_TORSO,
    MOUTH_CROP,
    DatasetFolder,
    TalkingHeadDataset,
    frame_bytes,
    load_dataset,
)
from ..formats.outputs import check_folder_output, ensure_writable
from ..formats.run_folder import RunFolder
from ..pose import HeadPose
from ..renderer import RenderOutput
from ..rng import Shard
from .audio_jitter import jittered_windows
from .blinks import BLINKING, blinks_in
from .conditions import SIGNALS, FrameCondition
from .distributed import Ranks, init_ranks
from .lip_patch import patch_loss, patch_pixels
from .masks import BitRows
from .pose_refine import PoseCorrections, batch_loss, composed, corrected_matrices, fit_frames
from .mouth_target import MouthProbe, mouth_targets, opening_signal
from .run_folder import (
    RESUMABLE,
    Run,
    RunError,
    check_same_dataset,
    load_model_state,
    load_run,
    read_checkpoint,
    read_run_doc,
    run_configs,
    resumed_config,
    save_atomic,
    scheduled_smoothing,
    stage_step,
    stored_config,
    write_run,
)
from .stages import Stage, check_frozen_trained, default_stages, group_parameters
from .talking_head import (
    ModelConfig,
    TalkingHead,
    mixed_precision,
    model_config,
    render_layers,
)
from .train_config import TrainConfig

# The run folder and the schedule live in their own modules; re-exported for existing imports.
__all__ = ["RESUMABLE", "Run", "RunError", "TrainConfig", "Trainer", "TrainingInterrupted", "load_run", "pose_refit_seconds", "resumed_config", "stored_config", "train"]



class _Schedule:
    """Exponential decay from each group's initial rate ``base`` to ``final * base`` at ``iters``.

    The initial rates are given, not read from the optimizer: a resumed optimizer carries the
    decayed rates of its checkpoint.
    """

    def __init__(self, optimizer: torch.optim.Optimizer, base: list[float], iters: int, final: float) -> None:
        self.optimizer, self.base, self.iters, self.final = optimizer, base, max(iters, 1), final

    def set(self, step: int) -> float:
        factor = self.final ** (min(step, self.iters) / self.iters)
        for g, lr in zip(self.optimizer.param_groups, self.base):
            g["lr"] = lr * factor
        return self.base[0] * factor


Part = tuple[RenderOutput, torch.Tensor, torch.Tensor, "torch.Tensor | None"]
"""A batch of rays to learn from: ``(render, target (R, 3), mask (R,) bool, held (R,) bool or
None)``; the mask is the opacity's target on the ``held`` rays (``None``: all of them)."""


def _optimise(
    parts: list[Part], mask_weight: float, optimizer: torch.optim.Optimizer, ranks: Ranks = Ranks(), extra: "tuple[torch.Tensor, float, torch.optim.Optimizer] | None" = None,
    also: Sequence[torch.optim.Optimizer] = (), penalty: torch.Tensor | None = None,
) -> tuple[float, float]:  # fmt: skip
    """One step on the loss of every part (:func:`~adnerf.model.pose_refine.batch_loss`: the MSE of
    the coarse and fine colours plus ``mask_weight`` times the MSE of their opacities against the
    parsing mask, on the rays it holds), over the rays of every part together (each part's mean
    weighted by its share of the rays), plus ``weight`` times the loss of ``extra = (loss, weight,
    its own optimizer)`` (the mouth target, whose read-out has its own optimizer), plus ``penalty``
    (a weighted term of the same parameters: the lip patch's); the optimizers ``also`` (the pose
    corrections') step too. Returns ``(loss, fine colour MSE)``, averaged over
    the processes (whose gradients are averaged before the step)."""
    total = sum(len(target) for _, target, _, _ in parts)
    loss = fine_mse = 0.0
    for out, target, mask, held in parts:
        share = len(target) / total  # 1.0 for one part: the products and sums below are then exact
        part, part_fine = batch_loss(out, target, mask, mask_weight, held)
        loss, fine_mse = loss + share * part, fine_mse + share * part_fine
    optimizers = [optimizer, *also] if extra is None else [optimizer, extra[2], *also]
    if extra is not None:
        loss = loss + extra[1] * extra[0]
    if penalty is not None:
        loss = loss + penalty
    for opt in optimizers:
        opt.zero_grad(set_to_none=True)
    if loss.requires_grad:  # False when empty-space skipping left no sample on any ray
        loss.backward()
    if ranks.average_gradients([q for opt in optimizers for group in opt.param_groups for q in group["params"]]):
        for opt in optimizers:
            opt.step()
    return tuple(ranks.mean([float(loss.detach()), float(fine_mse.detach())]))  # type: ignore[return-value]


@dataclass
class Batch:
    """This process's rays of a step, to render in one call (:meth:`Trainer.batch_of`).

    Attributes:
        frame: The frame, or the frame of each ray ``(R,)`` when the rays come from several.
        pixels: Flat pixel indices ``(R,)``.
        condition: The frame's condition, or one per ray (:meth:`FrameCondition.of_rays`).
        generator: The generator of the sampler's draws for these rays (a :class:`~adnerf.rng.Shard`
            of the step's generator under several processes).
    """

    frame: int | torch.Tensor
    pixels: torch.Tensor
    condition: FrameCondition
    generator: "torch.Generator | Shard"


REFIT_STEPS = 40
"""Adam steps of each training frame's correction in a pose refit (``TrainConfig.pose_refit``)."""
REFIT_RAYS = 64
"""Rays of each frame a step of a pose refit renders."""
REFIT_GROUP = 32
"""Frames a pose refit fits together (one render call a step)."""
REFIT_CHUNK = 8 * REFIT_GROUP
"""Frames a pose refit reads out of the dataset at a time."""
NECK_BAND = 0.1
"""How far the torso may reach behind the head, as a fraction of the head label's height."""


def head_heights(is_head: torch.Tensor, height: int) -> torch.Tensor:
    """Rows spanned by each frame's head label ``(N,)`` int64 (0 for a frame without one), of
    head labels ``(N, H*W)`` bool."""
    rows = is_head.reshape(len(is_head), height, -1).any(dim=2)
    idx = torch.arange(height, device=is_head.device)
    top = torch.where(rows, idx, height).amin(dim=1)
    bottom = torch.where(rows, idx, -1).amax(dim=1)
    return torch.where(rows.any(dim=1), bottom - top + 1, 0)


def neck_reach(heights: torch.Tensor, band: float = NECK_BAND) -> int:
    """The reach of :func:`behind_chin` in pixels: ``band`` times the median of the frames' head
    heights ``(N,)`` (:func:`head_heights`) over the frames that have a head, at least 1; 0 when
    no frame has one."""
    present = heights > 0
    if not bool(present.any()):
        return 0
    return max(1, round(band * float(heights[present].float().median())))


def near_torso(is_torso: torch.Tensor, height: int, width: int, reach: int) -> torch.Tensor:
    """The pixels ``(N, H*W)`` bool within ``reach`` pixels (a square around each) of the frames'
    torso pixels ``is_torso (N, H*W)``; none when ``reach`` is 0."""
    if reach <= 0:
        return torch.zeros_like(is_torso)
    torso = is_torso.reshape(-1, 1, height, width).float()
    # The square's maximum as the maximum over its rows of the maximum along each row.
    along = F.max_pool2d(torso, (1, 2 * reach + 1), stride=1, padding=(0, reach))
    return F.max_pool2d(along, (2 * reach + 1, 1), stride=1, padding=(reach, 0)).reshape(len(is_torso), -1) > 0


def behind_chin(is_head: torch.Tensor, is_torso: torch.Tensor, height: int, width: int, band: float = NECK_BAND, reach: int | None = None) -> torch.Tensor:
    """The head pixels where a torso drawn behind the head may be opaque: those within ``r``
    pixels (a square around each) of the frame's torso pixels, ``r`` = ``band`` times the
    median height in rows of the frames' head labels (at least 1 pixel; :func:`neck_reach`).

    That is where the chin, which moves with the speech, covers the neck in some frames and not
    in others. Further up the torso stays transparent behind the head, so a head turned further
    than in any training frame uncovers the plate rather than whatever the torso made up there.

    Args:
        is_head: Head labels ``(N, H*W)`` bool.
        is_torso: Torso labels ``(N, H*W)`` bool.
        height: ``H``.
        width: ``W``.
        band: The reach as a fraction of the head's height.
        reach: The reach in pixels, where it was measured on more frames than these (the
            trainer's, on the whole clip); ``None``: :func:`neck_reach` of these frames with ``band``.

    Returns:
        ``(N, H*W)`` bool, a subset of ``is_head``.
    """
    reach = neck_reach(head_heights(is_head, height), band) if reach is None else reach
    near = torch.zeros_like(is_head)
    for start in range(0, len(is_torso), 64):  # frames at a time: a float copy of all at once is large
        near[start : start + 64] = near_torso(is_torso[start : start + 64], height, width, reach)
    return near & is_head


class TrainingInterrupted(Exception):
    """Training stopped on a signal (SIGINT, SIGTERM) after finishing its step and writing a
    checkpoint; ``--resume`` continues from it.

    Attributes:
        signum: The signal.
        stage: The stage it stopped in.
        step: Steps of that stage done.
        iters: Steps the stage has.
    """

    def __init__(self, signum: int, stage: str, step: int, iters: int) -> None:
        self.signum, self.stage, self.step, self.iters = signum, stage, step, iters
        super().__init__(f"stopped at {stage} step {step} of {iters} ({signal.Signals(signum).name}); --resume continues")


@contextmanager
def stop_on_signals(trainer: "Trainer") -> Iterator[None]:
    """While training, SIGINT and SIGTERM (Ctrl-C; a scheduler's notice before it kills) ask
    ``trainer`` to stop after its current step (:attr:`Trainer.stop_signal`); a second one
    stops at once. Outside the main thread (where Python delivers signals) nothing is changed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def ask(signum: int, frame: object) -> None:
        if trainer.stop_signal is not None:  # asked twice: stop now
            raise KeyboardInterrupt
        trainer.stop_signal = signum

    before = {sig: signal.signal(sig, ask) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


@dataclass
class MouthPlan:
    """Whether stage 1 trains the mouth target, and on what (:func:`mouth_plan`).

    Attributes:
        used: Whether the target is trained.
        doc: What ``run.json`` records as ``mouth_target``: ``used``, the clip's ``signal`` and
            ``min_signal``, or ``why`` not.
        targets: ``(N, 2)`` the standardised opening and width of every frame (when used).
        valid: ``(N,)`` bool, the frames with a target (when used).
    """

    used: bool
    doc: dict
    targets: "np.ndarray | None" = None
    valid: "np.ndarray | None" = None


def mouth_plan(ds: TalkingHeadDataset, tcfg: TrainConfig) -> MouthPlan:
    """Whether the mouth target is trained on ``ds``: with ``lip_weight`` above 0, landmarks, and
    audio that predicts the training frames' opening at least ``lip_min_signal`` (cross-validated).

    Raises:
        RunError: The landmarks give no usable target (e.g. a mouth that never moves).
    """
    if tcfg.lip_weight <= 0 or ds.landmarks is None:
        return MouthPlan(False, {"used": False, "why": "lip_weight is 0" if tcfg.lip_weight <= 0 else "the dataset has no landmarks"})
    try:
        targets, valid = mouth_targets(ds.landmarks, ds.meta.train)
    except ValueError as exc:
        raise RunError(f"{DatasetFolder(ds.root).landmarks}: {exc}; train with {{\"lip_weight\": 0}} (--config) to go on without the mouth target") from exc
    signal = opening_signal(ds.features, targets, valid, ds.meta.train)
    known = not math.isnan(signal)
    used = (known and signal >= tcfg.lip_min_signal) or tcfg.lip_min_signal <= -1
    doc = {"used": used, "signal": round(signal, 4) if known else None, "min_signal": tcfg.lip_min_signal}
    if not used:
        said = f"predicts the training frames' mouth opening at {signal:.2f} (cross-validated correlation)" if known else "cannot be cross-validated on so few training frames"
        doc["why"] = f"the audio {said}, under lip_min_signal {tcfg.lip_min_signal:g}: the audio code learns from the photometric loss alone"
    return MouthPlan(used, doc, targets if used else None, valid if used else None)


class Trainer:
    """A training session of a talking head on a dataset, stepped by its stages.

    :func:`train` drives one through a run folder (:meth:`fit`); ``bench fields`` steps one a few
    iterations at a time (:meth:`head_stage` with ``max_steps``) and reads its clock (``elapsed``,
    seconds by stage name), counters (``steps`` by stage name, with ``head_step`` and
    ``torso_step`` for the default two; ``samples``: field evaluations) and tensors (``rays``,
    ``plate``, ``windows``: on ``device``).

    Args:
        root: The run folder (checkpoints and the log are written there by the main process).
        ds: The dataset.
        mcfg: The model.
        tcfg: The schedule.
        device: Where to train.
        progress: Show progress bars.
        ranks: This process among the training processes (:mod:`adnerf.model.distributed`).
        plan: Whether and on what the mouth target is trained (:func:`mouth_plan` of ``ds`` and
            ``tcfg`` when ``None``).
        stages: The schedule's stages in order (:func:`~adnerf.model.stages.default_stages` of
            ``tcfg`` when ``None``); each gets an optimizer of its parameter groups.
    """

    def __init__(
        self, root: Path, ds: TalkingHeadDataset, mcfg: ModelConfig, tcfg: TrainConfig, device: str, progress: bool,
        ranks: Ranks = Ranks(), plan: "MouthPlan | None" = None, stages: Sequence[Stage] | None = None,
    ) -> None:  # fmt: skip
        self.root, self.ds, self.tcfg, self.device, self.ranks = root, ds, tcfg, device, ranks
        flush_subnormals()  # a CPU step would take twice as long once Adam's moments decay below 1.2e-38
        self.files = RunFolder(root)  # where the checkpoint and the log go
        self.progress = progress and ranks.main
        torch.manual_seed(tcfg.seed)
        self.model = TalkingHead(mcfg).to(device)
        self.camera = ds.meta.camera(device=device)
        self.rays = self.camera.rays().flatten()
        # The clip stays as the dataset holds it, uint8 frames and labels (on the CPU the dataset's
        # own memory, no copy): a step converts only its own rays (:meth:`colours`, :meth:`labelled`).
        if torch.device(device).type == "cuda":  # the clip is copied there: refuse before a CUDA out-of-memory
            require(frame_bytes(ds.meta) * ds.meta.n_frames, f"{ds.root}: {ds.meta.n_frames} frames of {ds.meta.width}x{ds.meta.height} (uint8 frames and labels)", available=torch.cuda.mem_get_info(torch.device(device))[0], where=f"the GPU {device}")
        self.frames = torch.as_tensor(ds.frames, device=device).reshape(ds.meta.n_frames, -1, 3)
        self.labels = torch.as_tensor(ds.parsing, device=device).reshape(ds.meta.n_frames, -1)
        self.plate = torch.as_tensor(ds.background, device=device).reshape(-1, 3).float() / 255.0
        self.windows = torch.as_tensor(ds.features, device=device)
        # Stage 1 may read each step's windows moved in time (TrainConfig.audio_jitter): every
        # shift's windows, made once; `step_windows` are the ones the step's codes read.
        self.jittered = jittered_windows(ds, tcfg.audio_jitter, device) if tcfg.audio_jitter else None
        self.step_windows = self.windows
        # The frame pools stay on the CPU, as the generator does: reading a drawn frame back from
        # a GPU would wait for the work queued there at every draw.
        self.train_frames = torch.as_tensor(ds.meta.train)
        if self.model.reads_eye and ds.eye is None:
            raise RunError(f"the run's head reads the eye openness but {ds.root} has no {DatasetFolder(ds.root).eye.name}")
        self.eye = torch.as_tensor(ds.eye, device=device) if ds.eye is not None and self.model.reads_eye else None
        # The further registered signals (ModelConfig.frame_signals: the head's, the layers'
        # warps): each frame's value, read from the dataset by the signal's track.
        self.tracks: dict[str, torch.Tensor] = {}
        for name in mcfg.frame_signals:
            track = SIGNALS[name].track  # registered: the model was built with it
            values = None if track is None else track(ds)
            if values is None:
                raise RunError(f"the run reads the {name!r} signal but {ds.root} gives no value of it (register the signal with a track that reads it)")
            dtype = np.float32 if name in mcfg.head_signals else np.float64  # a warp is geometry: float64
            self.tracks[name] = torch.as_tensor(np.asarray(values, dtype=dtype).reshape(ds.meta.n_frames, -1), device=device)
        # Frames that teach the eye condition: the blinking ones (drawn more often, blink_frames).
        self.blinking = self.train_frames[torch.as_tensor(ds.eye)[self.train_frames] < BLINKING] if self.eye is not None else self.train_frames[:0]
        self.pixel_index = torch.arange(ds.meta.width * ds.meta.height, device=device)
        # Every pixel's centre (column, row), for the squares around the mouth and the eyes.
        self.pixel_centres = (self.pixel_index % ds.meta.width + 0.5, self.pixel_index // ds.meta.width + 0.5)
        # Which pixels' rays cross the head box, per frame: made on a frame's first draw and kept,
        # a bit a pixel (crossing every pixel's ray costs more than a tenth of a CPU step).
        self.in_head_box = BitRows(ds.meta.n_frames, ds.meta.width * ds.meta.height, device)
        self.boxed = torch.zeros(ds.meta.n_frames, dtype=torch.bool)
        self.reach_made = torch.zeros(ds.meta.n_frames, dtype=torch.bool)  # frames whose row of reach is made
        m = self.model
        m.fit_feature_scale(self.windows[self.train_frames.to(device)])
        # One fused kernel updates every parameter, on CUDA and on the CPU: a 1024-ray stage-1
        # step took 34 ms on an H200 against 47 ms with PyTorch's default multi-tensor Adam, and
        # the head stage's update 2.0 ms on two CPU cores against 11.3 ms with the default
        # per-parameter loop. The update is Adam's either way.
        # Each stage's optimizer, its parameter groups as the stage names them.
        self.stages = {stage.name: stage for stage in (default_stages(tcfg) if stages is None else stages)}
        self.optimizers = {
            stage.name: torch.optim.Adam([{"params": group_parameters(m, g), "lr": g.lr} for g in stage.groups], betas=(0.9, 0.99), fused=True)
            for stage in self.stages.values()
        }
        # The mouth targets the audio code is asked to predict (stage 1), from the landmarks, where
        # the clip's audio predicts them (mouth_doc says whether and why, for run.json). A head that
        # reads the mouth is given each frame's own; its read-out is the model's (rendering uses it).
        self.mouth_probe: MouthProbe | None = None
        self.lip_window: list[torch.Tensor] = []
        self.patch_window: list[torch.Tensor] = []  # the lip patch's 1 - SSIM of each step since the last log line
        plan = mouth_plan(ds, tcfg) if plan is None else plan
        self.mouth_doc = plan.doc
        if plan.used:
            self.mouth = torch.as_tensor(plan.targets, device=device)
            self.lip_pool = self.train_frames[torch.as_tensor(plan.valid)[self.train_frames]]
            self.mouth_probe = m.mouth_probe if m.mouth_probe is not None else MouthProbe(mcfg.audio_dim).to(device)
            self.opt_probe = torch.optim.Adam(self.mouth_probe.parameters(), lr=tcfg.lr, betas=(0.9, 0.99), fused=True)
        elif m.reads_mouth:
            raise RunError(f"the run's head reads the mouth, but the mouth target is not used on {ds.root} ({plan.doc['why']})")
        elif self.progress and "signal" in plan.doc:
            print(f"adnerf: {plan.doc['why']}", file=sys.stderr)
        # Each training frame's head-pose correction (pose_lr > 0), learnt in stage 1 from
        # pose_start on (:meth:`pose_of`); Adam moves only the corrections of frames drawn.
        self.pose_fix: PoseCorrections | None = None
        self.poses_learning = False
        if tcfg.pose_lr > 0:
            self.pose_fix = PoseCorrections(ds.meta.n_frames).to(device)
            self.opt_pose = torch.optim.Adam(self.pose_fix.parameters(), lr=tcfg.pose_lr)
        self.pose_refits = 0  # refit passes done (pose_refit), kept in the checkpoint
        self.generator = torch.Generator(device="cpu").manual_seed(tcfg.seed)
        self.steps = {name: 0 for name in self.stages}  # finished iterations, by stage
        self.elapsed = {name: 0.0 for name in self.stages}  # seconds spent in steps, by stage
        self.samples = 0  # field evaluations (after empty-space skipping) since construction
        self.stop_signal: int | None = None  # set by a signal (stop_on_signals): stop after this step

    # The two stages of the default schedule by their old names (bench fields and tests read them).
    @property
    def head_step(self) -> int:
        """Finished stage-1 iterations (``steps["head"]``)."""
        return self.steps["head"]

    @head_step.setter
    def head_step(self, value: int) -> None:
        self.steps["head"] = value

    @property
    def torso_step(self) -> int:
        """Finished stage-2 iterations (``steps["torso"]``)."""
        return self.steps.get("torso", 0)

    @property
    def opt_head(self) -> torch.optim.Optimizer:
        """Stage 1's optimizer (``optimizers["head"]``)."""
        return self.optimizers["head"]

    @property
    def opt_torso(self) -> torch.optim.Optimizer:
        """Stage 2's optimizer (``optimizers["torso"]``)."""
        return self.optimizers["torso"]

    @cached_property
    def neck_reach_px(self) -> int:
        """:func:`neck_reach` of the clip: the reach behind the chin in pixels, from every frame's
        head height (one pass over the labels, 64 frames at a time)."""
        h, n = self.ds.meta.height, self.ds.meta.n_frames
        return neck_reach(torch.cat([head_heights(self.labels[start : start + 64] == LABEL_HEAD, h) for start in range(0, n, 64)]))

    @cached_property
    def reach(self) -> BitRows:
        """Where the torso may be opaque behind the head (stage 2, head in front), a bit a pixel:
        a frame's row is :func:`behind_chin` of it, made on its first draw (:meth:`behind_head`)
        and kept; rows of frames not drawn yet are empty."""
        return BitRows(self.ds.meta.n_frames, self.ds.meta.height * self.ds.meta.width, self.device)

    def behind_head(self, frame: int | torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
        """Whether the torso may be opaque behind the head at pixels ``pix`` ``(R,)`` of ``frame``
        (or of each ray's frame ``(R,)``), bool ``(R,)``: :func:`behind_chin` of the frame, made
        on the frame's first draw (a clip's worth of masks before the first step took minutes for
        minutes of footage)."""
        reach = self.reach
        drawn = torch.unique(torch.as_tensor(frame).reshape(-1).cpu())
        todo = drawn[~self.reach_made[drawn]]
        if todo.numel():
            labels = self.labels[todo.to(self.labels.device)]
            reach.set(todo.to(reach.bytes.device), behind_chin(labels == LABEL_HEAD, labels == LABEL_TORSO, self.ds.meta.height, self.ds.meta.width, reach=self.neck_reach_px))
            self.reach_made[todo] = True
        return reach.at(frame, pix)

    def frame_bytes(self) -> dict[str, int]:
        """Bytes held for each frame of the clip, by store: the uint8 frames and labels, the
        packed masks (the head box's, and behind the chin once stage 2 made it); the same for every
        clip length, so training memory grows with the clip by this much a frame."""
        n = self.ds.meta.n_frames
        stores = {"frames": self.frames.numel() * self.frames.element_size(), "labels": self.labels.numel() * self.labels.element_size(), "in_head_box": self.in_head_box.nbytes}
        if "reach" in self.__dict__:
            stores["reach"] = self.reach.nbytes
        return {name: size // n for name, size in stores.items()}

    def colours(self, frame: int | torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
        """True colours ``(R, 3)`` float32 in ``[0, 1]`` of pixels ``pix`` of ``frame`` (or of each
        ray's frame ``(R,)``)."""
        return self.frames[frame, pix].float() / 255.0

    def labelled(self, label: int, frame: int | torch.Tensor, pix: torch.Tensor | None = None) -> torch.Tensor:
        """Whether pixels ``pix`` (default: all) of ``frame`` (or of each ray's frame) carry ``label``, bool."""
        return (self.labels[frame] if pix is None else self.labels[frame, pix]) == label

    # ---- checkpoints
    def save(self) -> None:
        if not self.ranks.main:
            return
        state = {
            "model": self.model.state_dict(),
            "generator": self.generator.get_state(),
            "stages": {name: {"step": self.steps[name], "optimizer": opt.state_dict()} for name, opt in self.optimizers.items()},
            "elapsed": self.elapsed,
        }
        if self.mouth_probe is not None:
            state["mouth_probe"] = {"model": self.mouth_probe.state_dict(), "opt": self.opt_probe.state_dict()}
        if self.pose_fix is not None:
            state["pose_corrections"] = {"delta": self.pose_fix.delta.detach().clone(), "opt": self.opt_pose.state_dict(), "refits": self.pose_refits}
        save_atomic(state, self.files.checkpoint)

    def load(self, ckpt: dict) -> None:
        """Continue from checkpoint content (see :func:`read_checkpoint`); the log keeps only the
        lines of the steps the checkpoint holds, so a resumed run logs each step once."""
        load_model_state(self.model, ckpt["model"], self.files.checkpoint, scheduled_smoothing(self.tcfg, stage_step(ckpt, "head")))
        for name, opt in self.optimizers.items():
            if name in ckpt["stages"]:
                opt.load_state_dict(ckpt["stages"][name]["optimizer"])
            self.steps[name] = stage_step(ckpt, name)
        self.generator.set_state(ckpt["generator"].cpu())  # loaded with map_location=device
        self.elapsed = {**self.elapsed, **ckpt["elapsed"]}
        if self.mouth_probe is not None and "mouth_probe" in ckpt:
            self.mouth_probe.load_state_dict(ckpt["mouth_probe"]["model"])
            self.opt_probe.load_state_dict(ckpt["mouth_probe"]["opt"])
        if self.pose_fix is not None and "pose_corrections" in ckpt:
            with torch.no_grad():
                self.pose_fix.delta.copy_(ckpt["pose_corrections"]["delta"])
            self.opt_pose.load_state_dict(ckpt["pose_corrections"]["opt"])
            self.pose_refits = int(ckpt["pose_corrections"].get("refits", 0))
        log = self.files.log
        if log.exists() and self.ranks.main:
            done = self.steps
            rows = [line for line in log.read_text().splitlines() if line.strip()]
            kept = []
            for line in rows:
                try:
                    row = json.loads(line)
                except ValueError:
                    continue  # a line cut by a kill
                if row.get("step", 0) <= done.get(row.get("stage"), 0):
                    kept.append(line)
            if len(kept) != len(rows):
                with atomic_path(log) as tmp:
                    tmp.write_text("".join(k + "\n" for k in kept))

    def log(self, row: dict) -> None:
        if not self.ranks.main:
            return
        with open(self.files.log, "a") as f:
            f.write(json.dumps(row) + "\n")

    # ---- sampling
    def pick_frame(self, blinks: bool = False) -> int:
        """A random training frame; with ``blinks``, a blinking one in ``blink_frames`` of the draws
        (when the head reads the eye openness and the clip blinks)."""
        pool = self.train_frames
        if blinks and self.blinking.numel() and float(torch.rand((), generator=self.generator)) < self.tcfg.blink_frames:
            pool = self.blinking
        k = int(torch.randint(len(pool), (1,), generator=self.generator))
        return int(pool[k])

    def pick_rays(self, candidates: torch.Tensor, n: int | None = None) -> torch.Tensor:
        """``n`` (default ``rays``) pixel indices drawn with replacement from ``candidates``; from
        every pixel when ``candidates`` is empty (a frame whose layer has no pixel in it)."""
        n = self.tcfg.rays if n is None else n
        if n == 0:
            return candidates[:0]
        pool = candidates if candidates.numel() else self.pixel_index
        idx = torch.randint(pool.numel(), (n,), generator=self.generator).to(pool.device)
        return pool[idx]

    def pick_among(self, pool: torch.Tensor, focus: torch.Tensor, fraction: float, n: int) -> torch.Tensor:
        """``n`` pixel indices: ``round(fraction * n)`` drawn among ``focus`` (none when it is
        empty), the rest among ``pool`` (:meth:`pick_rays`)."""
        n_focus = int(round(fraction * n)) if focus.numel() else 0
        return torch.cat([self.pick_rays(pool, n - n_focus), self.pick_rays(focus, n_focus)])

    def step_frames(self, layer: str, step: int, iters: int, rays_of: Callable[[int, HeadPose, int], torch.Tensor], codes_of: Callable[[list[int]], torch.Tensor]) -> list[tuple[int, torch.Tensor, FrameCondition]]:
        """A step's ``frames`` training frames, each ``(frame, pixels, condition)``: the frames are
        drawn first, then each frame's ``rays // frames`` pixels (``rays_of(frame, pose, n)``);
        then their audio codes in one call (``codes_of(frames) -> (frames, audio_dim)``: one
        audio network pass for the step, not one per frame) make each frame's condition, and the
        layer's occupancy grid is updated under the first frame's condition when due."""
        frames = [self.pick_frame() for _ in range(self.tcfg.frames)]
        n = self.tcfg.rays // self.tcfg.frames
        poses = [self.pose_of(frame) for frame in frames]
        pixels = [rays_of(frame, pose, n) for frame, pose in zip(frames, poses)]
        codes = codes_of(frames)
        groups = [(frame, pix, self.condition(frame, code, pose)) for frame, pix, code, pose in zip(frames, pixels, codes, poses)]
        self.maybe_update_occupancy(layer, step, iters, groups[0][2])
        return groups

    def refit_poses(self, frames: Sequence[int] | None = None) -> float:
        """One pose refit pass (``TrainConfig.pose_refit``): every training frame's correction
        (or those of ``frames``) is fitted again with the field frozen, from the learnt one on
        (:func:`~adnerf.model.pose_refine.fit_frames` on the inside of the head label, outside
        the mouth box, under the frame's own audio code and signals), and the fit's move is
        composed onto it. Learnt in stage 1 a few draws a frame, the corrections stay far from
        the pixels' best pose; the refit aligns them at once. The corrections' Adam moments are
        reset (they pointed at the old values). Every process fits alike (same field, seed and
        draws), so the corrections stay equal across processes.

        Returns:
            The pass's seconds.
        """
        if self.pose_fix is None:
            raise RuntimeError("pose_refit needs learnt corrections (pose_lr > 0)")
        t0 = time.perf_counter()
        frames = np.asarray(self.ds.meta.train if frames is None else frames, dtype=np.int64)
        model, dev = self.model, self.device
        with torch.no_grad():
            codes = model.frame_codes(self.windows)[torch.as_tensor(frames, device=dev)]
            learnt = self.pose_fix.delta.detach()[torch.as_tensor(frames, device=dev)]
        start = corrected_matrices(np.asarray(self.ds.poses[frames], dtype=np.float64), learnt.cpu().numpy())
        eye = None if self.eye is None else self.eye.cpu().numpy()[frames]
        signals = {name: values.cpu().numpy()[frames] for name, values in self.tracks.items()}
        plate = self.plate.reshape(self.ds.meta.height, self.ds.meta.width, 3)
        bar = tqdm(total=len(frames), desc=f"refit poses ({self.pose_refits + 1})", unit="frame", disable=not self.progress, dynamic_ncols=True)
        try:
            move = fit_frames(
                model, self.camera, plate, self.ds, frames, start, codes, eye=eye, signals=signals, seed=self.tcfg.seed + 1 + self.pose_refits, chunk=REFIT_CHUNK, bar=bar,
                steps=REFIT_STEPS, rays=REFIT_RAYS, group=REFIT_GROUP, lr=1e-3, amp=self.tcfg.amp,
            )  # fmt: skip
        finally:
            bar.close()
        with torch.no_grad():
            self.pose_fix.delta[torch.as_tensor(frames, device=dev)] = composed(learnt, torch.as_tensor(move, device=dev))
        self.opt_pose.state.clear()
        self.pose_refits += 1
        turn = np.degrees(np.linalg.norm(move[:, :3], axis=1))
        seconds = time.perf_counter() - t0
        self.log({"stage": "head", "step": self.steps["head"], "pose_refit": self.pose_refits, "frames": len(frames), "seconds": seconds, "mean_turn_deg": float(turn.mean())})
        return seconds

    def pose_of(self, frame: int) -> HeadPose:
        """Frame ``frame``'s head pose: the tracked one moved by its learnt correction (with
        gradients while the corrections learn, :attr:`poses_learning`), or the tracked one
        (``pose_lr`` 0)."""
        pose = self.ds.head_pose(frame, device=self.device)
        if self.pose_fix is None:
            return pose
        if self.poses_learning:
            return self.pose_fix(frame, pose)
        with torch.no_grad():
            return self.pose_fix(frame, pose)

    def eye_pixels(self, pose) -> torch.Tensor:  # noqa: ANN001
        """Flat indices of the pixels in squares of side ``EYE_CROP`` units around both eyes (none
        when the head does not read the eye openness, the dataset has no eye points, or the clip
        never blinks: then the eyes teach the condition nothing)."""
        if self.eye is None or self.ds.meta.eyes is None or not self.blinking.numel():
            return self.pixel_index[:0]
        uv, depth = (x.detach() for x in self.ds.meta.eyes_in_image(pose))  # a learning pose has gradients
        cols, rows = self.pixel_centres
        inside = torch.zeros_like(self.pixel_index, dtype=torch.bool)
        for k in range(2):
            half = 0.5 * EYE_CROP * self.ds.meta.intrinsics[0] / float(depth[k])
            inside |= ((cols - uv[k, 0]).abs() <= half) & ((rows - uv[k, 1]).abs() <= half)
        return self.pixel_index[inside]

    def head_box_pixels(self, frame: int, pose) -> torch.Tensor:  # noqa: ANN001
        """Flat indices of the pixels whose ray crosses the head box in ``frame`` (whose pose is
        ``pose``), kept from the frame's first draw."""
        if not self.boxed[frame]:
            near, far = self.model.layers["head"].crossing(self.rays, pose)
            self.in_head_box.set(frame, far > near)
            self.boxed[frame] = True
        return torch.nonzero(self.in_head_box.row(frame))[:, 0]

    def mouth_square(self, pose) -> tuple[float, float, float]:  # noqa: ANN001
        """The square of side ``MOUTH_CROP`` units around the mouth under ``pose``: its centre
        ``(u, v)`` and side, in pixels."""
        uv, depth = (x.detach() for x in self.ds.meta.mouth_in_image(pose))  # a learning pose has gradients
        return float(uv[0]), float(uv[1]), MOUTH_CROP * self.ds.meta.intrinsics[0] / float(depth)

    def mouth_pixels(self, pose) -> torch.Tensor:  # noqa: ANN001
        """Flat indices of the pixels in the square around the mouth (:meth:`mouth_square`)."""
        u, v, side = self.mouth_square(pose)
        cols, rows = self.pixel_centres
        inside = ((cols - u).abs() <= 0.5 * side) & ((rows - v).abs() <= 0.5 * side)
        return self.pixel_index[inside]

    def code(self, frame: int) -> torch.Tensor:
        """Frame ``frame``'s audio code ``(audio_dim,)`` (:meth:`TalkingHead.frame_codes`)."""
        return self.codes([frame])[0]

    def codes(self, frames: list[int]) -> torch.Tensor:
        """The audio codes ``(len(frames), audio_dim)`` of ``frames``, in one audio network pass,
        from the step's windows (moved in time in a stage-1 step under ``audio_jitter``)."""
        return self.model.frame_codes(self.step_windows, frames)

    def condition(self, frame: int, code: torch.Tensor, pose, speech: int | None = None) -> FrameCondition:  # noqa: ANN001
        """Frame ``frame``'s condition: its audio code, head pose and (when the head reads them) eye
        openness, mouth and further signals, the mouth of frame ``speech`` when the code is
        another frame's."""
        mouth = self.mouth[frame if speech is None else speech] if self.model.reads_mouth else None
        signals = {name: values[frame] for name, values in self.tracks.items()} or None
        return self.model.condition(code, pose, None if self.eye is None else self.eye[frame], mouth, signals=signals)

    def mouth_loss(self) -> "tuple[torch.Tensor, float, torch.optim.Optimizer] | None":
        """The mouth-target term of a stage-1 step, ``(loss, lip_weight, the read-out's
        optimizer)``: the read-out's error on the audio codes (as the step makes them, AudioAttNet's
        filtering included once on) of ``lip_frames`` training frames drawn with replacement;
        ``None`` without it (no random draw is made then)."""
        if self.mouth_probe is None:
            return None
        k = torch.randint(len(self.lip_pool), (self.tcfg.lip_frames,), generator=self.generator)
        frames = self.lip_pool[k].to(self.device)
        loss = self.mouth_probe.loss(self.model.frame_codes(self.step_windows, frames), self.mouth[frames])
        self.lip_window.append(loss.detach())  # the log's "lip": the window's mean (read when a line is written)
        return loss, self.tcfg.lip_weight, self.opt_probe

    def head_target(self, frame: int | torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
        """Stage-1 target colours ``(R, 3)`` of pixels ``pix`` of ``frame`` (or of each ray's frame
        ``(R,)``): the frame on head pixels, the plate elsewhere."""
        return torch.where(self.labelled(LABEL_HEAD, frame, pix)[:, None], self.colours(frame, pix), self.plate[pix])

    def maybe_update_occupancy(self, layer: str, step: int, iters: int, cond: FrameCondition) -> None:
        """Every ``occupancy_every`` iterations from ``occupancy_start``, re-estimate the layer's grid."""
        if self.model.layers[layer].occupancy is None or step < self.tcfg.occupancy_start * iters:
            return
        if step % self.tcfg.occupancy_every == 0:
            pose = HeadPose(cond.pose.R.detach(), cond.pose.t.detach())
            self.model.layers[layer].update_occupancy(FrameCondition(cond.audio.detach(), pose, cond.extra), generator=self.generator)

    # ---- stages
    def _loop(self, stage: Stage, step_fn: Callable[[int], tuple[float, float]], max_steps: int | None) -> None:
        """Run ``step_fn(step) -> (loss, fine mse)`` until the stage's iterations; log means over each log window."""
        name, iters = stage.name, stage.iters
        bar = tqdm(total=iters, initial=self.steps[name], desc=f"train {name}", unit="it", disable=not self.progress, dynamic_ncols=True)
        window_t, window_n, window_loss, window_mse, window_samples = time.perf_counter(), 0, 0.0, 0.0, self.samples
        done_here = 0
        try:  # the bar is closed before any error is printed
            while self.steps[name] < iters:
                if max_steps is not None and done_here >= max_steps:
                    break
                step = self.steps[name]
                t0 = time.perf_counter()
                loss, mse = step_fn(step)
                self.elapsed[name] += time.perf_counter() - t0
                self.steps[name] = step + 1
                done_here += 1
                window_n += 1
                window_loss += loss
                window_mse += mse
                bar.update(1)
                if (step + 1) % self.tcfg.log_every == 0 or step + 1 == iters:
                    now = time.perf_counter()
                    rays_per_s = window_n * self.tcfg.rays / max(now - window_t, 1e-9)
                    samples_per_s = (self.samples - window_samples) / max(now - window_t, 1e-9)
                    loss, mse = window_loss / window_n, window_mse / window_n
                    psnr = psnr_from_mse(mse)
                    window_t, window_n, window_loss, window_mse, window_samples = now, 0, 0.0, 0.0, self.samples
                    bar.set_postfix(loss=f"{loss:.2e}", psnr=f"{psnr:.2f}", rays_s=f"{rays_per_s:.0f}")
                    row = {"stage": name, "step": step + 1, "loss": loss, "mse": mse, "psnr": psnr, "rays_per_s": rays_per_s, "samples_per_s": samples_per_s}
                    if self.lip_window:  # the mouth target's error (standardised units; 1: no better than the mean mouth)
                        row["lip"], self.lip_window = float(torch.stack(self.lip_window).mean()), []
                    if self.patch_window:  # the lip patch's 1 - SSIM, unweighted
                        row["lip_patch"], self.patch_window = float(torch.stack(self.patch_window).mean()), []
                    self.log({**row, "elapsed": self.elapsed[name]})
                if (step + 1) % self.tcfg.checkpoint_every == 0 or step + 1 == iters:
                    self.save()
                if self.stop_signal is not None:
                    if (step + 1) % self.tcfg.checkpoint_every and step + 1 != iters:
                        self.save()
                    raise TrainingInterrupted(self.stop_signal, name, step + 1, iters)
        finally:
            bar.close()

    def batch_of(self, groups: list[tuple[int, torch.Tensor, FrameCondition]]) -> Batch:
        """This process's rays of a step's frames ``(frame, pixels (n,), condition)``, to render in
        one call (:class:`Batch`).

        Every process drew the same groups and renders its part of each group's rays, with the
        random numbers one process would draw for them. One call for several frames is what a GPU
        wants (a step's time there is mostly launches, not arithmetic); the rays and losses are
        those of a call per frame.
        """
        if len(groups) == 1:
            frame, pix, cond = groups[0]
            return Batch(frame, self.ranks.part(pix), cond, self.ranks.shard(self.generator))
        parts = [self.ranks.part(pix) for _, pix, _ in groups]
        counts = torch.tensor([len(p) for p in parts], device=self.device)
        which = torch.repeat_interleave(torch.arange(len(groups), device=self.device), counts)
        frames = torch.tensor([frame for frame, _, _ in groups], device=self.device)[which]
        generator = self.ranks.shard(self.generator, tuple(len(pix) for _, pix, _ in groups))
        return Batch(frames, torch.cat(parts), FrameCondition.of_rays([cond for _, _, cond in groups], which), generator)

    def head_part(self, batch: Batch) -> Part:
        """Render a stage-1 batch (this process's rays; :meth:`batch_of`): ``(render, target, head
        mask, None)`` (the mask holds on every ray)."""
        frame, pix, cond = batch.frame, batch.pixels, batch.condition
        with mixed_precision(self.device, self.tcfg.amp):
            out = self.model.layers["head"].render(self.rays[pix], cond, background=self.plate[pix], jitter=True, generator=batch.generator)
        self.samples += out.samples_evaluated
        return out, self.head_target(frame, pix), self.labelled(LABEL_HEAD, frame, pix), None

    def eye_batch(self) -> tuple[int, torch.Tensor, FrameCondition] | None:
        """For heads that blink: ``eye_rays * rays`` more rays around the eyes of a frame drawn
        among the blinking ones in ``blink_frames`` of the iterations (else among all), under the
        audio code of another random frame, so the eye condition is taught without taking rays or
        frames from the rest of the head, and alone explains the blinks (rendered in the same
        call as the step's frames); ``None`` for heads without it (no random draw is made then)."""
        if not self.blinking.numel() or self.ds.meta.eyes is None or self.tcfg.eye_rays <= 0:
            return None
        frame = self.pick_frame(blinks=True)
        pose = self.pose_of(frame)
        eyes = self.eye_pixels(pose)
        if not eyes.numel():
            return None
        pix = self.pick_rays(eyes, int(round(self.tcfg.eye_rays * self.tcfg.rays)))
        # The speech of another frame: the eyes do not depend on it, and with a few blinks in a
        # clip a blink's own audio code would name its frame well enough to be learnt in place of
        # the eye condition (which held-out speech then cannot call up).
        speech = self.pick_frame()
        return frame, pix, self.condition(frame, self.code(speech), pose, speech)

    def head_rays(self, frame: int, pose: HeadPose, n: int) -> torch.Tensor:
        """Stage-1 pixels of ``frame``: ``n`` of those whose ray crosses the head box, the
        ``mouth_rays`` share of them around the mouth. The box's pixels, kept from the frame's
        first draw, are those of its tracked pose: under its learnt correction they would depend
        on when the frame was first drawn, and a resumed run would draw other rays. With
        ``lip_patch``, the last ``lip_patch ** 2`` of the mouth's rays are a patch
        (:meth:`lip_patch_pixels`)."""
        pool = self.head_box_pixels(frame, self.ds.head_pose(frame, device=self.device))
        size = self.tcfg.lip_patch
        if not size:
            return self.pick_among(pool, self.mouth_pixels(pose), self.tcfg.mouth_rays, n)
        n_mouth = int(round(self.tcfg.mouth_rays * n))
        return torch.cat([self.pick_rays(pool, n - n_mouth), self.pick_rays(self.mouth_pixels(pose), n_mouth - size * size), self.lip_patch_pixels(pose)])

    def lip_patch_pixels(self, pose: HeadPose) -> torch.Tensor:
        """A ``lip_patch`` x ``lip_patch`` patch of pixels, row-major, at a random place in the
        central half of the square around the mouth (:func:`~adnerf.model.lip_patch.patch_pixels`)."""
        u, v, side = self.mouth_square(pose)
        return patch_pixels((u, v), side, self.tcfg.lip_patch, self.ds.meta.width, self.ds.meta.height, self.generator, self.device)

    def lip_patch_penalty(self, groups: list[tuple[int, torch.Tensor, FrameCondition]], part: Part) -> torch.Tensor | None:
        """``lip_patch_weight`` times the patches' ``1 - SSIM`` (:func:`~adnerf.model.lip_patch.patch_loss`,
        fine colours, or coarse without a fine pass) of a stage-1 step whose first ``frames`` groups
        are its frames' rays, each ending with its patch (:meth:`head_rays`), in the order
        :meth:`batch_of` renders them; ``None`` without ``lip_patch``."""
        size = self.tcfg.lip_patch
        if not size:
            return None
        out, target = part[0], part[1]
        ends = torch.cumsum(torch.tensor([len(pix) for _, pix, _ in groups]), 0)[: self.tcfg.frames]
        at = (ends[:, None] - size * size + torch.arange(size * size)[None, :]).reshape(-1).to(target.device)
        rgb = (out.fine if out.fine is not None else out.coarse).rgb
        loss = patch_loss(rgb[at], target[at], size)
        self.patch_window.append(loss.detach())  # the log's "lip_patch"
        return self.tcfg.lip_patch_weight * loss

    def frozen_head(self, pix: torch.Tensor, cond: FrameCondition) -> Layer:
        """The stage-1 head along pixels ``pix`` ``(R,)`` under ``cond`` (one frame's, or each
        ray's) as a premultiplied layer (``rgb (R, 3)``, ``opacity (R,)``, float32), without
        gradients.

        Stage 2 renders it for its own rays at each step: the head is frozen, so this is the value
        a cache of every frame's head render would hold, for no memory and no pass over the clip
        before the first step (rays of a step are far fewer than a clip's pixels).
        """
        return render_layers(self.model, self.rays[pix], cond, layers=("head",), amp=self.tcfg.amp)["head"]

    def torso_part(self, frame: int | torch.Tensor, pix: torch.Tensor, cond: FrameCondition, *, jitter: bool = True, generator: "torch.Generator | Shard | None" = None) -> Part:
        """Render stage-2 rays ``pix`` of ``frame`` (or of each ray's frame, ``(R,)``, under a
        per-ray condition) through the torso with the frozen head (:meth:`frozen_head` at those
        rays) in the model's order.

        Returns:
            ``(render, target, torso mask, rays whose opacity the mask holds)``. The render's colours
            are the whole stack over the plate; its opacities are the torso's. With the head in
            front, the torso's opacity is free at the head pixels just above the torso
            (:func:`behind_chin`): the neck goes on behind the chin, and holding it to 0 there
            would average the chin's moving edge into a half-transparent band under it.
        """
        torso = self.model.layers["torso"]
        head_in_front = self.model.config.head_in_front
        head = self.frozen_head(pix, cond)
        background = self.plate[pix] if head_in_front else over(head, Layer.opaque(self.plate[pix])).rgb
        with mixed_precision(self.device, self.tcfg.amp):
            out = torso.render(self.rays[pix], cond, background=background, jitter=jitter, generator=self.ranks.shard(self.generator) if generator is None else generator)
        self.samples += out.samples_evaluated
        if not head_in_front:
            return out, self.colours(frame, pix), self.labelled(LABEL_TORSO, frame, pix), None

        def under_head(c: Composite) -> Composite:
            return replace(c, rgb=over(head, Layer.opaque(c.rgb.float())).rgb)

        out = RenderOutput(under_head(out.coarse), None if out.fine is None else under_head(out.fine), out.samples_evaluated)
        return out, self.colours(frame, pix), self.labelled(LABEL_TORSO, frame, pix), ~self.behind_head(frame, pix)

    @cached_property
    def torso_box_pixels(self) -> torch.Tensor:
        """Flat indices of the pixels whose ray crosses the torso box (camera space: every frame's)."""
        near, far = self.model.layers["torso"].crossing(self.rays)
        return torch.nonzero(far > near)[:, 0]

    def torso_rays(self, frame: int, pose: HeadPose, n: int) -> torch.Tensor:
        """Stage-2 pixels of ``frame``: ``n`` of those whose ray crosses the torso box, the
        ``torso_person_rays`` share of them on the frame's torso label."""
        return self.pick_among(self.torso_box_pixels, torch.nonzero(self.labelled(LABEL_TORSO, frame))[:, 0], self.tcfg.torso_person_rays, n)

    def torso_batch_part(self, batch: Batch) -> Part:
        """:meth:`torso_part` of a stage-2 batch (:meth:`batch_of`)."""
        return self.torso_part(batch.frame, batch.pixels, batch.condition, generator=batch.generator)

    @property
    def layer_steps(self) -> dict[str, tuple[Callable[[int, HeadPose, int], torch.Tensor], Callable[[Batch], Part]]]:
        """What a stage's step draws for each layer: ``(rays_of(frame, pose, n) -> pixels,
        part(batch) -> (render, target, mask, opacity-held rays))``."""
        return {"head": (self.head_rays, self.head_part), "torso": (self.torso_rays, self.torso_batch_part)}

    def run_stage(self, stage: Stage, max_steps: int | None) -> None:
        """Train ``stage`` from its finished iterations to its end, or ``max_steps`` of it.

        A step sets the learning rates, draws ``frames`` training frames and their rays for the
        stage's layer, makes their audio codes (with gradients when the stage trains the audio
        encoders, which also switch AudioAttNet on at ``att_start`` of the stage and fit the mouth
        target; heads that blink add eye rays) and takes one optimizer step.

        Raises:
            RunError: A layer the stage draws frozen is not finished training.
        """
        tcfg = self.tcfg
        check_frozen_trained(stage, list(self.stages.values()), self.steps)
        rays_of, part_of = self.layer_steps[stage.layer]
        if stage.trains_audio:
            codes_of = self.codes
        else:
            with torch.no_grad():
                codes = self.model.frame_codes(self.windows)
            codes_of = lambda frames: codes[frames]  # noqa: E731
        opt = self.optimizers[stage.name]
        sched = _Schedule(opt, [g.lr for g in stage.groups], stage.iters, tcfg.lr_final)
        teaches_eye = stage.trains_audio and "eye" in self.model.layers[stage.layer].conditions
        self.model.train()

        refits = tcfg.pose_refit if stage.layer == "head" and self.pose_fix is not None and stage.iters > 0 else 0
        refit_at = [round(i * stage.iters / refits) for i in range(1, refits + 1)]  # the last: the stage's end

        def step_fn(step: int) -> tuple[float, float]:
            while self.pose_refits < refits and step >= refit_at[self.pose_refits]:
                self.refit_poses()
            sched.set(step)
            if stage.trains_audio:
                self.model.set_audio_smoothing(step >= tcfg.att_start * stage.iters)
                if self.jittered is not None:  # the step's audio, moved by a drawn shift
                    self.step_windows = self.jittered[int(torch.randint(len(self.jittered), (1,), generator=self.generator))]
            # The head's stage also aligns the training frames' poses to it, from pose_start on.
            self.poses_learning = self.pose_fix is not None and stage.layer == "head" and step >= tcfg.pose_start * stage.iters
            groups = self.step_frames(stage.layer, step, stage.iters, rays_of, codes_of)
            eye_batch = self.eye_batch() if teaches_eye else None  # heads that blink: rays at the eyes of another frame
            if eye_batch is not None:
                groups.append(eye_batch)
            part = part_of(self.batch_of(groups))
            also = [self.opt_pose] if self.poses_learning else []
            penalty = self.lip_patch_penalty(groups, part) if stage.layer == "head" else None
            return _optimise([part], tcfg.mask_weight, opt, self.ranks, self.mouth_loss() if stage.trains_audio else None, also, penalty)

        try:
            self._loop(stage, step_fn, max_steps)
        finally:
            self.poses_learning = False
            self.step_windows = self.windows
        if refits and self.steps[stage.name] >= stage.iters and self.pose_refits < refits:
            t0 = time.perf_counter()
            while self.pose_refits < refits:
                self.refit_poses()
            self.elapsed[stage.name] += time.perf_counter() - t0  # as a pass inside the stage's steps is
            self.save()

    def fit(self, stages: Sequence[Stage] | None = None, max_steps: int | None = None) -> None:
        """Run stages of this trainer in order (default: all of them), ``max_steps`` iterations
        in all at most; a finished stage is passed over.

        Raises:
            ValueError: A stage the trainer was not made with (it has no optimizer).
        """
        stages = list(self.stages.values()) if stages is None else list(stages)
        unknown = [s.name for s in stages if self.stages.get(s.name) != s]
        if unknown:
            raise ValueError(f"stage {unknown[0]!r} is not one of this trainer's ({', '.join(self.stages)}); pass it to Trainer(stages=...)")
        budget = max_steps
        for stage in stages:
            if budget is not None and budget <= 0:
                break
            before = self.steps[stage.name]
            self.run_stage(stage, budget)
            if budget is not None:
                budget -= self.steps[stage.name] - before

    def set_iterations(self, name: str, iters: int) -> None:
        """Stretch or shorten stage ``name`` to ``iters`` iterations, in the stage and the schedule
        (``bench fields`` fits its schedule to a time budget as it goes); the learning rates and
        AudioAttNet's start follow the new length from the next step."""
        self.stages[name] = replace(self.stages[name], iters=iters)
        if hasattr(self.tcfg, f"{name}_iters"):
            setattr(self.tcfg, f"{name}_iters", iters)

    def head_stage(self, max_steps: int | None) -> None:
        """Stage 1 (:meth:`run_stage` of the ``"head"`` stage)."""
        self.run_stage(self.stages["head"], max_steps)

    def torso_stage(self, max_steps: int | None) -> None:
        """Stage 2 (:meth:`run_stage` of the ``"torso"`` stage)."""
        self.run_stage(self.stages["torso"], max_steps)


def train(
    dataset: str | Path,
    run_dir: str | Path,
    *,
    stage: Literal["head", "torso", "all"] = "all",
    config: TrainConfig | None = None,
    device: str = "cpu",
    resume: bool = False,
    progress: bool = True,
    max_steps: int | None = None,
) -> Path:
    """Train (or resume training) a talking head on a dataset.

    Args:
        dataset: Dataset folder (see :mod:`adnerf.formats.dataset`).
        run_dir: Run folder to create (or to resume).
        stage: ``"head"``, ``"torso"`` or ``"all"`` (head, then torso).
        config: Schedule; on resume, ``None`` keeps the stored one, and a given one may differ
            from it only in :data:`RESUMABLE` keys (e.g. to train longer or add the torso stage).
        device: ``"cpu"`` or ``"cuda"``.
        resume: Continue from ``run_dir/checkpoint.pt``; without it an existing run is an error.
        progress: Show progress bars.
        max_steps: Stop this call after this many iterations (checkpoints as usual); for tests
            and for splitting long runs.

    Returns:
        The run folder.

    Raises:
        RunError: Nothing to resume, a run already there without ``resume``, another dataset
            than the run's, a change a resume cannot make, a damaged checkpoint, or the torso
            stage before a finished head stage. Raised before anything is written.
        adnerf.lock.FolderBusyError: Another live process trains ``run_dir``.
        TrainingInterrupted: SIGINT or SIGTERM arrived; the step was finished and a checkpoint
            written first.
        adnerf.formats.outputs.OutputError: ``run_dir`` is a file, holds other files, or is not writable.
    """
    if stage not in ("head", "torso", "all"):
        raise ValueError(f"stage must be head, torso or all; got {stage!r}")
    flush_subnormals()  # before the dataset's checks start torch's worker threads (adnerf.subnormals)
    root = Path(run_dir)
    ranks, device = init_ranks(device)
    ds = load_dataset(dataset, truth=False)
    files = RunFolder(root)
    ckpt = None
    # Every check comes before the first write: a refused command leaves the folder as it was.
    if resume:
        if not files.is_run():
            raise RunError(f"{root}: nothing to resume (no {files.run_json.name}); drop --resume to start a new run")
        doc = read_run_doc(root)
        mcfg, stored = run_configs(doc)
        tcfg = resumed_config(stored, config)
        check_same_dataset(doc, ds, dataset, root)
        if files.checkpoint.exists():
            ckpt = read_checkpoint(files.checkpoint, device)
    else:
        if files.is_run() or files.checkpoint.exists():
            raise RunError(f"{root}: a run already exists there; pass --resume to continue it or choose another folder")
        check_folder_output(root, "run", inputs=[dataset], flag=None)
        tcfg = config or TrainConfig()
    tcfg.validate()
    plan = mouth_plan(ds, tcfg)
    if not resume:
        # The head reads the eye openness when the clip blinks (else it carries nothing to learn),
        # and the mouth when the mouth target is used and mouth_input asks for it; the torso
        # follows its motion where the dataset measured it and torso_motion asks for it.
        mcfg = model_config(
            ds.meta, tcfg.preset, eye=blinks_in(ds.eye, ds.meta.train), mouth=plan.used and tcfg.mouth_input == 1,  # type: ignore[arg-type]
            head_samples=tcfg.head_samples, torso_samples=tcfg.torso_samples, head_grid=tcfg.head_grid, head_width=tcfg.head_width, head_gate=tcfg.head_gate, head_planes=tcfg.head_planes, torso_motion=ds.torso is not None and tcfg.torso_motion == 1,
        )  # fmt: skip
    if mcfg.feature_dim != ds.meta.feature_dim:
        raise RunError(f"the run's model takes {mcfg.feature_dim}-d audio features but {dataset} has {ds.meta.feature_dim}-d ({ds.meta.feature_kind})")
    stages = default_stages(tcfg)
    chosen = [s for s in stages if stage in ("all", s.name)]
    done = {s.name: stage_step(ckpt, s.name) if ckpt else 0 for s in stages}
    for k, s in enumerate(chosen):  # a stage drawing a layer frozen needs the stage that trains it finished, or run first
        check_frozen_trained(s, stages, done, before=chosen[:k])
    if tcfg.audio_jitter and ds.meta.feature_kind not in BUILTIN_KINDS:  # before hours of work
        raise RunError(f"audio_jitter cuts the windows again from the dataset's audio, which adnerf can do for {', '.join(BUILTIN_KINDS)} features; {dataset} has {ds.meta.feature_kind!r} (set audio_jitter to 0)")
    if tcfg.lip_patch and ranks.world > 1:  # each process renders a part of a frame's rays, so no whole patch
        raise RunError(f"lip_patch trains in one process; this run has {ranks.world}")
    if (tcfg.rays // tcfg.frames) % ranks.world:
        raise RunError(f"{ranks.world} processes must split the {tcfg.rays // tcfg.frames} rays of each frame in a batch evenly; choose rays divisible by {ranks.world * tcfg.frames}")
    # One writer per run folder: a second training of it (another terminal, a restarted job)
    # is refused here, before it writes (process 0 holds the lock for every process).
    with FolderLock(root, "run") if ranks.main else nullcontext():
        ensure_writable(root)
        devices = ranks.gather(str(device))
        ranks.barrier()  # every process has checked the folder before process 0 writes into it
        trainer = Trainer(root, ds, mcfg, tcfg, device, progress, ranks, plan)
        if ckpt is not None:
            trainer.load(ckpt)
        if ranks.main:
            write_run(root, dataset, ds, mcfg, tcfg, {"world_size": ranks.world, "backend": ranks.backend, "devices": devices}, {"mouth_target": trainer.mouth_doc})
        ranks.barrier()
        with stop_on_signals(trainer):
            trainer.fit(chosen, max_steps)
        if not files.checkpoint.exists():
            trainer.save()
        ranks.barrier()
    return root


def pose_refit_seconds(run_dir: str | Path, dataset: str | Path, *, device: str = "cpu", frames: int = REFIT_GROUP) -> float:
    """Seconds a pose refit pass (``TrainConfig.pose_refit``) spends on each training frame, timed
    on the first ``frames`` training frames with a run's field as its checkpoint holds it.

    For schedules fitted to a time budget (``bench real``): a pass's cost grows with the clip's
    training frames, not with the stage's iterations. The timed frames' corrections are refitted
    in memory and not saved: the checkpoint is not rewritten (the run's log gets the timed pass's
    row, marked with its frame count).

    Raises:
        RunError: ``run_dir`` holds no checkpoint, or its run does not learn pose corrections.
    """
    root = Path(run_dir)
    files = RunFolder(root)
    if not files.checkpoint.exists():
        raise RunError(f"{root}: no checkpoint to time a pose refit with")
    ds = load_dataset(dataset, truth=False)
    doc = read_run_doc(root)
    mcfg, tcfg = run_configs(doc)
    if tcfg.pose_lr <= 0:
        raise RunError(f"{root}: its run learns no pose corrections (pose_lr 0), so there is no refit to time")
    trainer = Trainer(root, ds, mcfg, tcfg, device, False, Ranks(), mouth_plan(ds, tcfg))
    trainer.load(read_checkpoint(files.checkpoint, device))
    picked = list(ds.meta.train)[: max(1, frames)]
    return trainer.refit_poses(picked) / len(picked)
