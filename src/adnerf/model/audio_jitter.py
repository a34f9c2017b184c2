"""The training frames' speech windows moved in time: the audio a stage-1 step reads, jittered.

A mouth does not follow its sound to the 20 ms of one speech feature: the jaw leads some sounds
and trails others, and the landmarks that measure it are themselves uncertain by a frame. An
encoder trained on each frame's one window learns that window's exact content; trained on windows
moved by a few features either way (:attr:`~adnerf.model.train_config.TrainConfig.audio_jitter`)
it learns the codes that neighbouring audio also gives, as image augmentation teaches a network
what a small shift leaves unchanged.

The moved windows are cut again from the dataset's audio (``audio.wav``) by the dataset's own
extractor at the frame times ``i / fps + s / 50`` (where preprocessing placed frame ``i``, moved
by ``s`` features); shift 0 is the dataset's stored windows themselves. All shifts are made once,
before training: ``2 * audio_jitter + 1`` copies of the windows (for one minute of footage at
30 fps with log-mel and phonemes, 26 MB each).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..audio.features import BUILTIN_KINDS, FEATURE_RATE, WINDOW, FeatureSpec, speech_windows
from ..formats.dataset import DatasetFolder, SceneMeta, TalkingHeadDataset
from ..io import read_audio

__all__ = ["MAX_AUDIO_JITTER", "AudioJitterError", "jittered_windows", "moved_windows"]

MAX_AUDIO_JITTER = WINDOW // 2
"""The largest shift, in features: half a window (a larger one reads another sound)."""


class AudioJitterError(ValueError):
    """The dataset's windows cannot be cut again from its audio (an imported or model kind)."""


def moved_windows(root: str | Path, meta: SceneMeta, stored: np.ndarray, jitter: int) -> np.ndarray:
    """Every frame's feature window moved by each shift in ``[-jitter, jitter]`` features.

    Args:
        root: The dataset folder (its ``audio.wav``).
        meta: Its meta (``feature_kind``, ``fps``, ``n_frames``).
        stored: Its stored windows ``(N, 16, D)`` (``features.npy``), shift 0.
        jitter: Largest shift in features, ``1 .. MAX_AUDIO_JITTER``.

    Returns:
        ``(2 * jitter + 1, N, 16, D)`` float32 windows; row ``jitter + s`` holds the windows moved
        by ``s`` features (later audio for ``s > 0``), row ``jitter`` the stored ones.

    Raises:
        AudioJitterError: The dataset's features are not of a kind adnerf computes from its audio,
            or the windows cut again do not have the stored windows' shape.
        ValueError: ``jitter`` out of range.
    """
    if not 1 <= jitter <= MAX_AUDIO_JITTER:
        raise ValueError(f"the audio jitter is 1 to {MAX_AUDIO_JITTER} features; got {jitter}")
    kind = meta.feature_kind
    if kind not in BUILTIN_KINDS:
        raise AudioJitterError(f"{root}: the windows are cut again from the dataset's audio, which adnerf can do for {', '.join(BUILTIN_KINDS)} features, not {kind!r}")
    audio = read_audio(DatasetFolder(root).audio)
    times = np.arange(meta.n_frames) / meta.fps
    spec = FeatureSpec(kind=kind)  # type: ignore[arg-type]
    stored = np.asarray(stored, dtype=np.float32)
    rows = []
    for s in range(-jitter, jitter + 1):
        moved = stored if s == 0 else speech_windows(audio, times + s / FEATURE_RATE, spec).astype(np.float32)
        if moved.shape != stored.shape:
            raise AudioJitterError(f"{root}: its audio's {kind} windows are {moved.shape}, its stored windows {stored.shape}; preprocess it again")
        rows.append(moved)
    return np.stack(rows)


def jittered_windows(ds: TalkingHeadDataset, jitter: int, device: str | torch.device = "cpu") -> torch.Tensor:
    """:func:`moved_windows` of a loaded dataset, as a float32 tensor on ``device``."""
    return torch.from_numpy(moved_windows(ds.root, ds.meta, ds.features, jitter)).to(device)
