"""Metrics of the real-clip benchmark: landmark distance, lip sync and its offset, head-region
PSNR, LPIPS from local weights, and ``adnerf bench real`` end to end on a small synthetic clip."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from adnerf.bench.real import HEAD_SHARE, bench_real, fitted_schedule, plot_mouth_opening, schedule_config
from adnerf.bench.voices import mouth_follow
from adnerf.cli import main
from adnerf.evaluation.evaluate import head_metrics
from adnerf.evaluation.landmark_metrics import (
    amplitude,
    av_offset,
    landmark_metrics,
    mouth_opening,
)
from adnerf.evaluation.lpips import CHANNELS, AlexFeatures, find_lpips, load_lpips
from adnerf.evaluation.syncnet import SyncNet
from adnerf.io import read_video
from adnerf.synth import SynthConfig, synthesize


def _talking_landmarks(n: int = 40, seed: int = 0) -> np.ndarray:
    """68 landmarks per frame of a face whose inner lips open and close irregularly."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(20, 80, size=(68, 2))
    base[0], base[16] = (10.0, 50.0), (90.0, 50.0)  # face width 80 px
    opening = np.abs(np.convolve(rng.normal(size=n + 4), np.ones(5) / 5, mode="valid")) * 6
    lms = np.repeat(base[None], n, axis=0)
    for upper, lower in ((61, 67), (62, 66), (63, 65)):
        lms[:, upper] = (50.0, 60.0)
        lms[:, lower, 0] = 50.0
        lms[:, lower, 1] = 60.0 + opening
    return lms


def test_landmark_metrics_known_answers() -> None:
    true = _talking_landmarks()
    same = landmark_metrics(true, true)
    assert same.lmd_mouth_px == 0.0 and same.lmd_all_px == 0.0 and same.mouth_open_corr == pytest.approx(1.0) and same.av_offset_frames == 0
    np.testing.assert_allclose(mouth_opening(true), true[:, 66, 1] - 60.0)
    moved = true.copy()
    moved[:, 48:68] += (3.0, 4.0)  # the mouth 5 px off
    m = landmark_metrics(moved, true)
    assert m.lmd_mouth_px == pytest.approx(5.0) and m.lmd_all_px == pytest.approx(5.0 * 20 / 68)
    assert m.face_width_px == pytest.approx(80.0) and m.lmd_mouth == pytest.approx(5.0 / 80.0)
    # Moving the whole mouth leaves its shape right; the still mouth is wrong by its moving lips.
    assert m.lmd_mouth_shape_px == pytest.approx(0.0, abs=1e-12) and same.lmd_mouth_shape_px == 0.0
    # Only the three lower inner-lip points move (by the opening o_t, in y): centred on the mouth's
    # centroid, those three move by (1 - 3/20) (o_t - mean o) and the other 17 by -3/20 of it.
    d = np.abs(mouth_opening(true) - mouth_opening(true).mean())
    still = float((3 * (1 - 3 / 20) + 17 * 3 / 20) / 20 * d.mean())
    assert m.lmd_mouth_still_px == pytest.approx(still) and still > 0.2
    # A mouth that never opens scores the still mouth's figure when it holds the mean shape.
    held = true.copy()
    held[:, 48:68] = true[:, 48:68].mean(axis=0)
    held[:, 48:68] += true[:, 48:68].mean(axis=1, keepdims=True) - held[:, 48:68].mean(axis=1, keepdims=True)
    assert landmark_metrics(held, true).lmd_mouth_shape_px == pytest.approx(still)
    # A render whose mouth moves 2 frames late: the offset says +2, the other way round -2.
    late = np.concatenate([true[:2], true[:-2]])
    assert landmark_metrics(late, true).av_offset_frames == 2
    early = np.concatenate([true[2:], true[-2:]])
    assert landmark_metrics(early, true).av_offset_frames == -2
    k, c = av_offset(mouth_opening(late), mouth_opening(true))
    assert k == 2 and c == pytest.approx(1.0)
    # The amplitude: the truth against itself 1 and 1; a mouth that opens half as wide (about its
    # own mean) 0.5 and 0.5 whatever its correlation says (1); one drawn upside down -1 and 1.
    assert same.mouth_open_slope == pytest.approx(1.0) and same.mouth_open_std_ratio == pytest.approx(1.0)
    half = true.copy()
    o = mouth_opening(true)
    half[:, [67, 66, 65], 1] -= 0.5 * (o - o.mean())[:, None]
    h = landmark_metrics(half, true)
    assert h.mouth_open_slope == pytest.approx(0.5) and h.mouth_open_std_ratio == pytest.approx(0.5) and h.mouth_open_corr == pytest.approx(1.0)
    assert amplitude(-o, o) == pytest.approx((-1.0, 1.0))
    # Noise on a full-width mouth keeps the slope near 1 and raises the ratio: the two differ.
    noisy = o + np.random.default_rng(0).normal(0, o.std(), len(o))
    slope, ratio = amplitude(noisy, o)
    assert abs(slope - 1.0) < 0.35 and ratio > 1.2
    assert all(np.isnan(amplitude(o, np.ones_like(o))))
    with pytest.raises(ValueError):
        landmark_metrics(true[:, :60], true[:, :60])


def test_head_psnr_of_a_known_error() -> None:
    rng = np.random.default_rng(1)
    target = rng.integers(20, 230, size=(3, 16, 16, 3), dtype=np.uint8)
    labels = np.zeros((3, 16, 16), np.uint8)
    labels[:, 2:12, 3:13] = 1
    pred = target.copy()
    pred[labels == 1] += 10  # an error of 10 levels on every head pixel, none elsewhere
    pred[labels == 0] = 0  # off the head nothing counts
    psnr, ssim = head_metrics(pred, target, labels)
    assert psnr == pytest.approx(-10 * math.log10((10 / 255) ** 2))
    assert ssim is not None and ssim < 1.0
    assert head_metrics(target, target, labels)[0] == 100.0  # identical: the cap
    assert head_metrics(pred, target, np.zeros_like(labels)) == (None, None)


def _save_lpips_weights(folder: Path, seed: int = 0) -> tuple[Path, Path]:
    """A random AlexNet in torchvision's layout (with a classifier, as torchvision saves it) and
    LPIPS linear layers in the lpips package's layout."""
    torch.manual_seed(seed)
    backbone = AlexFeatures()
    state = {**backbone.state_dict(), "classifier.1.weight": torch.zeros(4, 4)}
    linear = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(CHANNELS)}
    torch.save(state, folder / "alexnet.pth")
    torch.save(linear, folder / "alex_lin.pth")
    return folder / "alexnet.pth", folder / "alex_lin.pth"


def test_lpips_loads_local_weights_and_measures(tmp_path: Path) -> None:
    backbone_path, linear_path = _save_lpips_weights(tmp_path)
    assert find_lpips(backbone_path, linear_path) == (backbone_path, linear_path)
    assert find_lpips(tmp_path / "missing.pth", linear_path) is None
    model = load_lpips(backbone_path, linear_path)
    g = torch.Generator().manual_seed(2)
    a, b = torch.rand(2, 3, 64, 64, generator=g), torch.rand(2, 3, 64, 64, generator=g)
    assert torch.allclose(model(a, a), torch.zeros(2)) and (model(a, b) > 0).all()
    torch.testing.assert_close(model(a, b), model(b, a))
    # Known answer with only the first layer weighted: by hand from conv1 + ReLU.
    lin = torch.load(linear_path)
    only_first = {k: (v if k.startswith("lin0") else torch.zeros_like(v)) for k, v in lin.items()}
    torch.save(only_first, tmp_path / "first.pth")
    first = load_lpips(backbone_path, tmp_path / "first.pth")
    state = torch.load(backbone_path)
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def feat(x: torch.Tensor) -> torch.Tensor:
        f = F.relu(F.conv2d(((2 * x - 1) - shift) / scale, state["features.0.weight"], state["features.0.bias"], stride=4, padding=2))
        return f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)

    expected = (lin["lin0.model.1.weight"] * (feat(a) - feat(b)).pow(2)).sum(1).mean((1, 2))
    torch.testing.assert_close(first(a, b), expected)
    with pytest.raises(ValueError, match="not LPIPS linear layers"):
        load_lpips(backbone_path, backbone_path)
    with pytest.raises(ValueError, match="torchvision's layout"):
        load_lpips(linear_path, linear_path)


def test_mouth_follow_finds_a_late_mouth() -> None:
    rng = np.random.default_rng(0)
    activity = np.convolve(rng.random(120), np.ones(5) / 5, mode="same")
    late = np.concatenate([np.full(2, activity[0]), activity[:-2]])  # the lips move 2 frames after the sound
    row = mouth_follow(5.0 + 10.0 * late, activity)
    assert row["offset"] == 2 and row["corr_at_offset"] == pytest.approx(1.0, abs=1e-6) and row["corr"] < 0.9
    assert mouth_follow(activity, activity) == {"corr": 1.0, "offset": 0, "corr_at_offset": 1.0}
    assert mouth_follow(np.zeros(20), activity[:20])["corr"] is None  # a still mouth has no correlation


def test_a_variants_config_and_its_schedule(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``bench real --config``: the variant's fields over the defaults, its run folder told apart
    by a hash of them, the benchmark's own fields refused; and the fitted schedule takes the pose
    refit's passes out of the budget before it splits the rest between the stages."""
    from adnerf.model.train_config import TrainConfig

    base, tag = schedule_config(None, seed=3)
    assert tag == "" and base == TrainConfig(seed=3)
    refit, tag = schedule_config({"pose_refit": 2, "head_width": 96}, seed=0)
    assert refit.pose_refit == 2 and refit.head_width == 96 and tag.startswith("_cfg") and len(tag) == 12
    assert schedule_config({"head_width": 96, "pose_refit": 2}, seed=5)[1] == tag  # the order of the keys does not matter
    assert schedule_config({"pose_refit": 1}, seed=0)[1] != tag
    for bad, says in (({"head_iters": 10}, "head_iters"), ({"seed": 1}, "seed"), ({"no_such_field": 1}, "invalid training config"), ({"pose_refit": -1}, "pose_refit")):
        with pytest.raises(ValueError, match=says):
            schedule_config(bad, seed=0)
    # 10 minutes at 0.1 s an iteration: 6000 iterations; two 60 s refit passes leave 4800.
    plain, how = fitted_schedule(base, 10.0, 0.1)
    assert (plain.head_iters, plain.torso_iters) == (round(HEAD_SHARE * 6000), round((1 - HEAD_SHARE) * 6000)) and "refit" not in how
    fitted, how = fitted_schedule(refit, 10.0, 0.1, refit_pass=60.0)
    assert (fitted.head_iters, fitted.torso_iters) == (round(HEAD_SHARE * 4800), round((1 - HEAD_SHARE) * 4800)) and "2 pose refit passes ~120 s" in how
    assert fitted.pose_refit == 2 and fitted.head_width == 96
    with pytest.raises(ValueError, match="give more minutes"):
        fitted_schedule(refit, 2.0, 0.1, refit_pass=59.0)
    # The command line reads the variant from a JSON file, and refuses a bad one before any work.
    bad = tmp_path / "bad.json"
    bad.write_text('{"torso_iters": 5}')
    assert main(["bench", "real", str(tmp_path / "clip.mp4"), "--config", str(bad), "--work", str(tmp_path / "never")]) == 2
    assert "torso_iters" in capsys.readouterr().err and not (tmp_path / "never").exists()


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("real") / "scene", SynthConfig(seconds=3.0, size=96, voice="formant", seed=4)) / "video.mp4"


def test_bench_real_runs_end_to_end_and_reuses_its_work(clip: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    backbone_path, linear_path = _save_lpips_weights(tmp_path)
    torch.manual_seed(0)
    syncnet_path = tmp_path / "syncnet.model"
    torch.save(SyncNet(64).state_dict(), syncnet_path)  # random weights: the plumbing, not the score
    row = bench_real(clip, size=None, minutes=0.05, work=tmp_path / "work", lpips_backbone=backbone_path, lpips_linear=linear_path, syncnet=syncnet_path, sweep=2, progress=False, log=lambda m: None)
    json.dumps(row)  # serialisable as it is
    for key in ("psnr", "ssim", "psnr_head", "ssim_head", "psnr_mouth", "lpips"):
        assert isinstance(row[key], (int, float)) and math.isfinite(row[key]), key
    assert row["held_out_frames"] == row["frames"] == 11 and row["clip_frames"] == 75 and row["train_frames"] == 64
    assert row["landmarks_found_true"] == 11 and row["features"] == "auto"
    assert row["feature_kind"] == json.loads((Path(row["dataset"]) / "meta.json").read_text())["feature_kind"]  # what auto chose
    # SyncNet scores the 11 held-out frames' 6 windows, the renders and the true frames alike.
    assert row["syncnet"] == "scored" and row["syncnet_windows"] == 6 and len(row["syncnet_curve"]) == 31
    assert row["lse_d"] > 0 and row["lse_d_true"] > 0 and row["lse_d"] != row["lse_d_true"]
    # Three seconds of training render no face dlib finds: then there is no LMD, and it says why.
    assert ("lmd_mouth_px" in row) == (row["landmarks_found_render"] >= 0.5 * 11)
    assert row["layers"]["lip_in_head"] >= 0.98 and Path(row["sheet"]).stat().st_size > 0
    assert Path(row["sheet"]).parent == Path(row["run"])  # the run's own: another seed's run does not overwrite it
    lips = row["lip_signal"]  # the clip's own ceiling, from the dataset's landmarks and audio
    assert lips["frames"] == 75 and len(lips["ridge_cv_blocks"]) == 6 and -1 <= lips["ridge_cv_corr"] <= 1
    assert set(row["seconds"]) == {"video", "preprocess", "train_wall", "evaluate", "sheet", "sweep"}
    # The pose sweep: two held-out frames at each yaw, the first and the last, with its sheet.
    sweep = row["pose_sweep"]
    assert [r["yaw"] for r in sweep["rows"]] == [0.0, 5.0, 10.0, 15.0, 20.0] and sweep["frames"] == [64, 74]
    assert Path(sweep["sheet"]).stat().st_size > 0 and Path(sweep["sheet"]).parent == Path(row["run"]) and set(row["pose_range"]) == {"yaw", "pitch", "roll"}
    plot_mouth_opening(row, tmp_path / "mouth.png")
    assert (tmp_path / "mouth.png").stat().st_size > 0
    # Again: the dataset and the run are reused, and without LPIPS weights the column says so.
    capsys.readouterr()
    drive = clip.parent / "audio.wav"
    argv = ["bench", "real", str(clip), "--size", "0", "--minutes", "0.05", "--work", str(tmp_path / "work"), "--json", "--lpips-backbone", str(tmp_path / "none.pth"), "--sweep", "0"]
    assert main([*argv, "--drive", str(drive), "--syncnet", str(syncnet_path)]) == 0
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again["lpips"] == "no weights" and again["syncnet"] == "scored" and again["seconds"]["preprocess"] < 1.0
    # Driven by other speech (here the clip's whole audio): one row per file, after the reference
    # rows of the clip's own audio (every frame; the held-out true frames and render when found).
    driven = again["driven"]
    assert driven[-1]["audio"] == str(drive) and driven[-1]["frames"] == 75 and "landmarks_found" in driven[-1]
    assert read_video(driven[-1]["video"]).frames.shape[0] == 75
    if driven[-1]["landmarks_found"] >= 0.5 * 75:  # the driven clip is scored against its speech
        assert driven[-1]["syncnet_windows"] == 70
    assert driven[0]["audio"] == "the clip's own audio, every frame" and driven[0]["frames"] == 75
    assert len(driven) == 2 + 2 * ("mouth_opening_true_px" in row)
    with pytest.raises(ValueError, match="no such audio file"):
        bench_real(clip, size=None, minutes=0.05, work=tmp_path / "never", drive=(tmp_path / "missing.wav",), progress=False, log=lambda m: None)
    with pytest.raises(ValueError, match="not a SyncNet checkpoint"):
        bench_real(clip, size=None, minutes=0.05, work=tmp_path / "never", syncnet=linear_path, progress=False, log=lambda m: None)
    assert not (tmp_path / "never").exists()
    assert again["psnr"] == pytest.approx(row["psnr"], abs=1e-6)  # the same run, rendered again
    # Other preprocessing settings in the same work folder: the run is not continued on a dataset it
    # was not started on, and the dataset is left as it was.
    stamp = (Path(row["dataset"]) / "preprocess_report.json").stat().st_mtime_ns
    with pytest.raises(ValueError, match="other preprocessing settings"):
        bench_real(clip, size=None, minutes=0.05, test_fraction=0.2, work=tmp_path / "work", progress=False, log=lambda m: None)
    assert (Path(row["dataset"]) / "preprocess_report.json").stat().st_mtime_ns == stamp
    assert row["clothes"] == "grabcut" and "_noclothes" not in row["dataset"]
    # adnerf evaluate reports the same metrics for the run and its dataset.
    assert main(["evaluate", row["run"], row["dataset"], "--json", "--lpips-backbone", str(backbone_path), "--lpips-linear", str(linear_path), "--syncnet", str(syncnet_path)]) == 0
    ev = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("psnr", "psnr_head", "ssim_head", "psnr_mouth", "lpips", "landmarks_found_true", "lse_d", "lse_c", "lse_d_true"):
        assert ev[key] == pytest.approx(row[key], abs=1e-6), key
    # adnerf lip-signal measures the same ceiling from the dataset alone.
    assert main(["lip-signal", row["dataset"], "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == json.loads(json.dumps(lips))
    # Without weights the columns say so, and nothing is fetched.
    assert main(["evaluate", row["run"], row["dataset"], "--json", "--poses", "tracked", "--no-landmarks"]) == 0
    bare = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert bare["syncnet"] == "no weights" and bare["lpips"] == "no weights" and "lse_d" not in bare
    # A dataset without landmarks has no lip signal: refused in one line.
    (Path(row["dataset"]) / "landmarks.npy").rename(tmp_path / "landmarks.npy")
    assert main(["lip-signal", row["dataset"]]) == 2
    assert "no landmarks.npy" in capsys.readouterr().err


def test_landmark_evaluation_of_true_and_delayed_frames(clip: Path, tmp_path: Path) -> None:
    """Through the real detector: the true frames as renders give LMD 0 and perfect sync; the true
    frames two frames late (early) give a positive (negative) offset. The cartoon's jaw moves
    smoothly, so over 50 frames the correlation's peak is broad: within a frame of the delay."""
    from adnerf.evaluation.evaluate import landmark_evaluation
    from adnerf.formats.dataset import load_dataset
    from adnerf.preprocess import PreprocessConfig, preprocess_video

    preprocess_video(clip, tmp_path / "data", PreprocessConfig(focal=1.33 * 96))
    ds = load_dataset(tmp_path / "data", truth=False)
    frames = list(range(2, 52))
    same = landmark_evaluation(ds, frames, ds.frames[frames])
    assert same["landmarks_found_render"] == 50 and same["lmd_all_px"] == 0.0 and same["av_offset_frames"] == 0
    late = landmark_evaluation(ds, frames, ds.frames[[f - 2 for f in frames]])
    early = landmark_evaluation(ds, frames, ds.frames[[f + 2 for f in frames]])
    assert late["av_offset_frames"] in (1, 2, 3) and early["av_offset_frames"] in (-1, -2, -3)
    assert late["lmd_mouth_px"] > 0 and late["mouth_open_corr"] < same["mouth_open_corr"]
    # SyncNet on the true frames as renders: the same crops, the same scores as the truth's.
    from adnerf.evaluation.evaluate import syncnet_evaluation

    torch.manual_seed(1)
    net = SyncNet(64).eval()
    scored = syncnet_evaluation(ds, frames, ds.frames[frames], net)
    assert scored["syncnet_windows"] == 45 and scored["lse_d"] == scored["lse_d_true"] and scored["lse_c"] == scored["lse_c_true"]
    assert syncnet_evaluation(ds, frames, ds.frames[[f - 2 for f in frames]], net)["lse_d"] != scored["lse_d"]
    assert syncnet_evaluation(ds, frames[::2], ds.frames[frames[::2]], net) == {"syncnet": "needs consecutive frames"}
