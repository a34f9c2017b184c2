"""The product end to end on a tiny synthetic scene: dataset, training, resume, rendering, errors."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.cli import main
from adnerf.commands.demo import check_reused_scene, run_demo
from adnerf.commands.render_video import (
    RenderError,
    check_speech,
    load_poses,
    pingpong,
    render_frames,
)
from adnerf.evaluation.evaluate import evaluate_run, mouth_boxes, mouth_darkness
from adnerf.io import AudioTrack, read_audio, read_video
from adnerf.formats.dataset import VERSION, DatasetError, load_dataset, write_wav
from adnerf.model.train import RunError, TrainConfig, load_run, train
from adnerf.synth import SynthConfig, synthesize

TINY = SynthConfig(seconds=1.6, size=32, voice="formant", seed=3)
TINY_TRAIN = TrainConfig(head_iters=24, torso_iters=12, rays=128, log_every=4, checkpoint_every=8)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("tiny") / "data", TINY)


@pytest.fixture(scope="module")
def tiny_run(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train(tiny, tmp_path_factory.mktemp("tiny_run") / "run", config=TINY_TRAIN, progress=False)


def test_synthetic_dataset_is_consistent(tiny: Path) -> None:
    ds = load_dataset(tiny)
    n = round(TINY.seconds * TINY.fps)
    assert ds.frames.shape == (n, 32, 32, 3) and ds.features.shape[:2] == (n, 16)
    assert ds.truth is not None and ds.truth.jaw.min() >= 0 and ds.truth.jaw.max() <= 1
    # Labels, depth and pixels agree: person pixels have a surface, background pixels show the plate.
    person = ds.truth.parsing > 0
    assert np.isfinite(ds.truth.depth[person]).all() and np.isinf(ds.truth.depth[~person]).all()
    assert np.array_equal(ds.frames[~person], np.broadcast_to(ds.background, ds.frames.shape)[~person])
    assert (ds.parsing == 1).any() and (ds.parsing == 2).any()
    # The camera sees the head centre where the pose puts it.
    uv = ds.meta.camera().project(torch.as_tensor(ds.poses[:, :3, 3]))
    centre = np.round(uv.numpy()).astype(int)
    assert all(ds.parsing[i, y, x] == 1 for i, (x, y) in enumerate(centre))
    assert set(ds.meta.train).isdisjoint(ds.meta.test) and max(ds.meta.train) < min(ds.meta.test)
    video = read_video(tiny / "video.mp4")
    assert video.frames.shape == ds.frames.shape and video.audio is not None


def test_synthesis_is_deterministic(tiny: Path, tmp_path: Path) -> None:
    again = load_dataset(synthesize(tmp_path / "again", TINY))
    first = load_dataset(tiny)
    assert np.array_equal(again.frames, first.frames) and np.array_equal(again.poses, first.poses)


def test_mouth_measure_follows_the_true_jaw(tmp_path: Path) -> None:
    ds = load_dataset(synthesize(tmp_path / "m", SynthConfig(seconds=4.0, size=96, voice="formant", seed=1)))
    frames = list(range(ds.meta.n_frames))
    boxes = mouth_boxes(ds, frames)
    seen = [mouth_darkness(f[y0:y1, x0:x1]) for f, (x0, y0, x1, y1) in zip(ds.frames, boxes)]
    assert np.corrcoef(seen, ds.truth.jaw)[0, 1] > 0.9


def test_dataset_errors(tiny: Path, tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such dataset"):
        load_dataset(tmp_path / "missing")
    copy = tmp_path / "copy"
    shutil.copytree(tiny, copy)
    meta = json.loads((copy / "meta.json").read_text())
    meta["version"] = VERSION + 1
    (copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="version"):
        load_dataset(copy)
    meta["version"] = VERSION
    meta["n_frames"] += 1
    (copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="missing or unreadable"):
        load_dataset(copy)


def test_training_lowers_the_loss_and_renders_mp4_with_audio(tiny: Path, tiny_run: Path, tmp_path: Path) -> None:
    rows = [json.loads(line) for line in (tiny_run / "log.jsonl").read_text().splitlines()]
    head = [r["loss"] for r in rows if r["stage"] == "head"]
    torso = [r["loss"] for r in rows if r["stage"] == "torso"]
    assert len(head) == 6 and len(torso) == 3
    assert np.mean(head[-2:]) < np.mean(head[:2])
    out = tmp_path / "out.mp4"
    assert main(["render", str(tiny_run), "--audio", str(tiny / "audio.wav"), "-o", str(out), "--yaw", "5", "--frames", str(tmp_path / "png")]) == 0
    video = read_video(out)
    audio = read_audio(tiny / "audio.wav")
    assert len(video.frames) == int(audio.duration * TINY.fps) == len(list((tmp_path / "png").glob("*.png")))
    assert abs(video.audio.duration - audio.duration) < 0.05
    metrics, clip = evaluate_run(load_run(tiny_run), load_dataset(tiny), "test")
    assert {"psnr", "ssim", "psnr_mouth", "ssim_mouth", "mouth_open_corr"} <= set(metrics)
    assert 0 < metrics["psnr"] < 100 and clip.frames.shape[0] == len(load_dataset(tiny).meta.test)
    assert metrics["psnr_eyes"] is not None and 0 < metrics["psnr_eyes"] <= 100  # the scene has eye points


def test_kill_and_resume_gives_the_same_steps(tiny: Path, tmp_path: Path) -> None:
    cfg = TrainConfig(head_iters=6, torso_iters=3, rays=64, log_every=1, checkpoint_every=3)
    straight = train(tiny, tmp_path / "straight", config=cfg, progress=False)
    killed = tmp_path / "killed"
    train(tiny, killed, config=cfg, progress=False, max_steps=5)  # "killed" after step 5: steps 4-5 are lost
    assert torch.load(killed / "checkpoint.pt", weights_only=False)["stages"]["head"]["step"] == 3
    train(tiny, killed, progress=False, resume=True)
    a = torch.load(straight / "checkpoint.pt", weights_only=False)
    b = torch.load(killed / "checkpoint.pt", weights_only=False)
    assert (a["stages"]["head"]["step"], a["stages"]["torso"]["step"]) == (b["stages"]["head"]["step"], b["stages"]["torso"]["step"]) == (6, 3)
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key
    with pytest.raises(RunError, match="already exists"):
        train(tiny, straight, config=cfg, progress=False)


def test_kill_and_resume_in_stage_two_gives_the_same_steps(tiny: Path, tmp_path: Path) -> None:
    # Stage 2 trains against the cached head renders; a resumed run reads them back from the file
    # and must see the values the uninterrupted run trained on.
    cfg = TrainConfig(head_iters=3, torso_iters=6, rays=64, log_every=1, checkpoint_every=3)
    straight = train(tiny, tmp_path / "straight", config=cfg, progress=False)
    killed = tmp_path / "killed"
    train(tiny, killed, config=cfg, progress=False, max_steps=8)  # killed after torso step 5: steps 4-5 are lost
    assert torch.load(killed / "checkpoint.pt", weights_only=False)["stages"]["torso"]["step"] == 3
    train(tiny, killed, progress=False, resume=True)
    a = torch.load(straight / "checkpoint.pt", weights_only=False)
    b = torch.load(killed / "checkpoint.pt", weights_only=False)
    assert b["stages"]["torso"]["step"] == 6
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key


def test_background_replacement_changes_only_the_background(tiny: Path, tiny_run: Path) -> None:
    run, ds = load_run(tiny_run), load_dataset(tiny)
    idx = list(ds.meta.test)
    plate = ds.background.astype(np.float32) / 255.0
    other = np.random.default_rng(0).random(plate.shape).astype(np.float32)
    a = render_frames(run, ds.features[idx], ds.poses[idx], plate)
    b = render_frames(run, ds.features[idx], ds.poses[idx], other)
    transmittance = (1 - a.head_opacity) * (1 - a.torso_opacity)
    expected = transmittance[..., None] * (other - plate) * 255.0
    diff = b.frames.astype(np.float64) - a.frames.astype(np.float64)
    assert np.abs(diff - expected).max() <= 1.0 + 1e-6  # uint8 rounding of each image
    # The person (where the tiny run has learnt most opacity) changes in proportion to what shows
    # through; empty pixels become the new background.
    solid = transmittance <= np.quantile(transmittance, 0.02)
    empty = transmittance > 1 - 1e-6
    assert transmittance[solid].max() < 0.5 and empty.any()
    assert np.abs(diff[solid]).max() <= 255.0 * transmittance[solid].max() + 1.0
    assert np.abs(b.frames[empty] / 255.0 - np.broadcast_to(other, b.frames.shape)[empty]).max() <= 0.5 / 255 + 1e-6


def test_zero_yaw_is_the_plain_render_and_yaw_turns_the_head(tiny: Path, tiny_run: Path) -> None:
    run, ds = load_run(tiny_run), load_dataset(tiny)
    idx = list(ds.meta.test)[:2]
    plate = ds.background.astype(np.float32) / 255.0
    plain = render_frames(run, ds.features[idx], ds.poses[idx], plate)
    zero = render_frames(run, ds.features[idx], ds.poses[idx], plate, yaw=0.0, pitch=0.0, roll=0.0)
    assert np.array_equal(plain.frames, zero.frames)
    turned = render_frames(run, ds.features[idx], ds.poses[idx], plate, yaw=15.0)
    assert not np.array_equal(plain.frames, turned.frames)


def test_invalid_inputs_give_clear_errors(tiny: Path, tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    silent = tmp_path / "silent.wav"
    write_wav(silent, AudioTrack(np.zeros(16000, dtype=np.float32), 16000))
    cases = [
        (["render", str(tmp_path / "nope"), "--audio", str(tiny / "audio.wav"), "-o", str(tmp_path / "a.mp4")], "not an adnerf run"),
        (["render", str(tiny_run), "--audio", str(silent), "-o", str(tmp_path / "b.mp4")], "no speech"),
        (["evaluate", str(tiny_run), str(tmp_path / "nope")], "no such dataset folder"),
        (["train", str(tmp_path / "nope"), "-o", str(tmp_path / "r")], "no such dataset folder"),
        (["render", str(tiny_run), "--audio", str(tiny / "audio.wav"), "-o", str(tmp_path / "c.avi")], ".mp4"),
    ]
    bad_poses = tmp_path / "poses.npy"
    np.save(bad_poses, np.tile(np.eye(4), (3, 1, 1)))
    cases.append((["render", str(tiny_run), "--audio", str(tiny / "audio.wav"), "--poses", str(bad_poses), "-o", str(tmp_path / "d.mp4")], "has 3 poses"))
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)


def test_pose_helpers(tmp_path: Path) -> None:
    poses = np.arange(4)[:, None, None] * np.ones((4, 4, 4))
    assert pingpong(poses, 9)[:, 0, 0].tolist() == [0, 1, 2, 3, 2, 1, 0, 1, 2]
    with pytest.raises(RenderError, match="no speech"):
        check_speech(AudioTrack(np.full(16000, 1e-4, dtype=np.float32), 16000), "x")
    check_speech(AudioTrack(0.5 * np.sin(np.arange(16000) * 0.1).astype(np.float32), 16000), "x")
    np.save(tmp_path / "bad.npy", np.zeros((2, 3)))
    with pytest.raises(RenderError, match="shape"):
        load_poses(tmp_path / "bad.npy", 2)


def test_render_takes_precomputed_feature_windows(tiny: Path, tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    windows = np.load(tiny / "features.npy")[:10]
    feats = tmp_path / "aud.npy"
    np.save(feats, windows)
    out = tmp_path / "f.mp4"
    assert main(["render", str(tiny_run), "--audio", str(tiny / "audio.wav"), "--features", str(feats), "-o", str(out)]) == 0
    assert len(read_video(out).frames) == 10
    np.save(feats, windows[:, :, :3])
    assert main(["render", str(tiny_run), "--audio", str(tiny / "audio.wav"), "--features", str(feats), "-o", str(tmp_path / "g.mp4")]) == 2
    assert "shape (M, 16," in capsys.readouterr().err
    # A run trained on imported DeepSpeech windows cannot compute them for new audio: it says so.
    ds_run = tmp_path / "ds_run"
    shutil.copytree(tiny_run, ds_run)
    doc = json.loads((ds_run / "run.json").read_text())
    doc["meta"]["feature_kind"] = "deepspeech"
    (ds_run / "run.json").write_text(json.dumps(doc))
    assert main(["render", str(ds_run), "--audio", str(tiny / "audio.wav"), "-o", str(tmp_path / "h.mp4")]) == 2
    assert "--features" in capsys.readouterr().err
    assert not (tmp_path / "g.mp4").exists() and not (tmp_path / "h.mp4").exists()


@pytest.mark.parametrize("head_in_front", [True, False])
def test_stage_two_trains_the_frame_the_renderer_draws(tiny: Path, tiny_run: Path, tmp_path: Path, head_in_front: bool) -> None:
    # Stage 2 composites the torso it trains with the frozen head rendered at its own rays; in
    # either order of the layers that is the frame render_frame draws at the drawn pixels.
    from adnerf.compositor import Layer, over
    from adnerf.formats.dataset import LABEL_HEAD, LABEL_TORSO
    from adnerf.model.talking_head import render_frame, render_layers, render_on_plate
    from adnerf.model.train import Trainer, behind_chin

    run = load_run(tiny_run)
    ds = load_dataset(tiny)
    tr = Trainer(tmp_path, ds, replace(run.model.config, head_in_front=head_in_front), run.train_config, "cpu", progress=False)
    tr.model.load_state_dict(run.model.state_dict())
    tr.head_step = run.train_config.head_iters
    near, far = tr.model.layers["torso"].crossing(tr.rays)
    in_box = far > near
    assert 0 < in_box.float().mean() < 1
    with torch.no_grad():
        codes = tr.model.frame_codes(tr.windows)
    black = torch.zeros(ds.meta.height, ds.meta.width, 3)
    labels = torch.as_tensor(ds.parsing).reshape(ds.meta.n_frames, -1)
    for f in ds.meta.train[:: max(1, len(ds.meta.train) // 4)]:
        pix = torch.nonzero(in_box)[:, 0]
        cond = tr.condition(f, codes[f], ds.head_pose(f))
        # The head at the step's rays: the head alone, premultiplied, as a whole frame draws it.
        alone = render_frame(tr.model, tr.camera, ds.head_pose(f), codes[f], black, layers=("head",))
        head = tr.frozen_head(pix, cond)
        torch.testing.assert_close(head.rgb, alone.rgb.reshape(-1, 3)[pix], rtol=0, atol=1e-5)
        torch.testing.assert_close(head.opacity, alone.head_opacity.reshape(-1)[pix], rtol=0, atol=1e-5)
        tr.model.eval()
        out, target, mask, held = tr.torso_part(f, pix, cond, jitter=False)
        want = render_on_plate(tr.model, tr.rays[pix], cond, tr.plate[pix])
        torch.testing.assert_close(out.final.rgb.detach().float(), want, rtol=0, atol=1e-5)
        each = render_layers(tr.model, tr.rays[pix], cond)
        torch.testing.assert_close(out.final.opacity.detach().float(), each["torso"].opacity, rtol=0, atol=1e-5)  # the torso's own
        flipped = over(each["torso"], over(each["head"], Layer.opaque(tr.plate[pix]))) if head_in_front else over(each["head"], over(each["torso"], Layer.opaque(tr.plate[pix])))
        assert (flipped.rgb - want).abs().max() > 0.02  # the two orders differ on these pixels
        true = torch.as_tensor(ds.frames[f]).reshape(-1, 3)[pix].float() / 255.0
        assert torch.equal(target, true) and torch.equal(mask, labels[f, pix] == LABEL_TORSO)
        # Behind the chin, the torso's opacity is left free; in front of the head, held to the parsing.
        if head_in_front:
            reach = behind_chin(labels == LABEL_HEAD, labels == LABEL_TORSO, ds.meta.height, ds.meta.width)
            assert torch.equal(held, ~reach[f, pix]) and reach.any()
        else:
            assert held is None
    if head_in_front:  # the packed masks read back as the dense ones, a frame at a time and per ray
        drawn = ds.meta.train[:: max(1, len(ds.meta.train) // 4)]
        assert torch.nonzero(tr.reach_made)[:, 0].tolist() == sorted(drawn)  # made for the frames drawn, not the clip
        every = torch.arange(ds.meta.height * ds.meta.width)
        assert torch.equal(torch.stack([tr.behind_head(f, every) for f in range(ds.meta.n_frames)]), reach)
        frames = torch.randint(ds.meta.n_frames, (500,))
        pixels = torch.randint(ds.meta.height * ds.meta.width, (500,))
        assert torch.equal(tr.behind_head(frames, pixels), reach[frames, pixels])


def test_training_holds_a_clip_as_its_uint8_frames_and_labels(tiny: Path, tiny_run: Path, tmp_path: Path) -> None:
    # Minutes of footage must fit: per frame the trainer keeps the uint8 frame and labels (the
    # dataset's own memory on the CPU) and a bit a pixel per mask, no float copy of the clip and
    # no per-frame head renders (float32 frames alone would be 12 bytes a pixel).
    from adnerf.model.train import Trainer

    run, ds = load_run(tiny_run), load_dataset(tiny)
    tr = Trainer(tmp_path, ds, run.model.config, run.train_config, "cpu", progress=False)
    assert tr.frames.dtype == torch.uint8 and tr.labels.dtype == torch.uint8
    assert tr.frames.data_ptr() == ds.frames.ctypes.data and tr.labels.data_ptr() == ds.parsing.ctypes.data  # shared, not copied
    tr.reach  # stage 2's mask, made
    pixels = ds.meta.height * ds.meta.width
    held = tr.frame_bytes()
    assert set(held) == {"frames", "labels", "in_head_box", "reach"}
    assert held["frames"] == 3 * pixels and held["labels"] == pixels
    assert held["in_head_box"] == held["reach"] == -(-pixels // 8)
    # The tensors the trainer holds with a frame axis are those stores and nothing else.
    n = ds.meta.n_frames
    per_frame = {name for name, v in vars(tr).items() if isinstance(v, torch.Tensor) and v.ndim and v.shape[0] == n and v.numel() > n}
    assert per_frame <= {"frames", "labels", "windows", "step_windows"}, per_frame
    assert tr.step_windows is tr.windows and tr.jittered is None  # the step's windows are the stored ones (no audio_jitter)
    assert tr.windows.numel() * tr.windows.element_size() // n == 16 * ds.meta.feature_dim * 4  # the audio windows: no pixels
    # Stage 2 trains without a pass over the clip first and writes no head cache.
    train(tiny, tmp_path / "resumed", config=replace(TINY_TRAIN, head_iters=1, torso_iters=2), progress=False)
    assert not (tmp_path / "resumed" / "head_renders.pt").exists()


def test_the_torso_may_reach_behind_the_chin_only() -> None:
    from adnerf.model.train import behind_chin

    # Two frames of 40 x 30: a head of rows 5..24 (20 rows, so the reach is 2 pixels), columns
    # 2..27, on a torso from row 25 down, columns 10..19; in the second frame the chin is 3 rows
    # lower (the jaw open).
    H, W = 40, 30
    head = torch.zeros(2, H, W, dtype=torch.bool)
    torso = torch.zeros(2, H, W, dtype=torch.bool)
    head[0, 5:25, 2:28] = True
    torso[0, 25:, 10:20] = True
    head[1, 5:28, 2:28] = True
    torso[1, 28:, 10:20] = True
    got = behind_chin(head.reshape(2, -1), torso.reshape(2, -1), H, W).reshape(2, H, W)
    want = torch.zeros(2, H, W, dtype=torch.bool)
    want[0, 23:25, 8:22] = True  # two rows above the torso, two columns either side of it
    want[1, 26:28, 8:22] = True
    assert torch.equal(got, want)
    wider = behind_chin(head.reshape(2, -1), torso.reshape(2, -1), H, W, band=0.25).reshape(2, H, W)
    assert torch.equal(wider[0].nonzero()[:, 0].unique(), torch.arange(20, 25))  # a reach of 5 rows
    assert not behind_chin(torch.zeros(1, 4, dtype=torch.bool), torch.ones(1, 4, dtype=torch.bool), 2, 2).any()  # no head


def test_the_mask_term_counts_only_the_rays_it_holds() -> None:
    from adnerf.compositor import composite
    from adnerf.model.train import _optimise
    from adnerf.renderer import RenderOutput

    # One sample per ray: opacity a = 1 - exp(-density * 1); the target colour is met exactly.
    density = torch.nn.Parameter(torch.tensor([[1.0], [2.0], [0.5], [3.0]]))
    opt = torch.optim.SGD([density], lr=0.0)
    rgb = torch.full((4, 1, 3), 0.5)

    def render() -> RenderOutput:
        return RenderOutput(composite(rgb, density, torch.zeros(4, 1), torch.ones(4, 1)), None)

    comp = render().coarse
    target = comp.rgb.detach()
    mask = torch.tensor([True, False, True, False])
    a = comp.opacity.detach()
    held = torch.tensor([True, True, False, False])
    loss, _ = _optimise([(render(), target, mask, held)], 0.5, opt)
    # Coarse and final are the same pass: the mask term twice, over the held rays, divided by all 4.
    want = 2 * 0.5 * float(((a - mask.float()).square() * held).sum()) / 4
    assert loss == pytest.approx(want, rel=1e-6)
    loss_all, _ = _optimise([(render(), target, mask, None)], 0.5, opt)
    assert loss_all == pytest.approx(2 * 0.5 * float((a - mask.float()).square().mean()), rel=1e-6)
    assert loss_all > loss * 1.5


def test_demo_refuses_a_folder_with_another_scene(tiny: Path, tmp_path: Path) -> None:
    # The tiny scene is exactly what TINY makes; a folder left by a demo with other settings (the
    # scene's length changed between versions) is refused before any training, so the metrics
    # are never reported under settings they were not measured with.
    meta = load_dataset(tiny).meta
    check_reused_scene(meta, TINY, tiny)
    shutil.copytree(tiny, tmp_path / "demo" / "data")
    longer = SynthConfig(seconds=3.0, size=32, voice="formant", seed=3)
    with pytest.raises(DatasetError, match="another scene"):
        run_demo(tmp_path / "demo", synth_config=longer, train_config=TINY_TRAIN, progress=False, log=lambda _: None)
    assert not (tmp_path / "demo" / "run").exists()
    for other in (SynthConfig(seconds=1.6, size=48), SynthConfig(seconds=1.6, size=32, test_fraction=0.5)):
        with pytest.raises(DatasetError, match="another scene"):
            check_reused_scene(meta, other, tiny)
    # The jaw must be driven the same way: a scene from before visemes (its source says nothing
    # of the mouth: a loudness jaw) is not the viseme scene of the same length.
    assert "mouth=loudness" in meta.source
    with pytest.raises(DatasetError, match="visemes jaw"):
        check_reused_scene(meta, SynthConfig(seconds=1.6, size=32, voice="espeak", mouth="visemes", seed=3), tiny)
    older = replace(meta, source=meta.source.replace(" mouth=loudness", ""))
    check_reused_scene(older, TINY, tiny)
