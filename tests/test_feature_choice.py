"""preprocessing's ``--features auto``: the phonemes are added beside the log-mel only where the
log-mel predicts the training frames' mouth opening."""

from __future__ import annotations

import numpy as np
import pytest

from adnerf.preprocess.feature_choice import choose_features
from adnerf.preprocess.pipeline import PreprocessConfig, PreprocessError

N, TRAIN = 300, list(range(255))


def _landmarks(opening: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``(N, 68, 2)`` landmarks whose inner-lip pairs (61-67, 62-66, 63-65) are ``opening``
    pixels apart, eye corners 40 px apart, and a mouth width that varies a little."""
    lm = np.zeros((len(opening), 68, 2))
    lm[:, 36], lm[:, 45] = (30.0, 40.0), (70.0, 40.0)
    width = 20.0 + 0.5 * rng.standard_normal(len(opening))
    lm[:, 48, 0], lm[:, 54, 0] = 50.0 - width / 2, 50.0 + width / 2
    lm[:, 48:55, 1] = 70.0
    for upper, lower in ((61, 67), (62, 66), (63, 65)):
        lm[:, upper] = (45.0 + 5 * (upper - 61), 70.0)
        lm[:, lower] = (45.0 + 5 * (upper - 61), 70.0)
        lm[:, lower, 1] += opening
    return lm


def _windows(rng: np.random.Generator, d: int) -> np.ndarray:
    return rng.standard_normal((N, 16, d)).astype(np.float32)


def _opening_from(windows: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An opening that the windows' middle rows predict, with a little noise."""
    return 4.0 + windows[:, 8, :3].sum(axis=1) + 0.3 * rng.standard_normal(N)


def test_phonemes_are_added_where_the_log_mel_predicts_the_opening() -> None:
    rng = np.random.default_rng(0)
    logmel, phonemes = _windows(rng, 6), _windows(rng, 4)
    choice = choose_features(logmel, phonemes, _landmarks(_opening_from(logmel, rng), rng), TRAIN, 0.2)
    assert choice.kind == "logmel+phonemes" and choice.doc["logmel_signal"] > 0.8
    # Log-mel first, then the phonemes: the order the "logmel+phonemes" extractor gives.
    np.testing.assert_array_equal(choice.windows, np.concatenate([logmel, phonemes], axis=-1))


def test_log_mel_alone_where_it_does_not_predict_the_opening() -> None:
    rng = np.random.default_rng(1)
    logmel, phonemes = _windows(rng, 6), _windows(rng, 4)
    # The opening follows the phonemes, not the log-mel: the log-mel's measure decides (the
    # richer windows would vouch for themselves), so the phonemes stay out.
    choice = choose_features(logmel, phonemes, _landmarks(_opening_from(phonemes, rng), rng), TRAIN, 0.2)
    assert choice.kind == "logmel" and choice.windows is logmel
    assert abs(choice.doc["logmel_signal"]) < 0.2 and "under 0.2" in choice.doc["why"]
    # A bar at -1 takes any measured signal.
    assert choose_features(logmel, phonemes, _landmarks(_opening_from(phonemes, rng), rng), TRAIN, -1.0).kind == "logmel+phonemes"


def test_the_signal_is_read_on_training_frames_only() -> None:
    rng = np.random.default_rng(2)
    logmel, phonemes = _windows(rng, 6), _windows(rng, 4)
    train = list(range(N // 2))
    opening = 4.0 + 0.5 * rng.standard_normal(N)
    opening[N // 2 :] = _opening_from(logmel, rng)[N // 2 :]  # only the frames after the training ones follow the log-mel
    assert choose_features(logmel, phonemes, _landmarks(opening, rng), train, 0.2).kind == "logmel"
    assert choose_features(logmel, phonemes, _landmarks(opening, rng), list(range(N)), 0.2).doc["logmel_signal"] > 0.2


def test_without_a_usable_mouth_the_log_mel_stays_alone() -> None:
    rng = np.random.default_rng(3)
    logmel, phonemes = _windows(rng, 6), _windows(rng, 4)
    none = choose_features(logmel, phonemes, None, TRAIN, 0.2)
    assert none.kind == "logmel" and none.doc["logmel_signal"] is None and "no landmarks" in none.doc["why"]
    still = choose_features(logmel, phonemes, _landmarks(np.full(N, 3.0), rng), TRAIN, 0.2)  # a mouth that never moves
    assert still.kind == "logmel" and "does not vary" in still.doc["why"]
    few = choose_features(logmel[:20], phonemes[:20], _landmarks(_opening_from(logmel, rng)[:20], rng), list(range(17)), 0.2)
    assert few.kind == "logmel" and "too few" in few.doc["why"]
    with pytest.raises(ValueError, match="same frames"):
        choose_features(logmel, phonemes[:-1], None, TRAIN, 0.2)


def test_auto_min_signal_is_a_correlation() -> None:
    with pytest.raises(PreprocessError, match="auto_min_signal"):
        PreprocessConfig(features="auto", auto_min_signal=1.5).validate()
    PreprocessConfig(features="auto").validate()
