"""Two-stage training, as in AD-NeRF, with atomic resumable checkpoints.

Stage 1 (``head``) trains the audio encoders and the coarse/fine head fields. The target of a
pixel is the frame where the parsing says *head* and the background plate elsewhere; the plate is
the background of the volume rendering (through the residual transmittance). Each iteration takes
one training frame (its pose and audio window, as in the paper) and draws rays among the pixels
whose ray crosses the head box, a quarter of them around the mouth (where the audio matters and
which is a small part of the head). AudioAttNet is switched on after ``att_start`` of the iterations.

Losses: the MSE of the coarse and fine colours, plus ``mask_weight`` times the MSE of their
opacities against the parsing mask of the layer being trained.

Stage 2 (``torso``) freezes the head and the audio encoders and trains the torso fields on the full
frames, with the stage-1 head rendered over the plate as the torso's background.

A run folder holds ``run.json`` (dataset, model and training configuration), ``background.png``,
``checkpoint.pt`` (written to a temporary file and renamed, every ``checkpoint_every`` iterations
and at the end of each stage), ``log.jsonl`` (one JSON object per logged iteration) and
``head_renders.pt`` (the cached stage-1 renders that stage 2 trains against).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable, Literal

import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from .atomic import atomic_path
from .distributed import Ranks, init_ranks
from .outputs import check_folder_output, ensure_writable
from .data import LABEL_HEAD, LABEL_TORSO, MOUTH_CROP, TalkingHeadDataset, load_dataset
from .fields import check_config_keys
from .renderer import RenderOutput
from .metrics import psnr_from_mse
from .talking_head import (
    AMP_MODES,
    ModelConfig,
    TalkingHead,
    layer_bounds,
    mixed_precision,
    model_config,
    render_head_on_plate,
    render_part,
    torso_bounds,
    update_occupancy,
)

__all__ = ["RESUMABLE", "RunError", "TrainConfig", "load_run", "resumed_config", "stored_config", "train"]

RUN_FORMAT = "adnerf-run"
RUN_VERSION = 1


class RunError(RuntimeError):
    """A run folder is missing, incomplete, of another version, or would be overwritten."""


@dataclass
class TrainConfig:
    """Training schedule.

    Attributes:
        head_iters: Stage-1 iterations.
        torso_iters: Stage-2 iterations. Measured on the 18 s demo scene with its stage-1 head fixed:
            2500 -> 4500 iterations raised the held-out torso PSNR from 23.0 to 24.1 dB and the
            background's from 36.3 to 38.1 dB (full frame 29.2 -> 30.1). The torso also covers head
            pixels (it is composited over the head) and gains more per second than the head, so
            the default schedule gives it many. On the 30 s demo scene, 4000 -> 3000 iterations
            cost 0.9 dB of full-frame held-out PSNR (31.4 -> 30.5) and nothing in the mouth crop
            (26.5 dB both), and saved the 2 minutes that keep the demo within 15 minutes.
        rays: Rays per iteration (all from one frame).
        lr: Initial learning rate of the fields (Adam).
        lr_audio: Initial learning rate of the audio encoders.
        lr_final: Final learning rate as a fraction of the initial one (exponential decay).
        att_start: Fraction of stage 1 after which AudioAttNet smooths the audio codes.
        mouth_rays: Fraction of each stage-1 batch drawn around the mouth (the dataset's mouth point
            projected with the frame's pose, a square of side ``MOUTH_CROP`` units); the rest is
            drawn from the whole head box.
        torso_person_rays: Fraction of each stage-2 batch drawn among the frame's torso pixels
            (the rest uniformly in the torso box, which is mostly background).
        mask_weight: Weight of the opacity loss against the parsing (stage 1: head pixels opaque,
            others clear; stage 2: torso pixels). Without it a static plate lets a layer stay
            half transparent and mix in the plate's colour, which a new background exposes.
        occupancy_start: Fraction of each stage after which the layer's occupancy grid is
            estimated and empty space skipped (the field needs a rough shape first).
        occupancy_every: Iterations between updates of the occupancy grid (each update
            evaluates both fields once per cell under the current frame's condition).
        checkpoint_every: Iterations between checkpoints.
        log_every: Iterations between log lines.
        amp: Mixed precision of the field evaluations: ``"auto"`` (bfloat16 on CUDA, off on
            CPU), ``"bf16"`` or ``"off"``; the compositor and the losses stay in float32.
        seed: Seed of the initialisation and of the ray sampling.
        preset: Field preset (``"fast"`` or ``"paper"``; see :func:`~adnerf.talking_head.model_config`).
    """

    head_iters: int = 3600
    torso_iters: int = 3000
    rays: int = 1024
    lr: float = 1e-2
    lr_audio: float = 2e-3
    lr_final: float = 0.1
    att_start: float = 0.6
    mouth_rays: float = 0.25
    torso_person_rays: float = 0.5
    mask_weight: float = 0.1
    occupancy_start: float = 0.1
    occupancy_every: int = 16
    checkpoint_every: int = 250
    log_every: int = 25
    amp: str = "auto"
    seed: int = 0
    preset: str = "fast"

    def validate(self) -> None:
        """Raise ``ValueError`` on impossible settings."""
        for name, kind in _FIELD_TYPES.items():
            value = getattr(self, name)
            if kind is float and not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number; got {value!r}")
        if self.head_iters < 0 or self.torso_iters < 0:
            raise ValueError("iteration counts must be >= 0")
        if self.rays < 1 or self.checkpoint_every < 1 or self.log_every < 1 or self.occupancy_every < 1:
            raise ValueError("rays, checkpoint_every, log_every and occupancy_every must be >= 1")
        if not (self.lr > 0 and self.lr_audio > 0 and 0 < self.lr_final <= 1):
            raise ValueError("learning rates must be positive and lr_final in (0, 1]")
        if not (0 <= self.att_start <= 1 and 0 <= self.occupancy_start <= 1):
            raise ValueError("att_start and occupancy_start must lie in [0, 1]")
        if self.amp not in AMP_MODES:
            raise ValueError(f"amp must be one of {AMP_MODES}; got {self.amp!r}")
        if self.mask_weight < 0:
            raise ValueError("mask_weight must be >= 0")
        if not (0 <= self.mouth_rays <= 1 and 0 <= self.torso_person_rays <= 1):
            raise ValueError("mouth_rays and torso_person_rays must lie in [0, 1]")
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {PRESETS}; got {self.preset!r}")

    @staticmethod
    def from_dict(d: object, base: "TrainConfig | None" = None) -> "TrainConfig":
        """From a dict (a ``--config`` JSON file) whose keys replace those of ``base`` (default: the
        defaults). Unknown keys, a non-object and a value of the wrong type (named by its key) are
        ``TypeError`` / ``ValueError``."""
        if not isinstance(d, dict):
            raise TypeError(f"a training config is a JSON object of TrainConfig fields; got a {type(d).__name__}")
        check_config_keys(d, TrainConfig, "training config")
        for key, value in d.items():
            kind = _FIELD_TYPES[key]
            ok = isinstance(value, str) if kind is str else isinstance(value, kind if kind is int else (int, float)) and not isinstance(value, bool)
            if not ok:
                raise TypeError(f"training config key {key!r} must be {_TYPE_WORDS[kind]}; got {value!r}")
        return replace(base or TrainConfig(), **{k: float(v) if _FIELD_TYPES[k] is float else v for k, v in d.items()})


PRESETS = ("fast", "paper")
_FIELD_TYPES: dict[str, type] = {f.name: {"int": int, "float": float, "str": str}[f.type] for f in fields(TrainConfig)}  # type: ignore[index]
_TYPE_WORDS = {int: "an integer", float: "a number", str: "a string"}
# What a resumed run may change: its length and how it is checkpointed, logged and computed.
# Everything else (rays, rates, seed, preset, ...) would make the continuation another run.
RESUMABLE = ("head_iters", "torso_iters", "amp", "checkpoint_every", "log_every")


def resumed_config(stored: TrainConfig, given: TrainConfig | None) -> TrainConfig:
    """The schedule a resume continues with: ``stored``, or ``given`` when it differs from it only
    in :data:`RESUMABLE` keys.

    Raises:
        RunError: ``given`` changes a key a resume cannot change.
    """
    if given is None:
        return stored
    changed = [f"{f.name} {getattr(stored, f.name)!r} -> {getattr(given, f.name)!r}" for f in fields(TrainConfig) if f.name not in RESUMABLE and getattr(given, f.name) != getattr(stored, f.name)]
    if changed:
        raise RunError(
            f"a resume continues the run's stored training config and can change only {', '.join(RESUMABLE)}; "
            f"this would change {'; '.join(changed)}. Train a new run (-o NEW) for other settings"
        )
    return given


def _write_json_atomic(path: Path, doc: dict) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1))


def _save_atomic(obj: object, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


@dataclass
class Run:
    """A loaded run: its configuration and model (on the requested device).

    Attributes:
        root: The run folder.
        dataset: The dataset folder it was trained on.
        model: The model with the latest checkpoint's weights.
        train_config: The schedule.
        head_step: Finished stage-1 iterations.
        torso_step: Finished stage-2 iterations.
        meta: The dataset's ``meta.json`` content (camera, fps, boxes, feature kind).
        elapsed: Training seconds per stage (``{"head": s, "torso": s}``), from the checkpoint.
    """

    root: Path
    dataset: Path
    model: TalkingHead
    train_config: TrainConfig
    head_step: int
    torso_step: int
    meta: dict
    elapsed: dict = field(default_factory=dict)

    @property
    def smooth_audio(self) -> bool:
        """Whether AudioAttNet was on at the end of what was trained."""
        return self.head_step > self.train_config.att_start * self.train_config.head_iters

    @property
    def has_torso(self) -> bool:
        """Whether stage 2 ran at all."""
        return self.torso_step > 0


def _read_run_doc(root: Path) -> dict:
    """``run.json`` of a run folder, checked for format and version."""
    path = root / "run.json"
    if not path.exists():
        raise RunError(f"{root}: not an adnerf run (no run.json); train one with `adnerf train DATASET -o {root}`")
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RunError(f"{path}: unreadable or damaged ({exc}); train a new run into another folder") from exc
    if not isinstance(doc, dict) or doc.get("format") != RUN_FORMAT or doc.get("version") != RUN_VERSION:
        found = (doc.get("format"), doc.get("version")) if isinstance(doc, dict) else (None, None)
        raise RunError(f"{path}: format {found[0]!r} version {found[1]!r}; this adnerf reads {RUN_FORMAT} version {RUN_VERSION}")
    return doc


def stored_config(root: str | Path) -> TrainConfig:
    """The training schedule stored in a run folder's ``run.json``."""
    return TrainConfig.from_dict(_read_run_doc(Path(root))["train"])


_CHECKPOINT_KEYS = ("model", "opt_head", "opt_torso", "generator", "head_step", "torso_step", "elapsed")


def _read_checkpoint(path: Path, device: str | torch.device) -> dict:
    """A checkpoint file's content; a missing, empty or damaged file is a :class:`RunError`."""
    if not path.exists():
        raise RunError(f"{path.parent}: no checkpoint.pt yet (training has not written one); train with `adnerf train DATASET -o {path.parent}`")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # torch.load raises many types on a damaged file (EOFError, RuntimeError, UnpicklingError, ...)
        raise RunError(
            f"{path}: damaged or incomplete checkpoint ({type(exc).__name__}: {exc}); adnerf writes checkpoints atomically, "
            "so the file was changed outside adnerf: restore it, or train a new run into another folder"
        ) from exc
    if not isinstance(ckpt, dict) or any(k not in ckpt for k in _CHECKPOINT_KEYS):
        raise RunError(f"{path}: not an adnerf checkpoint (missing entries); restore it, or train a new run into another folder")
    return ckpt


def load_run(root: str | Path, device: str | torch.device = "cpu") -> Run:
    """Load a run folder's configuration and latest checkpoint.

    Raises:
        RunError: Missing folder, ``run.json`` or checkpoint, a damaged one, or another format version.
    """
    root = Path(root)
    doc = _read_run_doc(root)
    ckpt_path = root / "checkpoint.pt"
    ckpt = _read_checkpoint(ckpt_path, device)
    model = TalkingHead(ModelConfig.from_dict(doc["model"])).to(device)
    _load_model_state(model, ckpt["model"], ckpt_path)
    model.eval()
    return Run(root, Path(doc["dataset"]), model, TrainConfig.from_dict(doc["train"]), ckpt["head_step"], ckpt["torso_step"], doc["meta"], ckpt["elapsed"])


def _check_same_dataset(doc: dict, ds: TalkingHeadDataset, dataset: str | Path, root: Path) -> None:
    """Refuse to resume ``root`` on a dataset other than the one it was trained on."""
    meta = {k: v for k, v in asdict(ds.meta).items() if k not in ("train", "test")}
    stored = doc.get("dataset_sha256")
    same = stored == ds.fingerprint() if stored else json.loads(json.dumps(meta)) == doc.get("meta")
    if not same:
        raise RunError(
            f"{root} was trained on another dataset ({doc.get('dataset')}) than {dataset}: its content differs. "
            f"A resume continues on the same data; resume with that dataset, or train a new run (-o NEW) on {dataset}"
        )


def _load_model_state(model: TalkingHead, state: dict, path: Path) -> None:
    """Load weights; a checkpoint from before occupancy grids existed leaves them unestimated."""
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.split(".")[0].endswith("_occupancy")]
    if missing or unexpected:
        raise RunError(f"{path}: weights do not match the run's model (missing {missing[:3]}, unexpected {unexpected[:3]})")


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


def _optimise(out: RenderOutput, target: torch.Tensor, mask: torch.Tensor, mask_weight: float, optimizer: torch.optim.Optimizer, ranks: Ranks = Ranks()) -> tuple[float, float]:
    """One step on the MSE of the coarse and fine colours plus ``mask_weight`` times the MSE of
    their opacities against the parsing mask; returns ``(loss, fine colour MSE)``, averaged over
    the processes (whose gradients are averaged before the step)."""
    fine_mse = F.mse_loss(out.final.rgb.float(), target)
    loss = F.mse_loss(out.coarse.rgb.float(), target) + fine_mse
    if mask_weight > 0:
        m = mask.float()
        loss = loss + mask_weight * (F.mse_loss(out.coarse.opacity.float(), m) + F.mse_loss(out.final.opacity.float(), m))
    optimizer.zero_grad(set_to_none=True)
    if loss.requires_grad:  # False when empty-space skipping left no sample on any ray
        loss.backward()
    if ranks.average_gradients([q for group in optimizer.param_groups for q in group["params"]]):
        optimizer.step()
    return tuple(ranks.mean([float(loss.detach()), float(fine_mse.detach())]))  # type: ignore[return-value]


class _Trainer:
    def __init__(self, root: Path, ds: TalkingHeadDataset, mcfg: ModelConfig, tcfg: TrainConfig, device: str, progress: bool, ranks: Ranks = Ranks()) -> None:
        self.root, self.ds, self.tcfg, self.device, self.ranks = root, ds, tcfg, device, ranks
        self.progress = progress and ranks.main
        torch.manual_seed(tcfg.seed)
        self.model = TalkingHead(mcfg).to(device)
        self.camera = ds.meta.camera(device=device)
        self.rays = self.camera.rays().flatten()
        self.frames = torch.as_tensor(ds.frames, device=device).reshape(ds.meta.n_frames, -1, 3).float() / 255.0
        self.plate = torch.as_tensor(ds.background, device=device).reshape(-1, 3).float() / 255.0
        labels = torch.as_tensor(ds.parsing, device=device).reshape(ds.meta.n_frames, -1)
        self.is_head, self.is_torso = labels == LABEL_HEAD, labels == LABEL_TORSO
        self.windows = torch.as_tensor(ds.features, device=device)
        self.train_frames = torch.as_tensor(ds.meta.train, device=device)
        self.pixel_index = torch.arange(ds.meta.width * ds.meta.height, device=device)
        m = self.model
        m.fit_feature_scale(self.windows[self.train_frames])
        self.opt_head = torch.optim.Adam(
            [
                {"params": list(m.head.parameters()) + list(m.head_fine.parameters()), "lr": tcfg.lr},
                {"params": list(m.audio_net.parameters()) + list(m.att_net.parameters()), "lr": tcfg.lr_audio},
            ],
            betas=(0.9, 0.99),
        )
        self.opt_torso = torch.optim.Adam(list(m.torso.parameters()) + list(m.torso_fine.parameters()), lr=tcfg.lr, betas=(0.9, 0.99))
        self.generator = torch.Generator(device="cpu").manual_seed(tcfg.seed)
        self.head_step = self.torso_step = 0
        self.elapsed = {"head": 0.0, "torso": 0.0}
        self.samples = 0  # field evaluations (after empty-space skipping) since construction

    # ---- checkpoints
    def save(self) -> None:
        if not self.ranks.main:
            return
        state = {
            "model": self.model.state_dict(),
            "opt_head": self.opt_head.state_dict(),
            "opt_torso": self.opt_torso.state_dict(),
            "generator": self.generator.get_state(),
            "head_step": self.head_step,
            "torso_step": self.torso_step,
            "elapsed": self.elapsed,
        }
        _save_atomic(state, self.root / "checkpoint.pt")

    def load(self, ckpt: dict) -> None:
        """Continue from checkpoint content (see :func:`_read_checkpoint`); the log keeps only the
        lines of the steps the checkpoint holds, so a resumed run logs each step once."""
        _load_model_state(self.model, ckpt["model"], self.root / "checkpoint.pt")
        self.opt_head.load_state_dict(ckpt["opt_head"])
        self.opt_torso.load_state_dict(ckpt["opt_torso"])
        self.generator.set_state(ckpt["generator"].cpu())  # loaded with map_location=device
        self.head_step, self.torso_step, self.elapsed = ckpt["head_step"], ckpt["torso_step"], ckpt["elapsed"]
        log = self.root / "log.jsonl"
        if log.exists() and self.ranks.main:
            done = {"head": self.head_step, "torso": self.torso_step}
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
        with open(self.root / "log.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")

    # ---- sampling
    def pick_frame(self) -> int:
        k = int(torch.randint(len(self.train_frames), (1,), generator=self.generator))
        return int(self.train_frames[k])

    def pick_rays(self, candidates: torch.Tensor, n: int | None = None) -> torch.Tensor:
        """``n`` (default ``rays``) pixel indices drawn with replacement from ``candidates``; from
        every pixel when ``candidates`` is empty (a frame whose layer has no pixel in it)."""
        n = self.tcfg.rays if n is None else n
        if n == 0:
            return candidates[:0]
        pool = candidates if candidates.numel() else self.pixel_index
        idx = torch.randint(pool.numel(), (n,), generator=self.generator).to(pool.device)
        return pool[idx]

    def mouth_pixels(self, pose) -> torch.Tensor:
        """Flat indices of the pixels in the square of side ``MOUTH_CROP`` units around the mouth."""
        uv, depth = self.ds.meta.mouth_in_image(pose)
        half = 0.5 * MOUTH_CROP * self.ds.meta.intrinsics[0] / float(depth)
        W = self.camera.width
        cols = self.pixel_index % W + 0.5
        rows = self.pixel_index // W + 0.5
        inside = ((cols - uv[0]).abs() <= half) & ((rows - uv[1]).abs() <= half)
        return self.pixel_index[inside]

    def code(self, frame: int, smooth: bool) -> torch.Tensor:
        return self.model.frame_code(self.windows, frame, smooth)

    @property
    def smooth_audio(self) -> bool:
        """Whether the finished stage-1 iterations have switched AudioAttNet on (as :attr:`Run.smooth_audio`)."""
        return self.head_step > self.tcfg.att_start * self.tcfg.head_iters

    def head_target(self, frame: int, pix: torch.Tensor) -> torch.Tensor:
        """Stage-1 target colours ``(R, 3)`` of pixels ``pix``: the frame on head pixels, the plate elsewhere."""
        return torch.where(self.is_head[frame, pix, None], self.frames[frame, pix], self.plate[pix])

    def maybe_update_occupancy(self, part: str, step: int, iters: int, pose, code: torch.Tensor) -> None:
        """Every ``occupancy_every`` iterations from ``occupancy_start``, re-estimate the layer's grid."""
        if self.model.config.occupancy_resolution <= 0 or step < self.tcfg.occupancy_start * iters:
            return
        if step % self.tcfg.occupancy_every == 0:
            update_occupancy(self.model, part, pose, code.detach(), generator=self.generator)  # type: ignore[arg-type]

    # ---- stages
    def _loop(self, stage: str, iters: int, step_fn: Callable[[int], tuple[float, float]], max_steps: int | None) -> None:
        """Run ``step_fn(step) -> (loss, fine mse)`` until ``iters``; log means over each log window."""
        start_step = getattr(self, f"{stage}_step")
        bar = tqdm(total=iters, initial=start_step, desc=f"train {stage}", unit="it", disable=not self.progress, dynamic_ncols=True)
        window_t, window_n, window_loss, window_mse, window_samples = time.perf_counter(), 0, 0.0, 0.0, self.samples
        done_here = 0
        while getattr(self, f"{stage}_step") < iters:
            if max_steps is not None and done_here >= max_steps:
                break
            step = getattr(self, f"{stage}_step")
            t0 = time.perf_counter()
            loss, mse = step_fn(step)
            self.elapsed[stage] += time.perf_counter() - t0
            setattr(self, f"{stage}_step", step + 1)
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
                row = {"stage": stage, "step": step + 1, "loss": loss, "mse": mse, "psnr": psnr, "rays_per_s": rays_per_s, "samples_per_s": samples_per_s}
                self.log({**row, "elapsed": self.elapsed[stage]})
            if (step + 1) % self.tcfg.checkpoint_every == 0 or step + 1 == iters:
                self.save()
        bar.close()

    def head_stage(self, max_steps: int | None) -> None:
        tcfg = self.tcfg
        sched = _Schedule(self.opt_head, [tcfg.lr, tcfg.lr_audio], tcfg.head_iters, tcfg.lr_final)
        self.model.train()

        def step_fn(step: int) -> tuple[float, float]:
            sched.set(step)
            frame = self.pick_frame()
            pose = self.ds.head_pose(frame, device=self.device)
            near, far = layer_bounds(self.model, "head", pose)(self.rays)
            candidates = torch.nonzero(far > near)[:, 0]
            mouth = self.mouth_pixels(pose)
            n_mouth = int(round(tcfg.mouth_rays * tcfg.rays)) if mouth.numel() else 0
            pix = torch.cat([self.pick_rays(candidates, tcfg.rays - n_mouth), self.pick_rays(mouth, n_mouth)])
            pix = self.ranks.part(pix)  # every process drew the same batch; it renders its part
            target = self.head_target(frame, pix)
            code = self.code(frame, smooth=step >= tcfg.att_start * tcfg.head_iters)
            self.maybe_update_occupancy("head", step, tcfg.head_iters, pose, code)
            with mixed_precision(self.device, tcfg.amp):
                out = render_part(self.model, "head", self.rays[pix], pose, code, background=self.plate[pix], jitter=True, generator=self.ranks.shard(self.generator))
            self.samples += out.samples_evaluated
            return _optimise(out, target, self.is_head[frame, pix], tcfg.mask_weight, self.opt_head, self.ranks)

        self._loop("head", tcfg.head_iters, step_fn, max_steps)

    @torch.no_grad()
    def head_renders(self, in_box: torch.Tensor) -> torch.Tensor:
        """Stage-1 renders over the plate of every frame ``(N, H*W, 3)``, cached in the run folder.

        Only the pixels stage 2 draws rays at (``in_box (H*W,)``: rays that cross the torso box,
        and the frame's torso pixels) are rendered; the others hold the plate, which stage 2 never
        reads.
        """
        path = self.root / "head_renders.pt"
        if path.exists():
            cached = torch.load(path, map_location=self.device, weights_only=False)
            if cached["head_step"] == self.head_step:
                return cached["renders"].float()
        self.model.eval()
        codes = self.model.all_codes(self.windows, self.smooth_audio)
        out = self.plate.expand_as(self.frames).clone()
        for frame in tqdm(self.ds.meta.train, desc="head renders", unit="frame", disable=not self.progress, dynamic_ncols=True):
            pix = torch.nonzero(in_box | self.is_torso[frame])[:, 0]
            pose = self.ds.head_pose(frame, device=self.device)
            out[frame, pix] = render_head_on_plate(self.model, self.rays[pix], pose, codes[frame], self.plate[pix], amp=self.tcfg.amp)
        if self.ranks.main:
            _save_atomic({"head_step": self.head_step, "renders": out.half()}, path)
        return out

    def torso_stage(self, max_steps: int | None) -> None:
        tcfg = self.tcfg
        if self.head_step < tcfg.head_iters:
            raise RunError(f"stage 2 needs a finished stage 1 ({self.head_step}/{tcfg.head_iters} head iterations); run --stage head first")
        near, far = torso_bounds(self.model.config, self.rays.origins)(self.rays)
        backgrounds = self.head_renders(far > near)
        with torch.no_grad():
            codes = self.model.all_codes(self.windows, self.smooth_audio)
        candidates = torch.nonzero(far > near)[:, 0]
        sched = _Schedule(self.opt_torso, [tcfg.lr], tcfg.torso_iters, tcfg.lr_final)
        self.model.train()

        def step_fn(step: int) -> tuple[float, float]:
            sched.set(step)
            frame = self.pick_frame()
            pose = self.ds.head_pose(frame, device=self.device)
            person = torch.nonzero(self.is_torso[frame])[:, 0]
            n_person = int(round(tcfg.torso_person_rays * tcfg.rays)) if person.numel() else 0
            pix = torch.cat([self.pick_rays(candidates, tcfg.rays - n_person), self.pick_rays(person, n_person)])
            pix = self.ranks.part(pix)
            target = self.frames[frame, pix]
            self.maybe_update_occupancy("torso", step, tcfg.torso_iters, pose, codes[frame])
            with mixed_precision(self.device, tcfg.amp):
                out = render_part(self.model, "torso", self.rays[pix], pose, codes[frame], background=backgrounds[frame, pix], jitter=True, generator=self.ranks.shard(self.generator))
            self.samples += out.samples_evaluated
            return _optimise(out, target, self.is_torso[frame, pix], tcfg.mask_weight, self.opt_torso, self.ranks)

        self._loop("torso", tcfg.torso_iters, step_fn, max_steps)


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
        dataset: Dataset folder (see :mod:`adnerf.data`).
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
        adnerf.outputs.OutputError: ``run_dir`` is a file, holds other files, or is not writable.
    """
    if stage not in ("head", "torso", "all"):
        raise ValueError(f"stage must be head, torso or all; got {stage!r}")
    root = Path(run_dir)
    ranks, device = init_ranks(device)
    ds = load_dataset(dataset, truth=False)
    run_json = root / "run.json"
    ckpt = None
    # Every check comes before the first write: a refused command leaves the folder as it was.
    if resume:
        if not run_json.exists():
            raise RunError(f"{root}: nothing to resume (no run.json); drop --resume to start a new run")
        doc = _read_run_doc(root)
        mcfg = ModelConfig.from_dict(doc["model"])
        tcfg = resumed_config(TrainConfig.from_dict(doc["train"]), config)
        _check_same_dataset(doc, ds, dataset, root)
        if (root / "checkpoint.pt").exists():
            ckpt = _read_checkpoint(root / "checkpoint.pt", device)
    else:
        if run_json.exists() or (root / "checkpoint.pt").exists():
            raise RunError(f"{root}: a run already exists there; pass --resume to continue it or choose another folder")
        check_folder_output(root, "run", inputs=[dataset], flag=None)
        tcfg = config or TrainConfig()
        mcfg = model_config(ds.meta, tcfg.preset)  # type: ignore[arg-type]
    tcfg.validate()
    if mcfg.feature_dim != ds.meta.feature_dim:
        raise RunError(f"the run's model takes {mcfg.feature_dim}-d audio features but {dataset} has {ds.meta.feature_dim}-d ({ds.meta.feature_kind})")
    head_done = ckpt["head_step"] if ckpt else 0
    if stage == "torso" and head_done < tcfg.head_iters:
        raise RunError(f"stage 2 needs a finished stage 1 ({head_done}/{tcfg.head_iters} head iterations); run --stage head (with --resume) first")
    if tcfg.rays % ranks.world:
        raise RunError(f"{ranks.world} processes must split the {tcfg.rays} rays of a batch evenly; choose rays divisible by {ranks.world}")
    ensure_writable(root)
    devices = ranks.gather(str(device))
    ranks.barrier()  # every process has checked the folder before process 0 writes into it
    trainer = _Trainer(root, ds, mcfg, tcfg, device, progress, ranks)
    if ckpt is not None:
        trainer.load(ckpt)
    if ranks.main:
        _write_run(root, dataset, ds, mcfg, tcfg, {"world_size": ranks.world, "backend": ranks.backend, "devices": devices})
    ranks.barrier()
    budget = max_steps
    if stage in ("head", "all"):
        before = trainer.head_step
        trainer.head_stage(budget)
        if budget is not None:
            budget -= trainer.head_step - before
    if stage == "torso" or (stage == "all" and tcfg.torso_iters > 0 and (budget is None or budget > 0)):
        trainer.torso_stage(budget)
    if not (root / "checkpoint.pt").exists():
        trainer.save()
    ranks.barrier()
    return root


def _write_run(root: Path, dataset: str | Path, ds: TalkingHeadDataset, mcfg: ModelConfig, tcfg: TrainConfig, distributed: dict) -> None:
    """``run.json`` (with how the run is trained: processes, backend, devices) and the plate."""
    root.mkdir(parents=True, exist_ok=True)
    meta = {k: v for k, v in asdict(ds.meta).items() if k not in ("train", "test")}
    doc = {
        "format": RUN_FORMAT,
        "version": RUN_VERSION,
        "dataset": str(Path(dataset).resolve()),
        "dataset_sha256": ds.fingerprint(),
        "model": mcfg.to_dict(),
        "train": asdict(tcfg),
        "meta": meta,
        "distributed": distributed,
    }
    _write_json_atomic(root / "run.json", doc)
    shutil.copyfile(Path(dataset) / "background.png", root / "background.png")

