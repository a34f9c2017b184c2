"""Eye blinks: natural blink tracks, the eye aspect ratio, the synthetic lids and their truth, the
head's eye condition in training and rendering, and ``render --blink``."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.cli import main
from adnerf.commands.render_video import render_frames
from adnerf.evaluation.readers import EyeReader, exact_frame, eye_boxes
from adnerf.model.blinks import (
    BLINK_GAP,
    BLINK_SECONDS,
    blink_track,
    blinks_in,
    count_blinks,
    eye_track,
)
from adnerf.model.conditions import (
    EYE_FREQUENCIES,
    SIGNAL_WIDTHS,
    FrameCondition,
    eye_code,
)
from adnerf.formats.dataset import load_dataset
from adnerf.model.layers import RadianceLayer
from adnerf.model.train import TrainConfig, Trainer, load_run, train
from adnerf.pose import HeadPose
from adnerf.preprocess.landmarks import eye_aspect_ratio, eye_openness
from adnerf.synth import (
    HeadModel,
    SynthConfig,
    TorsoModel,
    background_plate,
    pose_track,
    render_eye_openings,
    render_frame,
    synthesize,
)

SCENE = SynthConfig(seconds=2.0, size=48, voice="formant", seed=1)
CFG = TrainConfig(head_iters=8, torso_iters=4, rays=64, log_every=4)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("blink") / "data", SCENE)


@pytest.fixture(scope="module")
def run(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train(scene, tmp_path_factory.mktemp("blinkrun") / "run", config=CFG, progress=False)


def test_natural_blinks_last_their_time_and_come_every_two_to_six_seconds() -> None:
    t = np.arange(0, 60.0, 0.001)
    eye = blink_track(t, seed=4)
    assert eye.min() == pytest.approx(0.0, abs=1e-6) and eye.max() == 1.0 and ((eye >= 0) & (eye <= 1)).all()
    shut = eye < 1.0
    starts = t[1:][shut[1:] & ~shut[:-1]]
    ends = t[1:][~shut[1:] & shut[:-1]]
    assert 9 <= len(starts) <= 31  # 60 s at one per 2-6 s
    np.testing.assert_allclose(ends - starts[: len(ends)], BLINK_SECONDS, atol=0.002)
    assert count_blinks(eye) == len(starts) and count_blinks(np.ones(5)) == 0  # each blink closes the eyes past half once
    gaps = np.diff(starts)
    assert gaps.min() >= BLINK_GAP[0] - 0.002 and gaps.max() <= BLINK_GAP[1] + 0.002
    assert np.array_equal(blink_track(t, seed=4), eye) and not np.array_equal(blink_track(t, seed=5), eye)


def test_eye_track_choices(tmp_path: Path) -> None:
    assert np.array_equal(eye_track("none", 7, 25.0), np.ones(7, np.float32))
    auto = eye_track("auto", 500, 25.0)
    assert auto.shape == (500,) and auto.min() < 0.5  # 20 s: blinks
    np.save(tmp_path / "mine.npy", np.linspace(0, 1, 10))
    np.testing.assert_allclose(eye_track(tmp_path / "mine.npy", 8, 25.0), np.linspace(0, 1, 10)[:8], rtol=0, atol=1e-7)
    with pytest.raises(ValueError, match="needs 12"):
        eye_track(tmp_path / "mine.npy", 12, 25.0)
    np.save(tmp_path / "nan.npy", np.array([1.0, np.nan, 1.0]))
    with pytest.raises(ValueError, match="finite"):
        eye_track(tmp_path / "nan.npy", 3, 25.0)
    with pytest.raises(ValueError, match="auto, none or a readable"):
        eye_track(tmp_path / "missing.npy", 3, 25.0)


def _eye_points(opening: float) -> np.ndarray:
    """68 landmarks whose two eyes are 4 px wide and open by ``opening`` px at both lid points."""
    lm = np.zeros((68, 2))
    for first, x in ((36, 0.0), (42, 10.0)):
        lm[first : first + 6] = [(x, 0), (x + 1, -opening / 2), (x + 3, -opening / 2), (x + 4, 0), (x + 3, opening / 2), (x + 1, opening / 2)]
    return lm


def test_eye_aspect_ratio_and_openness_known_answers() -> None:
    assert eye_aspect_ratio(_eye_points(2.0)) == pytest.approx(2 * 2.0 / (2 * 4.0))  # 0.5
    assert eye_aspect_ratio(_eye_points(0.0)) == pytest.approx(0.0)
    # A clip whose eyes are open at ratio 0.3 with one blink down to 0.12 (= 0.4 x 0.3): 1 and 0.
    ratios = np.full(50, 0.3)
    ratios[20:23] = (0.21, 0.12, 0.21)
    lms = np.stack([_eye_points(r * 4.0) for r in ratios])
    openness = eye_openness(lms)
    np.testing.assert_allclose(openness[[0, 20, 21, 22]], [1.0, 0.5, 0.0, 0.5], atol=1e-6)
    assert openness.dtype == np.float32


def test_synthetic_lids_close_only_over_the_eyes_and_are_the_truth(scene: Path) -> None:
    ds = load_dataset(scene)
    size = ds.meta.width
    head, torso, plate = HeadModel(size), TorsoModel(size), background_plate(size)
    pose = pose_track(1, 25.0, 0)[0]
    open_, closed = (render_frame(head, torso, pose, 0.3, plate, eye)[0] for eye in (1.0, 0.0))
    changed = np.abs(open_ - closed).max(-1) > 1e-6
    x0, y0, x1, y1 = eye_boxes(ds.meta, pose[None])[0]
    inside = np.zeros_like(changed)
    inside[y0:y1, x0:x1] = True
    assert changed.sum() >= 4 and not (changed & ~inside).any()
    assert ds.eye is not None and np.array_equal(ds.eye, ds.truth.eye.astype(np.float32))


def test_eye_reader_reads_the_exact_scene(tmp_path: Path) -> None:
    """At the demo's 128 px (at 48 px a lid 15% closed covers no pixel centre yet)."""
    ds = load_dataset(synthesize(tmp_path / "big", SynthConfig(seconds=1.0, size=128, voice="formant", seed=1)))
    poses = ds.poses[:3]
    reader = EyeReader(ds, poses)
    head, torso = HeadModel(ds.meta.width), TorsoModel(ds.meta.width)
    plate = ds.background.astype(np.float64) / 255.0
    truth = np.array([1.0, 0.35, 0.0])
    frames = np.stack([exact_frame(head, torso, p, plate, eye=e) for p, e in zip(poses, truth)])
    np.testing.assert_allclose(reader.read(frames, np.arange(3)), truth, atol=0.06)
    # The templates and the demo's exact frames ray-cast only the eye box: the same pixels as the
    # whole frame's (a box shifted by one pixel, or rows and columns swapped, would differ).
    crops = [exact_frame(head, torso, p, plate, eye=e, box=reader.box(i)) for i, (p, e) in enumerate(zip(poses, truth))]
    for i, crop in enumerate(crops):
        x0, y0, x1, y1 = reader.box(i)
        assert x1 - x0 != y1 - y0 and np.array_equal(crop, frames[i, y0:y1, x0:x1])
    np.testing.assert_array_equal(reader.read_crops(crops, np.arange(3)), reader.read(frames, np.arange(3)))
    with pytest.raises(ValueError, match="box"):
        reader.read_crops([c[1:] for c in crops], np.arange(3))  # a crop that is not its pose's box


def test_synthetic_render_of_a_box_is_that_box_of_the_frame() -> None:
    size = 48
    head, torso, plate = HeadModel(size), TorsoModel(size), background_plate(size)
    pose = pose_track(1, 25.0, 0)[0]
    whole = render_frame(head, torso, pose, 0.4, plate, 0.5)
    box = (5, 20, 41, 48)  # across the head, the torso and the background, to the bottom edge
    part = render_frame(head, torso, pose, 0.4, plate, 0.5, box=box)
    labels = part[1]
    assert (labels == 0).any() and (labels == 1).any() and (labels == 2).any()
    for a, b in zip(whole, part):
        np.testing.assert_array_equal(a[20:48, 5:41], b)
    # One cast for several eye openings (the eye reader's templates): each is render_frame's.
    eyes = (1.0, 0.4, 0.0)
    many = render_eye_openings(head, torso, pose, 0.4, plate, eyes)
    assert not np.array_equal(many[0], many[2])
    for e, rgb in zip(eyes, many):
        np.testing.assert_array_equal(rgb, render_frame(head, torso, pose, 0.4, plate, e)[0])
    for bad in ((5, 20, 5, 30), (0, 0, 49, 10), (-1, 0, 4, 4)):
        with pytest.raises(ValueError, match="box"):
            render_frame(head, torso, pose, 0.4, plate, box=bad)


def test_training_gives_each_frame_its_own_eye_openness(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = shutil.copytree(scene, tmp_path / "data")
    eye = np.random.default_rng(0).random(SCENE.n_frames).astype(np.float32)  # a different value in every frame
    np.save(data / "eye.npy", eye)
    ds = load_dataset(data)
    seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # per render: each ray's eye value, pose translation and speech's frame
    real = RadianceLayer.render

    def spy(self: RadianceLayer, rays, cond, **kw):  # noqa: ANN001, ANN003, ANN202
        if self.name == "head" and self.training:
            n = rays.origins.shape[0]
            eyes, t, speech = cond.extra["eye"].expand(n, 1)[:, 0], cond.pose.t.detach().expand(n, 3), cond.audio.expand(n, -1)[:, 0]
            seen.append((eyes.numpy().copy(), t.numpy().copy(), speech.long().numpy().copy()))
        return real(self, rays, cond, **kw)

    monkeypatch.setattr(RadianceLayer, "render", spy)
    # An audio code that names its frame, to see whose speech each batch is rendered under.
    monkeypatch.setattr(Trainer, "codes", lambda self, frames: torch.tensor(frames, dtype=torch.float32)[:, None].expand(-1, self.model.config.audio_dim))
    train(data, tmp_path / "run", config=CFG, progress=False)
    # One render an iteration: the frame's rays, then the eye batch's (a quarter as many).
    assert len(seen) == CFG.head_iters
    n_eye = round(CFG.eye_rays * CFG.rays)
    others = 0
    for values, t, speech in seen:
        assert len(values) == CFG.rays + n_eye
        frames = np.argmin(np.linalg.norm(ds.poses[None, :, :3, 3] - t[:, None], axis=2), axis=1)
        assert set(frames) <= set(ds.meta.train) and (values == eye[frames]).all() and set(speech) <= set(ds.meta.train)
        main, eyes = slice(0, CFG.rays), slice(CFG.rays, None)
        assert (speech[main] == frames[main]).all()  # the frame's batch: its own speech
        assert len(set(frames[eyes])) == 1 and len(set(speech[eyes])) == 1  # the eye batch: one frame, one speech
        others += int(speech[eyes][0] != frames[eyes][0])
    # The eye batches: the speech of another random frame (the eyes do not depend on it).
    assert others >= CFG.head_iters // 2


def test_the_eye_enters_as_a_code_that_is_zero_for_open_eyes() -> None:
    openness = torch.tensor([[1.0], [0.75], [0.5], [0.25], [0.0]], dtype=torch.float64)
    codes = eye_code(openness)
    assert codes.shape == (5, SIGNAL_WIDTHS["eye"]) == (5, 2 * EYE_FREQUENCIES)
    assert torch.equal(codes[0], torch.zeros(2 * EYE_FREQUENCIES, dtype=torch.float64))  # open: no input at all
    # Fully closed: sin(k pi / 2) and 1 - cos(k pi / 2) for k = 1..4.
    torch.testing.assert_close(codes[4], torch.tensor([1.0, 0.0, -1.0, 0.0, 1.0, 2.0, 1.0, 0.0], dtype=torch.float64), atol=1e-12, rtol=0)
    # Each degree of closure its own direction: the four closed-ish codes are independent (one
    # number scaled would have rank 1).
    assert torch.linalg.matrix_rank(codes[1:]) == 4
    pose = HeadPose(torch.eye(3), torch.zeros(3))
    cond = FrameCondition(torch.arange(3.0), pose, {"eye": torch.tensor([0.25])})
    torch.testing.assert_close(cond.vector(("audio", "eye"), torch.float32), torch.cat([torch.arange(3.0), eye_code(torch.tensor([0.25]))]))


def test_the_head_reads_the_eye_and_render_blinks_on_command(scene: Path, run: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    r, ds = load_run(run), load_dataset(scene)
    assert r.model.reads_eye and r.model.layers["head"].conditions == ("audio", "eye") and r.model.layers["torso"].conditions == ("audio", "pose")
    idx = list(ds.meta.test)[:2]
    plate = ds.background.astype(np.float32) / 255.0
    opened = render_frames(r, ds.features[idx], ds.poses[idx], plate, eye=np.ones(2, np.float32))
    shut = render_frames(r, ds.features[idx], ds.poses[idx], plate, eye=np.zeros(2, np.float32))
    default = render_frames(r, ds.features[idx], ds.poses[idx], plate)
    assert not np.array_equal(opened.frames, shut.frames) and np.array_equal(opened.frames, default.frames)
    cond = r.model.condition(torch.zeros(r.model.config.audio_dim), ds.head_pose(0), 0.25)
    torch.testing.assert_close(cond.vector(r.model.layers["head"].conditions, torch.float32)[-SIGNAL_WIDTHS["eye"] :], eye_code(torch.tensor([0.25])))
    np.save(tmp_path / "shut.npy", np.zeros(200))
    audio = str(scene / "audio.wav")
    assert main(["render", str(run), "--audio", audio, "-o", str(tmp_path / "a.mp4"), "--blink", str(tmp_path / "shut.npy")]) == 0
    assert main(["render", str(run), "--audio", audio, "-o", str(tmp_path / "b.mp4"), "--blink", "nope.npy"]) == 2
    assert "--blink nope.npy" in capsys.readouterr().err and not (tmp_path / "b.mp4").exists()


def test_runs_without_eyes_cannot_blink_and_old_scenes_still_train(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    data = synthesize(tmp_path / "still", SynthConfig(seconds=1.6, size=32, voice="formant", seed=2, blinks=False))
    (data / "eye.npy").unlink()  # as a dataset made before blinks
    ds = load_dataset(data)
    assert ds.eye is None and "blinks=off" in ds.meta.source
    run = train(data, tmp_path / "run", config=CFG, progress=False)
    assert not load_run(run).model.reads_eye
    np.save(tmp_path / "shut.npy", np.zeros(100))
    assert main(["render", str(run), "--audio", str(data / "audio.wav"), "-o", str(tmp_path / "a.mp4"), "--blink", str(tmp_path / "shut.npy")]) == 2
    assert "cannot blink" in capsys.readouterr().err
    assert main(["render", str(run), "--audio", str(data / "audio.wav"), "-o", str(tmp_path / "b.mp4")]) == 0  # auto: nothing to blink


def test_a_clip_that_never_blinks_trains_a_head_without_the_eye(scene: Path, tmp_path: Path) -> None:
    """Like the shared real clip (openness 0.81-1.23, no blink): the eye value would only tell
    frames apart, so the head does not read it; one blinking training frame is enough to read it."""
    data = shutil.copytree(scene, tmp_path / "data")
    ds = load_dataset(data)
    eye = np.random.default_rng(3).uniform(0.81, 1.23, SCENE.n_frames).astype(np.float32)
    np.save(data / "eye.npy", eye)
    assert not blinks_in(eye, ds.meta.train)
    run = train(data, tmp_path / "still", config=CFG, progress=False)
    assert not load_run(run).model.reads_eye
    eye[ds.meta.test[0]] = 0.1  # a blink among the held-out frames only: still nothing to learn
    assert not blinks_in(eye, ds.meta.train)
    eye[ds.meta.train[3]] = 0.74  # one training frame below BLINKING
    assert blinks_in(eye, ds.meta.train) and not blinks_in(None, ds.meta.train)
    np.save(data / "eye.npy", eye)
    assert load_run(train(data, tmp_path / "blinks", config=CFG, progress=False)).model.reads_eye


def test_eye_rays_are_drawn_around_both_eyes_and_blinking_frames_more_often(scene: Path, tmp_path: Path) -> None:
    from adnerf.model.blinks import BLINKING
    from adnerf.formats.dataset import EYE_CROP
    from adnerf.model.talking_head import model_config
    from adnerf.model.train import Trainer

    ds = load_dataset(scene)
    assert ds.meta.eyes is not None
    tr = Trainer(tmp_path, ds, model_config(ds.meta, eye=True), TrainConfig(blink_frames=1.0), "cpu", progress=False)
    frame = ds.meta.train[3]
    pose = ds.head_pose(frame)
    pix = tr.eye_pixels(pose).numpy()
    uv, depth = ds.meta.eyes_in_image(pose)
    W = ds.meta.width
    u, v = pix % W + 0.5, pix // W + 0.5
    half = 0.5 * EYE_CROP * ds.meta.intrinsics[0] / float(depth.mean())
    near = [np.maximum(np.abs(u - float(uv[k, 0])), np.abs(v - float(uv[k, 1]))) <= half + 1 for k in range(2)]
    assert pix.size > 0 and (near[0] | near[1]).all() and near[0].any() and near[1].any()
    # blink_frames = 1: every stage-1 frame is a blinking one; a head without eyes draws no eye rays.
    blinking = set(np.flatnonzero(ds.eye < BLINKING)) & set(ds.meta.train)
    assert blinking and all(tr.pick_frame(blinks=True) in blinking for _ in range(20))
    plain = Trainer(tmp_path / "p", ds, model_config(ds.meta), TrainConfig(), "cpu", progress=False)
    assert plain.eye_pixels(pose).numel() == 0 and plain.blinking.numel() == 0


def test_scene_metadata_keeps_its_old_form_without_eyes(scene: Path, tmp_path: Path) -> None:
    import json

    data = shutil.copytree(scene, tmp_path / "data")
    doc = json.loads((data / "meta.json").read_text())
    assert len(doc["eyes"]) == 2
    with_eyes = load_dataset(data)
    del doc["eyes"]
    (data / "meta.json").write_text(json.dumps(doc))
    without = load_dataset(data)
    assert without.meta.eyes is None and "eyes" not in without.meta.to_dict()
    assert with_eyes.fingerprint() != without.fingerprint()
    # The fingerprint of metadata without eyes is computed as before eyes existed.
    import hashlib
    from dataclasses import asdict

    before = {k: v for k, v in asdict(without.meta).items() if k not in ("eyes", "framing")}  # nor the framing, added later
    h = hashlib.sha256(json.dumps(before, sort_keys=True).encode())
    for arr in (without.frames, without.parsing, without.background, without.poses, without.features, without.audio.samples, without.eye):
        a = np.ascontiguousarray(arr)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.data)
    assert without.fingerprint() == h.hexdigest()
