"""The run folder's files: what training writes and rendering, evaluation and resuming read.

A run folder holds ``run.json`` (format and version, the dataset's path and fingerprint, the model
and training configuration, the dataset's camera and audio metadata without its split, how it was
trained, the head poses the training frames covered), ``background.png`` (the dataset's plate),
``checkpoint.pt`` (model, optimisers, random generator, finished steps and training seconds;
written atomically) and ``log.jsonl`` (one JSON object per logged iteration); any other file
there is not read.

:class:`RunFolder` names these files and reads the parts that need no model: ``run.json``
(checked for format and version), its scene metadata as a :class:`~adnerf.formats.dataset.SceneMeta`
and the checkpoint's training seconds. Building the model from a checkpoint is :func:`adnerf.model.run_folder.load_run`'s.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from .dataset import SceneMeta, meta_from_dict

__all__ = ["RUN_FORMAT", "RUN_VERSION", "RunError", "RunFolder", "scene_meta"]

RUN_FORMAT = "adnerf-run"
RUN_VERSION = 1


class RunError(RuntimeError):
    """A run folder is missing, incomplete, of another version, or would be overwritten."""


@dataclass(frozen=True)
class RunFolder:
    """Where each file of a run folder lies, and the run's stored description.

    Attributes:
        root: The run folder (it need not exist yet: training names the files it will write).
    """

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def run_json(self) -> Path:
        return self.root / "run.json"

    @property
    def checkpoint(self) -> Path:
        return self.root / "checkpoint.pt"

    @property
    def log(self) -> Path:
        return self.root / "log.jsonl"

    @property
    def background(self) -> Path:
        """The plate the run renders over by default (a copy of its dataset's)."""
        return self.root / "background.png"

    def is_run(self) -> bool:
        """Whether training has started here (``run.json`` is written before the first step)."""
        return self.run_json.exists()

    def doc(self) -> dict:
        """``run.json``, checked for format and version.

        Raises:
            RunError: No ``run.json``, an unreadable one, or another format or version.
        """
        path = self.run_json
        if not path.exists():
            raise RunError(f"{self.root}: not an adnerf run (no {path.name}); train one with `adnerf train DATASET -o {self.root}`")
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise RunError(f"{path}: unreadable or damaged ({exc}); train a new run into another folder") from exc
        if not isinstance(doc, dict) or doc.get("format") != RUN_FORMAT or doc.get("version") != RUN_VERSION:
            found = (doc.get("format"), doc.get("version")) if isinstance(doc, dict) else (None, None)
            raise RunError(f"{path}: format {found[0]!r} version {found[1]!r}; this adnerf reads {RUN_FORMAT} version {RUN_VERSION}")
        return doc

    def meta(self) -> SceneMeta:
        """The dataset's scene description as stored in ``run.json``. A run does not store the
        dataset's split, so every frame counts as a training frame here."""
        return scene_meta(self.doc()["meta"])

    def elapsed(self) -> dict:
        """Training seconds per stage (``{"head": s, "torso": s}``) in the latest checkpoint.

        Raises:
            RunError: No checkpoint yet.
        """
        if not self.checkpoint.exists():
            raise RunError(f"{self.root}: no {self.checkpoint.name} yet (training has not written one)")
        return dict(torch.load(self.checkpoint, map_location="cpu", weights_only=False)["elapsed"])


def scene_meta(stored: dict) -> SceneMeta:
    """A :class:`SceneMeta` from a run's stored metadata (``run.json``'s ``meta``: the dataset's,
    split left out), every frame a training frame."""
    return meta_from_dict({**stored, "train": list(range(int(stored["n_frames"]))), "test": []})
