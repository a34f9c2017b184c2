"""The lip-signal ceiling: ridge maps against a slow reference, folds that never see their test
block, a mouth predictable from its audio against one that is not, the sign of the mouth's delay,
and training's audio encoder, which finds a mouth the ridge map misses and none in a shuffled one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adnerf.audio.features import voiced_loudness
from adnerf.cli import main
from adnerf.evaluation.encoder_signal import encoder_signal
from adnerf.evaluation.landmark_metrics import INNER_PAIRS
from adnerf.evaluation.lip_signal import audio_windows, blocked_folds, dataset_lip_signal, lip_signal, ridge_fit_predict
from adnerf.formats.dataset import DatasetFolder, load_dataset
from adnerf.synth import SynthConfig, synthesize


def _reference_ridge(x_fit: np.ndarray, y_fit: np.ndarray, x_pred: np.ndarray, strength: float) -> np.ndarray:
    """Minimise |A w - (y - mean y)|^2 + strength * n |w|^2 over standardised columns, by lstsq on
    the augmented system [A; sqrt(lam) I] w = [y; 0]."""
    n, d = x_fit.shape
    mean, std = x_fit.mean(0), x_fit.std(0)
    std[std == 0] = 1.0
    a = (x_fit - mean) / std
    aug = np.vstack([a, np.sqrt(strength * n) * np.eye(d)])
    rhs = np.concatenate([y_fit - y_fit.mean(), np.zeros(d)])
    w = np.linalg.lstsq(aug, rhs, rcond=None)[0]
    return (x_pred - mean) / std @ w + y_fit.mean()


@pytest.mark.parametrize("n, d", [(60, 12), (12, 60)])  # the primal and the dual form
def test_ridge_equals_the_augmented_least_squares(n: int, d: int) -> None:
    rng = np.random.default_rng(0)
    x, y, xp = rng.normal(size=(n, d)) * rng.uniform(0.1, 10, d), rng.normal(size=n), rng.normal(size=(7, d))
    x[:, 3] = 2.5  # a constant column
    xp[:, 3] = 2.5
    for strength in (0.01, 4.0):
        np.testing.assert_allclose(ridge_fit_predict(x, y, xp, strength), _reference_ridge(x, y, xp, strength), rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="positive"):
        ridge_fit_predict(x, y, xp, 0.0)
    with pytest.raises(ValueError, match="ridge needs"):
        ridge_fit_predict(x, y[:-1], xp)


def test_folds_tile_the_clip_and_keep_the_guard() -> None:
    folds = blocked_folds(100, 6, 8)
    tested = np.concatenate([te for _, te in folds])
    np.testing.assert_array_equal(tested, np.arange(100))  # each frame tested once, in clip order
    for fit, te in folds:
        gap = np.abs(fit[:, None] - te[None, :]).min()
        assert gap == 9  # the nearest fitted frame is guard + 1 away
        assert len(fit) + len(te) + 16 - 8 * (te[0] == 0) - 8 * (te[-1] == 99) == 100
    with pytest.raises(ValueError, match="too few"):
        blocked_folds(24, 6, 8)  # 4 tested, but only 4 fitted beside a middle block


def _windows(n: int, rng: np.random.Generator) -> np.ndarray:
    """Feature windows of a smooth stationary feature track (each feature an AR(1) series, as
    speech features are), cut as the extractor's overlapping windows."""
    noise = rng.normal(size=(n + 16, 6))
    track = np.zeros_like(noise)
    for i in range(1, len(track)):
        track[i] = 0.7 * track[i - 1] + noise[i]
    return np.stack([track[i : i + 16] for i in range(n)])


def test_a_mouth_the_audio_predicts_scores_high_and_a_shuffled_one_does_not() -> None:
    rng = np.random.default_rng(1)
    n = 300
    windows = _windows(n, rng)
    opening = windows[:, 8, 2] - 0.5 * windows[:, 6, 4] + 0.1 * rng.normal(size=n)
    split = {"train": range(255), "test": range(255, n)}
    good = lip_signal(windows, opening, **split)
    assert good.ridge_cv_corr > 0.9 and good.ridge_tail_corr > 0.9 and min(good.ridge_cv_blocks) > 0.9
    bad = lip_signal(windows, rng.permutation(opening), **split)
    assert abs(bad.ridge_cv_corr) < 0.25 and abs(bad.ridge_tail_corr) < 0.5
    assert np.isnan(good.loudness_corr) and good.to_dict()["loudness_corr"] is None  # no audio given
    with pytest.raises(ValueError, match="one opening per window"):
        lip_signal(windows, opening[:-1])
    with pytest.raises(ValueError, match="or neither"):
        lip_signal(windows, opening, train=range(10))


@pytest.mark.parametrize("late", [3, -2])
def test_the_loudness_shift_is_the_mouths_delay(late: int) -> None:
    """Vowel bursts of a 300 Hz tone; the mouth opens ``late`` frames after each (before, if < 0)."""
    rate, fps, n = 16000, 25.0, 250
    rng = np.random.default_rng(2)
    t = np.arange(int(n / fps * rate)) / rate
    level = np.repeat(rng.uniform(0, 1, n // 5) > 0.5, 5).astype(float)  # on / off in 200 ms steps
    envelope = np.interp(t, np.arange(n) / fps, np.convolve(level, np.ones(3) / 3, "same"))
    samples = envelope * np.sin(2 * np.pi * 300 * t)
    loud = voiced_loudness(samples, rate, np.arange(n) / fps)
    opening = np.roll(loud, late) + 0.02 * rng.normal(size=n)  # the mouth at t shows the sound at t - late
    signal = lip_signal(_windows(n, rng), opening, loudness=loud)
    assert signal.loudness_offset_frames == late and signal.loudness_corr_at_offset > 0.9
    assert signal.loudness_corr < signal.loudness_corr_at_offset


def test_a_datasets_lip_signal_from_features_computed_again(tmp_path: Path) -> None:
    """``features=``: windows computed from the dataset's audio at the frame times ``i / fps`` are
    the ones preprocessing stored, up to the wav file's rounding (one feature early or late
    differs by far more), and another extractor is measured on the same frames."""
    data = synthesize(tmp_path / "data", SynthConfig(seconds=3.0, size=32, voice="formant", seed=3))
    stored = np.load(DatasetFolder(data).features)  # the synthetic scene stores log-mel
    again = audio_windows(data, "logmel")
    assert again.shape == stored.shape and np.median(np.abs(again - stored)) < 1e-3 and np.abs(again - stored).max() < 1.0
    assert np.median(np.abs(again[1:] - stored[:-1])) > 0.1  # what a frame's offset would read
    _with_jaw_landmarks(data)
    own = dataset_lip_signal(data, blocks=3, guard=2)
    assert own.ridge_cv_corr > 0.5  # its jaw is its loudness
    both = dataset_lip_signal(data, "logmel+phonemes", blocks=3, guard=2)
    assert both.frames == own.frames and both.ridge_cv_corr != own.ridge_cv_corr
    with pytest.raises(ValueError, match="features must be one of"):
        dataset_lip_signal(data, "wav2vec2")


def _with_jaw_landmarks(data: Path) -> None:
    """Landmarks whose inner lips open with the synthetic scene's jaw."""
    jaw = load_dataset(data).truth.jaw
    landmarks = np.zeros((len(jaw), 68, 2))
    landmarks[:, [b for _, b in INNER_PAIRS], 1] = 1.0 + 10.0 * jaw[:, None]
    np.save(DatasetFolder(data).landmarks, landmarks)


def test_a_datasets_encoder_signal_beside_its_ridge_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``encoder_epochs``: the encoder's held-out figure joins the ridge figures, which stay as
    they are without it; ``--encoder`` prints it and refuses a negative count."""
    data = synthesize(tmp_path / "data", SynthConfig(seconds=3.0, size=32, voice="formant", seed=5))  # its held-out jaw moves
    _with_jaw_landmarks(data)
    plain = dataset_lip_signal(data, blocks=3, guard=2)
    assert np.isnan(plain.encoder_tail_corr) and plain.to_dict()["encoder_tail_corr"] is None  # not asked for
    epochs: list[int] = []
    enc = dataset_lip_signal(data, blocks=3, guard=2, encoder_epochs=2, encoder_seeds=2, progress=epochs.append)
    assert len(epochs) == 4 and np.isfinite(enc.encoder_tail_corr) and np.isfinite(enc.encoder_tail_single_corr)
    assert (enc.ridge_tail_corr, enc.ridge_cv_corr) == (plain.ridge_tail_corr, plain.ridge_cv_corr)
    moved = dataset_lip_signal(data, blocks=3, guard=2, encoder_epochs=2, encoder_seeds=2, encoder_jitter=1)
    assert np.isfinite(moved.encoder_tail_corr) and moved.encoder_tail_corr != enc.encoder_tail_corr  # trained on moved windows
    assert main(["lip-signal", str(data), "--encoder", "-1"]) == 2
    assert main(["lip-signal", str(data), "--encoder-jitter", "1"]) == 2  # without --encoder
    assert main(["lip-signal", str(data), "--encoder", "1", "--encoder-jitter", "99"]) == 2
    assert main(["lip-signal", str(data), "--blocks", "3", "--guard", "2", "--encoder", "1"]) == 0
    assert "encoder -> opening, held-out corr (3 nets)" in capsys.readouterr().out


def test_the_encoder_finds_a_mouth_the_ridge_map_misses_and_none_in_a_shuffled_one() -> None:
    rng = np.random.default_rng(4)
    n = 600
    windows = _windows(n, rng)
    opening = np.abs(windows[:, 8, 2]) + 0.1 * rng.normal(size=n)  # opens for a feature's either sign
    split = {"train": range(500), "test": range(500, n)}
    found = encoder_signal(windows, opening, **split, epochs=30, seeds=2, lr=3e-3)
    ridge = lip_signal(windows, opening, **split).ridge_tail_corr
    assert found.ensemble_corr > 0.8 and found.single_corr > 0.7 and ridge < 0.5
    assert (found.seeds, found.epochs) == (2, 30)
    shuffled = encoder_signal(windows, rng.permutation(opening), **split, epochs=30, seeds=2, lr=3e-3)
    assert abs(shuffled.ensemble_corr) < 0.35  # what training on the held-out frames would not give
    again = encoder_signal(windows, opening, **split, epochs=30, seeds=2, lr=3e-3)
    assert again == found  # seeded


def test_the_encoder_refuses_what_it_cannot_measure() -> None:
    rng = np.random.default_rng(5)
    windows, opening = _windows(40, rng), rng.normal(size=40)
    split = {"train": range(30), "test": range(30, 40)}
    with pytest.raises(ValueError, match=r"windows \(N, 16, D\)"):
        encoder_signal(windows[:, :8], opening, **split)
    with pytest.raises(ValueError, match="one opening per window"):
        encoder_signal(windows, opening[:-1], **split)
    with pytest.raises(ValueError, match="finite"):
        encoder_signal(windows, np.where(np.arange(40) == 3, np.nan, opening), **split)
    with pytest.raises(ValueError, match="positive"):
        encoder_signal(windows, opening, **split, epochs=0)
    with pytest.raises(ValueError, match="two training and two held-out"):
        encoder_signal(windows, opening, train=range(30), test=[35])
    with pytest.raises(ValueError, match="does not vary"):
        encoder_signal(windows, np.ones(40), **split)
    with pytest.raises(ValueError, match="moved windows"):
        encoder_signal(windows, opening, **split, moved=windows[None, :-1])
