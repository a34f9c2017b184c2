"""A trained run, loaded: its model built from the latest checkpoint, its schedule and pose range.

The folder's files and ``run.json`` are :mod:`adnerf.formats.run_folder`'s (:class:`RunFolder`);
this module builds and writes what needs the model: :func:`load_run` gives a :class:`Run`,
:func:`write_run` writes ``run.json`` and the plate, and training (:mod:`adnerf.model.train`) is the
only writer.
"""

from __future__ import annotations

import json
import shutil
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..atomic import atomic_path
from ..lock import lock_owner
from ..formats.dataset import DatasetError, DatasetFolder, SceneMeta, TalkingHeadDataset, read_meta
from ..formats.run_folder import RUN_FORMAT, RUN_VERSION, RunError, RunFolder
from .pose_range import PoseRange
from .pose_refine import corrected_matrices
from .talking_head import ModelConfig, TalkingHead, migrate_state_dict
from .train_config import TrainConfig

__all__ = ["RESUMABLE", "RUN_FORMAT", "RUN_VERSION", "Run", "RunError", "load_run", "resumed_config", "stored_config", "stored_pose_range", "taught_pose_range", "write_run"]

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


def write_json_atomic(path: Path, doc: dict) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1))


def save_atomic(obj: object, path: Path) -> None:
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
        steps: Finished iterations by stage name (``{"head": n, "torso": m}``).
        meta: The dataset's ``meta.json`` content (camera, fps, boxes, feature kind).
        elapsed: Training seconds by stage name (``{"head": s, "torso": s}``), from the checkpoint.
        pose_range: The head poses the training frames covered (:mod:`adnerf.model.pose_range`);
            ``None`` for a run written before the range was stored whose dataset is gone.
        pose_corrections: The head-pose correction training learnt for each frame of its dataset
            ``(n_frames, 6)`` float64 (:mod:`adnerf.model.pose_refine`; zero for the frames it
            did not learn from), ``None`` for a run that kept the tracked poses.
    """

    root: Path
    dataset: Path
    model: TalkingHead
    train_config: TrainConfig
    steps: dict[str, int]
    meta: dict
    elapsed: dict = field(default_factory=dict)
    pose_range: PoseRange | None = None
    pose_corrections: np.ndarray | None = None

    def learnt_corrections(self, folder: str | Path, n_frames: int) -> np.ndarray | None:
        """The head-pose corrections ``(n_frames, 6)`` training learnt
        (:mod:`~adnerf.model.pose_refine`), when the dataset in ``folder``, of ``n_frames``
        frames, is the run's own; ``None`` for another dataset or a run that learnt none."""
        if self.pose_corrections is None or len(self.pose_corrections) != n_frames:
            return None
        try:
            same = Path(folder).resolve() == Path(self.dataset).resolve()
        except OSError:
            return None
        return self.pose_corrections if same else None

    def dataset_poses(self, poses: np.ndarray, frames: Sequence[int] | np.ndarray) -> np.ndarray:
        """The poses ``(N, 4, 4)`` the run gives frames ``frames`` of its own dataset, whose
        tracked poses are ``poses``: moved by the corrections training learnt for them (none for
        a run without; frames it did not learn from keep theirs)."""
        if self.pose_corrections is None:
            return np.asarray(poses, dtype=np.float64)
        return corrected_matrices(poses, self.pose_corrections[np.asarray(frames, dtype=np.int64)])

    @property
    def head_step(self) -> int:
        """Finished stage-1 iterations."""
        return self.steps.get("head", 0)

    @property
    def torso_step(self) -> int:
        """Finished stage-2 iterations."""
        return self.steps.get("torso", 0)

    @property
    def has_torso(self) -> bool:
        """Whether stage 2 ran at all."""
        return self.torso_step > 0

    @property
    def trained_layers(self) -> tuple[str, ...]:
        """The layers training has reached, in the model's order: those whose stage (the stage of
        the same name) ran at least one iteration, and the first stage's layer (the head) always."""
        first = next(iter(self.steps), "head")
        return tuple(name for name in self.model.layers if name == first or self.steps.get(name, 0) > 0)


def read_run_doc(root: Path) -> dict:
    """``run.json`` of a run folder, checked for format and version (:meth:`RunFolder.doc`)."""
    return RunFolder(root).doc()


def run_configs(doc: dict) -> tuple[ModelConfig, TrainConfig]:
    """The model and the training schedule of a run's ``run.json`` (:func:`read_run_doc`); a
    schedule key added after the run was written takes the value it trained with."""
    return ModelConfig.from_dict(doc["model"]), TrainConfig.from_stored(doc["train"])


def stored_config(root: str | Path) -> TrainConfig:
    """The training schedule stored in a run folder's ``run.json``."""
    return TrainConfig.from_stored(read_run_doc(Path(root))["train"])


CHECKPOINT_KEYS = ("model", "generator", "stages", "elapsed")
"""What a checkpoint holds: the model's weights, the random generator's state, each stage's
finished iterations and optimizer state by stage name (``{"head": {"step": n, "optimizer":
state}, ...}``) and the training seconds by stage name (and ``mouth_probe`` with the mouth target,
``pose_corrections`` with learnt poses)."""

OLD_CHECKPOINT_KEYS = ("model", "opt_head", "opt_torso", "generator", "head_step", "torso_step", "elapsed")
"""What a checkpoint held before the stages were named in it (:func:`migrate_checkpoint`)."""


def migrate_checkpoint(ckpt: dict) -> dict:
    """A checkpoint of the earlier layout (``head_step``, ``opt_head``, ``torso_step``,
    ``opt_torso``) with its stages under their names (:data:`CHECKPOINT_KEYS`); one of the current
    layout comes back unchanged."""
    if "stages" in ckpt or any(k not in ckpt for k in OLD_CHECKPOINT_KEYS):
        return ckpt
    out = {k: v for k, v in ckpt.items() if k not in ("opt_head", "opt_torso", "head_step", "torso_step")}
    out["stages"] = {name: {"step": ckpt[f"{name}_step"], "optimizer": ckpt[f"opt_{name}"]} for name in ("head", "torso")}
    return out


def stage_step(ckpt: dict, stage: str) -> int:
    """The finished iterations of ``stage`` in checkpoint content (0 for a stage it does not hold)."""
    return int(ckpt["stages"].get(stage, {}).get("step", 0))


def read_checkpoint(path: Path, device: str | torch.device) -> dict:
    """A checkpoint file's content; a missing, empty or damaged file is a :class:`RunError`."""
    if not path.exists():
        raise RunError(f"{path.parent}: no {path.name} yet (training has not written one); train with `adnerf train DATASET -o {path.parent}`")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # torch.load raises many types on a damaged file (EOFError, RuntimeError, UnpicklingError, ...)
        raise RunError(
            f"{path}: damaged or incomplete checkpoint ({type(exc).__name__}: {exc}); adnerf writes checkpoints atomically, "
            "so the file was changed outside adnerf: restore it, or train a new run into another folder"
        ) from exc
    ckpt = migrate_checkpoint(ckpt) if isinstance(ckpt, dict) else ckpt
    if not isinstance(ckpt, dict) or any(k not in ckpt for k in CHECKPOINT_KEYS):
        raise RunError(f"{path}: not an adnerf checkpoint (missing entries); restore it, or train a new run into another folder")
    return ckpt


def load_run(root: str | Path, device: str | torch.device = "cpu") -> Run:
    """Load a run folder's configuration and latest checkpoint (a warning says so when another
    process is training the run: its last checkpoint is what is read).

    Raises:
        RunError: Missing folder, ``run.json`` or checkpoint, a damaged one, or another format version.
    """
    root = Path(root)
    doc = read_run_doc(root)
    ckpt_path = RunFolder(root).checkpoint
    ckpt = read_checkpoint(ckpt_path, device)
    mcfg, tcfg = run_configs(doc)
    model = TalkingHead(mcfg).to(device)
    steps = {name: stage_step(ckpt, name) for name in ckpt["stages"]}
    load_model_state(model, ckpt["model"], ckpt_path, scheduled_smoothing(tcfg, steps.get("head", 0)))
    model.eval()
    owner = lock_owner(root)
    if owner is not None:  # read beside a training: its last complete checkpoint (written atomically)
        warnings.warn(f"{root} is being trained (process {owner.get('pid')} on {owner.get('host')}); using its last checkpoint, head step {steps.get('head', 0)}/{tcfg.head_iters}, torso step {steps.get('torso', 0)}/{tcfg.torso_iters}", stacklevel=2)
    fixes = ckpt.get("pose_corrections")
    corrections = None if fixes is None else fixes["delta"].detach().cpu().numpy().astype(np.float64)
    return Run(root, Path(doc["dataset"]), model, tcfg, steps, doc["meta"], ckpt["elapsed"], stored_pose_range(doc), corrections)


def taught_pose_range(poses: np.ndarray, meta: SceneMeta) -> PoseRange:
    """The pose range of a dataset's training frames: poses ``(N, 4, 4)`` and its :class:`SceneMeta`
    (the head box's width is the unit of the translation margin)."""
    return PoseRange.from_poses(poses[meta.train], meta.head_aabb[1][0] - meta.head_aabb[0][0])


def stored_pose_range(doc: dict) -> PoseRange | None:
    """A run's pose range: ``run.json``'s, or for a run written before it was stored, its dataset's
    (poses and training split), or ``None`` when that is gone or unreadable."""
    if "pose_range" in doc:
        try:
            return PoseRange.from_dict(doc["pose_range"])
        except ValueError as exc:
            raise RunError(f"the run's pose_range is damaged ({exc}); train a new run into another folder") from exc
    dataset = Path(doc.get("dataset", ""))
    try:
        return taught_pose_range(np.load(DatasetFolder(dataset).poses), read_meta(dataset))
    except (OSError, ValueError, DatasetError, IndexError):
        return None


def check_same_dataset(doc: dict, ds: TalkingHeadDataset, dataset: str | Path, root: Path) -> None:
    """Refuse to resume ``root`` on a dataset other than the one it was trained on."""
    meta = {k: v for k, v in ds.meta.to_dict().items() if k not in ("train", "test")}
    stored = doc.get("dataset_sha256")
    same = stored == ds.fingerprint() if stored else json.loads(json.dumps(meta)) == doc.get("meta")
    if not same:
        raise RunError(
            f"{root} was trained on another dataset ({doc.get('dataset')}) than {dataset}: its content differs. "
            f"A resume continues on the same data; resume with that dataset, or train a new run (-o NEW) on {dataset}"
        )


def scheduled_smoothing(tcfg: TrainConfig, head_step: int) -> bool:
    """Whether a schedule has switched AudioAttNet on after ``head_step`` finished stage-1 steps
    (step ``s`` smooths when ``s >= att_start * head_iters``)."""
    return head_step > tcfg.att_start * tcfg.head_iters


def load_model_state(model: TalkingHead, state: dict, path: Path, smoothing: bool) -> None:
    """Load weights, of the layers' layout or the earlier one (:func:`~adnerf.model.talking_head.migrate_state_dict`).

    A checkpoint from before occupancy grids existed leaves them unestimated; one from before the
    model held its audio-smoothing switch gets ``smoothing`` (what its schedule had switched on,
    :func:`scheduled_smoothing`).
    """
    missing, unexpected = model.load_state_dict(migrate_state_dict(state), strict=False)
    if "audio_smoothing" in missing:
        model.set_audio_smoothing(smoothing)
    missing = [k for k in missing if ".occupancy." not in k and k != "audio_smoothing"]
    if missing or unexpected:
        raise RunError(f"{path}: weights do not match the run's model (missing {missing[:3]}, unexpected {unexpected[:3]})")


def write_run(root: Path, dataset: str | Path, ds: TalkingHeadDataset, mcfg: ModelConfig, tcfg: TrainConfig, distributed: dict, extra: dict | None = None) -> None:
    """``run.json`` (with how the run is trained: processes, backend, devices; the pose range of
    the training frames; and ``extra``'s entries, e.g. whether the mouth target is used) and the plate."""
    root.mkdir(parents=True, exist_ok=True)
    meta = {k: v for k, v in ds.meta.to_dict().items() if k not in ("train", "test")}
    doc = {
        "format": RUN_FORMAT,
        "version": RUN_VERSION,
        "dataset": str(Path(dataset).resolve()),
        "dataset_sha256": ds.fingerprint(),
        "model": mcfg.to_dict(),
        "train": asdict(tcfg),
        "meta": meta,
        "distributed": distributed,
        "pose_range": taught_pose_range(ds.poses, ds.meta).to_dict(),
        **(extra or {}),
    }
    files = RunFolder(root)
    write_json_atomic(files.run_json, doc)
    shutil.copyfile(DatasetFolder(dataset).background, files.background)
