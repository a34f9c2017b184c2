"""How much a clip's audio tells about its mouth: the ceiling of lip sync that training can reach.

A radiance field driven by audio can only learn the mouth movements that the clip's audio
predicts. This module measures that on the dataset itself, before or without any training, from
the true inner-lip opening (dlib's landmarks of the true frames, ``landmarks.npy``) and the
audio:

- **Loudness**: the correlation of the opening with the loudness of the voiced band
  (:func:`~adnerf.audio.features.voiced_loudness`) and the shift that maximises it. In recorded
  speech the jaw opens for the loud vowels, so this is clearly positive near shift 0; a clip
  whose mouth was made by another system, or whose sound is offset, shows it.
- **Ridge**: a linear map from a frame's feature window (the windows the audio encoder reads,
  ``features.npy``) to its opening, fitted on some frames and scored on others by Pearson
  correlation. ``tail``: fitted on the training frames, scored on the held-out ones (what a
  trained run's held-out ``mouth_open_corr`` is measured on). ``cv``: blocked cross-validation,
  the clip cut into ``blocks`` contiguous blocks, each scored by a map fitted on the others minus
  ``guard`` frames on either side (neighbouring frames share audio windows). A long clip of
  one voice gives a ``cv`` well above zero; a short one does not, and then no audio encoder
  learns the mouth from it either (the encoder is not linear, but with a few hundred frames it
  overfits sooner than a ridge map does).

Conventions: frames are on the audio clock (frame ``i`` at ``i / fps`` seconds); offsets are in
frames, positive when the mouth moves *after* the sound (as :func:`~adnerf.evaluation.landmark_metrics.av_offset`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..ridge import blocked_cv_corr, blocked_folds, pearson, ridge_fit_predict  # the last three re-exported
from .landmark_metrics import av_offset, mouth_opening

if TYPE_CHECKING:
    from ..formats.dataset import SceneMeta
    from ..io import AudioTrack

__all__ = ["LipSignal", "audio_windows", "blocked_folds", "dataset_lip_signal", "lip_signal", "pearson", "ridge_fit_predict"]


@dataclass
class LipSignal:
    """What a clip's audio predicts about its mouth (:func:`lip_signal`).

    Attributes:
        frames: Frames measured.
        loudness_corr: Pearson correlation of the inner-lip opening with the voiced loudness at
            the same time; ``nan`` without audio.
        loudness_offset_frames: Shift in ``[-max_shift, max_shift]`` maximising that correlation
            (positive: the mouth moves after the sound).
        loudness_corr_at_offset: The correlation at that shift.
        ridge_tail_corr: Correlation over the held-out frames of the opening predicted by a ridge
            map fitted on the training frames; ``nan`` without a split.
        ridge_cv_corr: Mean over the blocks of the blocked cross-validated correlation (a block
            whose opening never changes has no correlation and is left out of the mean).
        ridge_cv_blocks: The per-block correlations, in clip order.
        encoder_tail_corr: Correlation over the held-out frames of the opening predicted by
            training's audio encoder trained on the training frames' opening alone, an ensemble
            of networks (:func:`~adnerf.evaluation.encoder_signal.encoder_signal`); ``nan``
            unless asked for (it trains networks: seconds to minutes).
        encoder_tail_single_corr: The same, the mean of the single networks' correlations.
    """

    frames: int
    loudness_corr: float
    loudness_offset_frames: int
    loudness_corr_at_offset: float
    ridge_tail_corr: float
    ridge_cv_corr: float
    ridge_cv_blocks: list[float]
    encoder_tail_corr: float = float("nan")
    encoder_tail_single_corr: float = float("nan")

    def to_dict(self) -> dict:
        """A JSON-serialisable dict (``nan`` as ``None``)."""
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()}


def lip_signal(
    windows: np.ndarray,
    opening: np.ndarray,
    *,
    loudness: np.ndarray | None = None,
    train: Sequence[int] | None = None,
    test: Sequence[int] | None = None,
    blocks: int = 6,
    guard: int = 8,
    max_shift: int = 5,
    strength: float = 0.1,
) -> LipSignal:
    """Measure how much the audio of a clip predicts its mouth opening.

    Args:
        windows: ``(N, 16, D)`` feature windows, one per frame (or ``(N, F)`` flat features).
        opening: ``(N,)`` true inner-lip opening per frame (pixels; any scale).
        loudness: ``(N,)`` voiced loudness per frame, or ``None`` (the loudness fields are ``nan``).
        train: Training frames for the tail figure; with ``test``, or both ``None``.
        test: Held-out frames for the tail figure.
        blocks: Cross-validation blocks.
        guard: Frames left out on either side of a test block (the windows' half width is 4
            video frames at 25 fps; 8 leaves room for the smoothing over neighbouring frames).
        max_shift: Largest loudness shift tried, frames.
        strength: Ridge penalty per fitted row (:func:`ridge_fit_predict`).

    Raises:
        ValueError: Mismatched lengths, non-finite values, or too few frames for the folds.
    """
    x = np.asarray(windows, np.float64)
    y = np.asarray(opening, np.float64)
    n = x.shape[0]
    x = x.reshape(n, -1)
    if y.shape != (n,):
        raise ValueError(f"one opening per window: {n} windows, openings of shape {y.shape}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("feature windows and openings must be finite (frames without a face have no opening)")
    if (train is None) != (test is None):
        raise ValueError("give both the training and the held-out frames, or neither")
    per_block = blocked_cv_corr(x, y, blocks, guard, strength)
    tail = float("nan")
    if train is not None and test is not None:
        tr, te = np.asarray(train, int), np.asarray(test, int)
        tail = pearson(ridge_fit_predict(x[tr], y[tr], x[te], strength), y[te])
    l_corr, l_off, l_at = float("nan"), 0, float("nan")
    if loudness is not None:
        loud = np.asarray(loudness, np.float64)
        if loud.shape != (n,):
            raise ValueError(f"one loudness per frame: {n} frames, loudness of shape {loud.shape}")
        l_corr = pearson(loud, y)
        k, l_at = av_offset(y, loud, max_shift)  # k > 0: the mouth at t + k matches the sound at t
        l_off = int(k)
    return LipSignal(n, float(l_corr), l_off, float(l_at), float(tail), float(np.nanmean(per_block)), [float(c) for c in per_block])


def audio_windows(root: str | Path, features: str) -> np.ndarray:
    """Feature windows ``(N, 16, D)`` of a dataset's frames computed again from its ``audio.wav``
    with another extractor, at the frame times ``i / fps`` where preprocessing placed them (its
    audio starts with frame 0); for the dataset's own extractor they are its ``features.npy`` up to
    the wav file's 16-bit rounding.

    Args:
        root: The dataset folder.
        features: ``"logmel"``, ``"phonemes"`` or ``"logmel+phonemes"`` (``wav2vec2`` needs a model).

    Raises:
        ValueError: Another extractor.
    """
    from ..formats.dataset import DatasetFolder, read_meta
    from ..io import read_audio

    return _windows_at_frames(read_audio(DatasetFolder(root).audio), read_meta(root), features)


def _windows_at_frames(audio: AudioTrack, meta: SceneMeta, features: str) -> np.ndarray:
    """:func:`audio_windows` of a dataset's audio and meta, already read."""
    from ..audio.features import BUILTIN_KINDS, FeatureSpec, speech_windows

    if features not in BUILTIN_KINDS:
        raise ValueError(f"features must be one of {', '.join(BUILTIN_KINDS)}; got {features!r}")
    return speech_windows(audio, np.arange(meta.n_frames) / meta.fps, FeatureSpec(kind=features))  # type: ignore[arg-type]


def dataset_lip_signal(
    root: str | Path,
    features: str | None = None,
    *,
    encoder_epochs: int = 0,
    encoder_seeds: int = 3,
    encoder_jitter: int = 0,
    progress: Callable[[int], None] | None = None,
    **kwargs: object,
) -> LipSignal:
    """:func:`lip_signal` of a dataset folder: its ``features.npy``, the opening of its
    ``landmarks.npy``, the voiced loudness of its ``audio.wav`` at the frame times, and its
    train / test split (``meta.json``). Preprocessing interpolates the landmarks of frames where
    no face was found, so every frame has an opening; a non-finite one is a ``ValueError``.

    Args:
        root: The dataset folder.
        features: An extractor of :data:`~adnerf.audio.features.BUILTIN_KINDS` whose windows
            are computed from ``audio.wav`` at the frame times ``i / fps`` (as preprocessing
            placed them) instead of reading ``features.npy``: which features carry this clip's
            mouth, without preprocessing it again. ``None``: the dataset's own.
        encoder_epochs: With a train / test split, also train ``encoder_seeds`` audio encoders for
            this many epochs on the training frames' opening and score them on the held-out
            frames (``encoder_tail_corr``); 0: not.
        encoder_seeds: Networks of that ensemble.
        encoder_jitter: Train them on windows moved by up to this many features either way, a
            shift drawn per sample (what ``TrainConfig.audio_jitter`` does in training); 0: not.
        progress: Called with 1 after each epoch of each network.
        **kwargs: :func:`lip_signal`'s settings.

    Raises:
        adnerf.formats.dataset.DatasetError: Not a dataset, or no ``landmarks.npy`` (``adnerf
            preprocess`` writes it; a synthetic scene has none).
    """
    from ..audio.features import voiced_loudness
    from ..io import read_audio
    from ..formats.dataset import DatasetError, DatasetFolder, read_meta

    root = Path(root)
    meta = read_meta(root)
    files = DatasetFolder(root)
    if not files.landmarks.exists():
        raise DatasetError(f"{root}: no {files.landmarks.name}; the lip signal needs the true frames' face landmarks (adnerf preprocess writes them)")
    audio = read_audio(files.audio)
    windows = np.load(files.features) if features is None else _windows_at_frames(audio, meta, features)
    landmarks = np.load(files.landmarks)
    if landmarks.shape != (meta.n_frames, 68, 2) or windows.shape[0] != meta.n_frames:
        raise DatasetError(f"{root}: landmarks {landmarks.shape} and features {windows.shape} do not match its {meta.n_frames} frames")
    loud = voiced_loudness(np.asarray(audio.samples, np.float64), audio.sample_rate, np.arange(meta.n_frames) / meta.fps)
    split = {"train": list(meta.train), "test": list(meta.test)} if meta.train and meta.test else {}
    opening = mouth_opening(landmarks)
    signal = lip_signal(windows, opening, loudness=loud, **split, **kwargs)  # type: ignore[arg-type]
    if encoder_epochs > 0 and split:
        from .encoder_signal import encoder_signal

        moved = None
        if encoder_jitter:
            from ..model.audio_jitter import moved_windows

            moved = moved_windows(root, meta if features is None else replace(meta, feature_kind=features), windows, encoder_jitter)
        enc = encoder_signal(windows, opening, split["train"], split["test"], epochs=encoder_epochs, seeds=encoder_seeds, moved=moved, progress=progress)
        signal = replace(signal, encoder_tail_corr=enc.ensemble_corr, encoder_tail_single_corr=enc.single_corr)
    return signal
