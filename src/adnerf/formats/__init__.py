"""The folders adnerf writes and reads, and where it may write them.

* :mod:`.dataset`: the dataset folder (``adnerf preprocess``, ``synth``, ``import-adnerf`` write
  it; training, rendering and evaluation read it): :class:`~.dataset.DatasetFolder` names its
  files, :class:`~.dataset.SceneMeta` describes the scene, :func:`~.dataset.load_dataset` /
  :func:`~.dataset.save_dataset` read and write it, with its label values and split.
* :mod:`.run_folder`: the run folder training writes: :class:`~.run_folder.RunFolder` names its
  files and reads ``run.json`` and the log.
* :mod:`.outputs`: the checks every command makes before it writes a file or folder.

This room is the only place that spells the file names of either folder; it sits below every
room that reads them (``model``, ``preprocess``, ``evaluation``, ``commands``, ``bench``).
"""

from .dataset import (
    LABEL_BACKGROUND,
    LABEL_HEAD,
    LABEL_TORSO,
    DatasetError,
    DatasetFolder,
    SceneMeta,
    TalkingHeadDataset,
    load_dataset,
    read_meta,
    save_dataset,
)
from .run_folder import RunError, RunFolder

__all__ = [
    "LABEL_BACKGROUND",
    "LABEL_HEAD",
    "LABEL_TORSO",
    "DatasetError",
    "DatasetFolder",
    "SceneMeta",
    "TalkingHeadDataset",
    "load_dataset",
    "read_meta",
    "save_dataset",
    "RunError",
    "RunFolder",
]
