"""Which audio features a dataset gets under ``--features auto``: the log-mel alone, or the
phonemes beside it (``"logmel+phonemes"``, :mod:`adnerf.audio.features`).

The log-mel says how loud and bright a moment of speech is, the phoneme recogniser which sound is
being made. Beside the log-mel the phonemes raise how well a minute of footage's audio predicts
its mouth; from a clip whose audio does not predict its mouth they only give the field more sounds
to learn that do not come back in held-out speech (``docs/decisions.md``, *Phoneme evidence beside
the log-mel*). So the clip decides by its own measure: the cross-validated correlation of a ridge
map from the log-mel windows with the training frames' inner-lip opening
(:func:`adnerf.model.mouth_target.opening_signal`, the measure that also gates the mouth target),
read on the log-mel alone so that the richer windows cannot vouch for themselves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..model.mouth_target import mouth_targets, opening_signal

__all__ = ["FeatureChoice", "choose_features"]


@dataclass
class FeatureChoice:
    """The features a dataset gets.

    Attributes:
        windows: ``(N, 16, D)`` float32 feature windows: the log-mel's ``D = 80``, or with the
            phonemes' after them.
        kind: ``"logmel"`` or ``"logmel+phonemes"``
            (:data:`adnerf.audio.features.FEATURE_KINDS`).
        doc: Why, for the preprocessing report: ``kind``, ``min_signal``, ``logmel_signal``
            (``None`` where it cannot be measured) and, where the phonemes are left out, ``why``.
    """

    windows: np.ndarray
    kind: str
    doc: dict = field(default_factory=dict)


def choose_features(logmel: np.ndarray, phonemes: np.ndarray, landmarks: np.ndarray | None, train: Sequence[int], min_signal: float) -> FeatureChoice:
    """Log-mel windows, with the phoneme windows beside them where the log-mel predicts the
    training frames' mouth opening at ``min_signal`` or more.

    Args:
        logmel: ``(N, 16, D1)`` log-mel windows of every frame.
        phonemes: ``(N, 16, D2)`` phoneme windows of the same frames.
        landmarks: ``(N, 68, 2)`` face landmarks in pixels, or ``None`` (not known: log-mel).
        train: The training frames (the signal is measured on them only).
        min_signal: The cross-validated correlation from which the phonemes are added, in [-1, 1].

    Raises:
        ValueError: The two windows do not cover the same frames.
    """
    if logmel.shape[:2] != phonemes.shape[:2]:
        raise ValueError(f"log-mel windows {logmel.shape} and phoneme windows {phonemes.shape} do not cover the same frames")
    doc: dict = {"kind": "logmel", "min_signal": min_signal, "logmel_signal": None}

    def logmel_only(why: str) -> FeatureChoice:
        return FeatureChoice(logmel, "logmel", {**doc, "why": why})

    if landmarks is None:
        return logmel_only("no landmarks: the mouth's opening is not known")
    try:
        targets, valid = mouth_targets(landmarks, train)
    except ValueError as exc:  # e.g. a mouth that never moves
        return logmel_only(f"no mouth target: {exc}")
    signal = opening_signal(logmel, targets, valid, train)
    if math.isnan(signal):
        return logmel_only("the training frames are too few to cross-validate the log-mel's signal")
    doc["logmel_signal"] = round(signal, 4)
    if signal < min_signal:
        return logmel_only(f"the log-mel predicts the training frames' mouth opening at {signal:.2f}, under {min_signal:g}: the phonemes would add sounds the mouth does not follow")
    both = np.concatenate([logmel, phonemes], axis=-1)
    return FeatureChoice(both, "logmel+phonemes", {**doc, "kind": "logmel+phonemes"})
