"""Known-answer tests of what users rely on, each written against a mistake that once passed the
suite: PSNR's peak and its 10 log10, the stage-1 targets (plate, not torso, outside the head),
the mouth-ray square on the mouth, ``--background`` used, ``--yaw`` turning the documented way,
and the render's audio windows in the frame they belong to."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from kornia.metrics import psnr as kornia_psnr

from adnerf.model import render_clip  # the render loop: what the spies replace
from adnerf.cli import main
from adnerf.commands.render_video import audio_frames, render_frames
from adnerf.evaluation.evaluate import eye_boxes_at, eye_psnr, head_metrics, image_metrics, mouth_boxes
from adnerf.io import AudioTrack, read_video
from adnerf.metrics import PSNR_CAP_DB, psnr, psnr_from_mse
from adnerf.formats.dataset import EYE_CROP, LABEL_HEAD, LABEL_TORSO, load_dataset
from adnerf.model.talking_head import model_config
from adnerf.model.train import TrainConfig, Trainer, load_run, train
from adnerf.pose import HeadPose
from adnerf.synth import SynthConfig, synthesize

SCENE = SynthConfig(seconds=1.6, size=32, voice="formant", seed=5)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("beh") / "data", SCENE)


@pytest.fixture(scope="module")
def run(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg = TrainConfig(head_iters=16, torso_iters=8, rays=128, log_every=4, checkpoint_every=8)
    return train(scene, tmp_path_factory.mktemp("behrun") / "run", config=cfg, progress=False)


# ---- PSNR


def test_psnr_of_a_known_noise_level() -> None:
    # +-10 grey levels on every pixel: MSE 100 / 255^2, PSNR 10 log10(255^2 / 100) = 28.13 dB.
    target = np.full((2, 16, 16, 3), 128, np.uint8)
    sign = np.where(np.indices((2, 16, 16, 3)).sum(0) % 2 == 0, 10, -10)
    pred = (target.astype(int) + sign).astype(np.uint8)
    want = 10 * math.log10(255.0**2 / 100.0)
    assert psnr(pred, target) == pytest.approx(want, abs=1e-9)
    assert image_metrics(pred, target)[0] == pytest.approx(want, abs=1e-9)
    head = np.full((2, 16, 16), LABEL_HEAD, np.uint8)
    assert head_metrics(pred, target, head)[0] == pytest.approx(want, abs=1e-9)
    # The training log's form: an MSE of colours in [0, 1].
    assert psnr_from_mse(0.01) == pytest.approx(20.0, abs=1e-12)
    assert psnr_from_mse(1e-4) == pytest.approx(40.0, abs=1e-12)
    assert psnr_from_mse(0.0) == PSNR_CAP_DB and psnr(target, target) == PSNR_CAP_DB
    with pytest.raises(ValueError):
        psnr_from_mse(float("nan"))


def test_psnr_agrees_with_kornia() -> None:
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(1, 3, 20, 24, generator=g), torch.rand(1, 3, 20, 24, generator=g)
    assert psnr(a, b) == pytest.approx(float(kornia_psnr(a.double(), b.double(), 1.0)), abs=1e-9)


def test_training_log_psnr_is_ten_log10_of_the_fine_mse(scene: Path, run: Path) -> None:
    import json

    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    rows = [r for r in rows if "mse" in r]
    assert rows
    for r in rows:
        assert r["psnr"] == pytest.approx(-10.0 * math.log10(r["mse"]), abs=1e-9)


# ---- training targets


def test_stage_one_targets_are_the_frame_on_the_head_and_the_plate_elsewhere(scene: Path, tmp_path: Path) -> None:
    ds = load_dataset(scene)
    tr = Trainer(tmp_path, ds, model_config(ds.meta), TrainConfig(), "cpu", progress=False)
    frame = ds.meta.train[0]
    labels = torch.as_tensor(ds.parsing[frame].reshape(-1))
    pix = torch.arange(labels.numel())
    target = tr.head_target(frame, pix)
    rgb = torch.as_tensor(ds.frames[frame].reshape(-1, 3), dtype=torch.float32) / 255.0
    plate = torch.as_tensor(ds.background.reshape(-1, 3), dtype=torch.float32) / 255.0
    head, torso = labels == LABEL_HEAD, labels == LABEL_TORSO
    assert head.any() and torso.any()
    torch.testing.assert_close(target[head], rgb[head].to(target))
    torch.testing.assert_close(target[~head], plate[~head].to(target))  # the torso too: stage 1 has no torso
    assert not torch.allclose(target[torso], rgb[torso].to(target))


def test_mouth_rays_are_drawn_around_the_mouth(scene: Path, tmp_path: Path) -> None:
    ds = load_dataset(scene)
    tr = Trainer(tmp_path, ds, model_config(ds.meta), TrainConfig(), "cpu", progress=False)
    for frame in ds.meta.train[:5]:
        pix = tr.mouth_pixels(ds.head_pose(frame)).numpy()
        assert pix.size > 0
        W = ds.meta.width
        u, v = pix % W + 0.5, pix // W + 0.5
        uv, _ = ds.meta.mouth_in_image(ds.head_pose([frame]))
        mu, mv = float(uv[0, 0]), float(uv[0, 1])
        assert abs(u.mean() - mu) <= 1.0 and abs(v.mean() - mv) <= 1.0  # centred on the mouth
        x0, y0, x1, y1 = mouth_boxes(ds, [frame])[0]  # and inside the evaluation's mouth crop, give or take a pixel
        assert u.min() >= x0 - 1 and u.max() <= x1 + 1 and v.min() >= y0 - 1 and v.max() <= y1 + 1


def test_eye_boxes_hold_the_pixels_of_the_trainers_eye_squares(scene: Path) -> None:
    """The evaluation's eye boxes are the pixels whose centre lies within ``EYE_CROP / 2`` of an
    eye's projection in both axes (the squares stage 1 draws its eye rays from), checked pixel by
    pixel; an error of 10 levels inside them alone gives the eyes' PSNR exactly."""
    ds = load_dataset(scene)
    meta = ds.meta
    cols, rows = np.meshgrid(np.arange(meta.width) + 0.5, np.arange(meta.height) + 0.5)
    frames = [0, 7, len(ds.frames) - 1]
    boxes = np.stack([eye_boxes_at(meta, ds.head_pose(f)) for f in frames])
    for f, frame_boxes in zip(frames, boxes):
        uv, depth = meta.eyes_in_image(ds.head_pose(f))
        assert abs(float(uv[0, 0]) - float(uv[1, 0])) > 2  # two eyes apart: a swapped axis would show
        for k, (x0, y0, x1, y1) in enumerate(frame_boxes):
            half = 0.5 * EYE_CROP * meta.intrinsics[0] / float(depth[k])
            want = (np.abs(cols - float(uv[k, 0])) <= half) & (np.abs(rows - float(uv[k, 1])) <= half)
            got = np.zeros_like(want)
            got[y0:y1, x0:x1] = True
            assert want.sum() >= 4 and np.array_equal(got, want)
    target = ds.frames[frames]
    pred = target.copy()
    inside = np.zeros(target.shape[:3], dtype=bool)
    for j, frame_boxes in enumerate(boxes):
        for x0, y0, x1, y1 in frame_boxes:
            inside[j, y0:y1, x0:x1] = True
    pred[inside] = np.where(target[inside] < 128, target[inside] + 10, target[inside] - 10)
    pred[~inside] = 255 - target[~inside]  # off the eyes nothing counts
    assert eye_psnr(pred, target, boxes) == pytest.approx(-10 * math.log10((10 / 255) ** 2))
    assert eye_psnr(pred, target, np.zeros_like(boxes)) is None


# ---- render


def _tone(path: Path, seconds: float = 1.0) -> Path:
    from adnerf.formats.dataset import write_wav

    t = np.arange(int(16000 * seconds)) / 16000.0
    write_wav(path, AudioTrack((0.3 * np.sin(2 * np.pi * 220 * t) * (1 + np.sin(2 * np.pi * 3 * t))).astype(np.float32), 16000))
    return path


def test_render_uses_the_given_background(scene: Path, run: Path, tmp_path: Path) -> None:
    green = np.zeros((40, 40, 3), np.uint8)
    green[..., 1] = 255  # BGR on disk: pure green either way
    cv2.imwrite(str(tmp_path / "green.png"), green)
    audio = _tone(tmp_path / "tone.wav")
    argv = ["render", str(run), "--audio", str(audio), "--from", str(scene)]
    assert main([*argv, "-o", str(tmp_path / "plate.mp4"), "--frames", str(tmp_path / "plate")]) == 0
    assert main([*argv, "-o", str(tmp_path / "green.mp4"), "--frames", str(tmp_path / "green"), "--background", str(tmp_path / "green.png")]) == 0
    corner = (slice(0, 3), slice(0, 3))  # far from the person
    with_plate = cv2.imread(str(tmp_path / "plate" / "000000.png"))[corner]
    with_green = cv2.imread(str(tmp_path / "green" / "000000.png"))[corner]
    plate = cv2.imread(str(scene / "background.png"))[corner]
    assert np.abs(with_plate.astype(int) - plate).max() <= 2
    assert np.abs(with_green.astype(int) - green[:3, :3]).max() <= 2
    assert read_video(tmp_path / "green.mp4").frames.shape[0] == len(list((tmp_path / "green").glob("*.png")))


def test_frames_composited_over_further_backgrounds_equal_their_own_renders(scene: Path, run: Path) -> None:
    """What the demo's new-background panel is: the layers of one render over another plate."""
    ds, r = load_dataset(scene), load_run(run)
    idx = list(ds.meta.test[:2])
    plate = ds.background.astype(np.float32) / 255.0
    noise = np.random.default_rng(0).random(plate.shape).astype(np.float32)
    both = render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=5.0, backgrounds=[noise, plate])
    alone = render_frames(r, ds.features[idx], ds.poses[idx], noise, yaw=5.0)
    np.testing.assert_array_equal(both.over[0], alone.frames)
    np.testing.assert_array_equal(both.over[1], both.frames)
    assert not np.array_equal(both.over[0], both.frames)
    np.testing.assert_array_equal(both.head_opacity, alone.head_opacity)
    # A box of pixels (what the demo reads the eyes from): the whole frames' pixels there.
    box = (3, 10, 30, 21)
    part = render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=5.0, backgrounds=[noise], box=box)
    assert part.frames.shape == (2, 11, 27, 3) and part.torso_opacity.shape == (2, 11, 27)
    np.testing.assert_allclose(part.frames, both.frames[:, 10:21, 3:30], atol=1)
    np.testing.assert_allclose(part.over[0], both.over[0][:, 10:21, 3:30], atol=1)
    np.testing.assert_allclose(part.head_opacity, both.head_opacity[:, 10:21, 3:30], atol=1e-5)



def test_a_turned_head_over_the_kept_torso_equals_its_own_render(scene: Path, run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """What the demo's turned panel is: the head turned, the torso kept from the un-turned render
    (it reads the track's pose), composited instead of rendered again."""
    ds, r = load_dataset(scene), load_run(run)
    idx = list(ds.meta.test[:2])
    plate = ds.background.astype(np.float32) / 255.0
    plain = render_frames(r, ds.features[idx], ds.poses[idx], plate, keep=("torso",))
    assert len(plain.kept["torso"]) == 2 and plain.kept["torso"][0][0].opacity.max() > 0.5
    turned = render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=12.0)
    drawn: list[tuple[str, ...]] = []
    real = render_clip.render_frame

    def spy(model, *args, **kw):  # noqa: ANN001, ANN002, ANN003, ANN202
        out = real(model, *args, **kw)
        drawn.append(tuple(name for name in out.opacity if name not in (kw.get("given") or {})))
        return out

    monkeypatch.setattr(render_clip, "render_frame", spy)
    reused = render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=12.0, given=plain.kept)
    assert drawn == [("head",), ("head",)]  # the torso was not rendered again
    np.testing.assert_array_equal(reused.frames, turned.frames)
    np.testing.assert_array_equal(reused.torso_opacity, turned.torso_opacity)
    assert not np.array_equal(turned.frames, plain.frames)
    swapped = {"torso": plain.kept["torso"][::-1]}  # another frame's torso is composited as given
    assert not np.array_equal(render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=12.0, given=swapped).frames, turned.frames)
    with pytest.raises(ValueError, match="given"):
        render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=12.0, given=plain.kept, torso_pose="edited")
    with pytest.raises(ValueError, match="no 'ear' layer"):
        render_frames(r, ds.features[idx], ds.poses[idx], plate, keep=("ear",))

def test_positive_yaw_turns_the_face_towards_the_image_left(scene: Path, run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The documented convention (``render --help``): positive yaw turns the face towards the
    image's left (the person's right), positive pitch nods it down, positive roll turns it
    clockwise in the image. Checked on the point in front of the head's centre (canonical -z)."""
    ds, r = load_dataset(scene), load_run(run)
    seen: list[HeadPose] = []
    real = render_clip.render_frame

    def spy(model, camera, pose, code, plate, **kw):  # noqa: ANN001, ANN003, ANN202
        seen.append(pose)
        return real(model, camera, pose, code, plate, **kw)

    monkeypatch.setattr(render_clip, "render_frame", spy)
    idx = [ds.meta.test[0]]
    plate = ds.background.astype(np.float32) / 255.0
    front = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)  # rigidly on the head: ahead of its centre, and to its image-right side
    cases = {"plain": {}, "yaw": {"yaw": 10.0}, "pitch": {"pitch": 10.0}, "roll": {"roll": 10.0}}
    points = {}
    for name, kw in cases.items():
        render_frames(r, ds.features[idx], ds.poses[idx], plate, **kw)
        points[name] = _project(ds, seen[-1].from_canonical(front))
    du = points["yaw"][0, 0] - points["plain"][0, 0]
    dv = points["pitch"][0, 1] - points["plain"][0, 1]
    dv_roll = points["roll"][1, 1] - points["plain"][1, 1]
    assert du < -0.5 and dv > 0.5 and dv_roll > 0.5


def _project(ds, points: torch.Tensor) -> np.ndarray:  # noqa: ANN001
    fx, fy, cx, cy = ds.meta.intrinsics
    p = points.numpy()
    return np.stack([fx * p[:, 0] / p[:, 2] + cx, fy * p[:, 1] / p[:, 2] + cy], 1)


@pytest.mark.parametrize(("fps", "neighbours"), [(25.0, (10, 6)), (30.0, (9, 6)), (24.0, (10, 6)), (50.0, (9, 7))])
def test_a_click_falls_in_the_window_of_its_frame(fps: float, neighbours: tuple[int, int]) -> None:
    """Frame ``i`` is shown at ``i / fps`` and its feature window is centred there (column 8 of 16
    is the feature at the frame's time): a click at ``k / fps`` is at column 8 of frame ``k``'s
    window, and in its neighbours' as many columns off as their times are (at 50 features per
    second: 2 columns at 25 fps; at 30 fps the frames 33 ms apart land on features 1.67 apart,
    32 and 35 around the click's 33)."""
    sr, k = 16000, 20
    x = 0.01 * np.random.default_rng(0).standard_normal(2 * sr).astype(np.float32)
    at = int(k / fps * sr)
    x[at - 40 : at + 40] += 0.9
    windows = audio_frames(AudioTrack(x, sr, 0.0), fps, "logmel", "click")
    loudest = windows.mean(2).argmax(1)  # the column of the click in each window
    assert (loudest[k - 1], loudest[k], loudest[k + 1]) == (neighbours[0], 8, neighbours[1])


def test_the_render_passes_each_frame_its_own_audio_code(scene: Path, run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ds, r = load_dataset(scene), load_run(run)
    codes: list[torch.Tensor] = []
    real = render_clip.render_frame

    def spy(model, camera, pose, code, plate, **kw):  # noqa: ANN001, ANN003, ANN202
        codes.append(code.clone())
        return real(model, camera, pose, code, plate, **kw)

    monkeypatch.setattr(render_clip, "render_frame", spy)
    idx = list(ds.meta.test)[:3]
    render_frames(r, ds.features[idx], ds.poses[idx], ds.background.astype(np.float32) / 255.0)
    with torch.no_grad():
        want = [r.model.frame_codes(torch.as_tensor(ds.features[idx]), [i])[0] for i in range(len(idx))]
    for got, exp in zip(codes, want):
        torch.testing.assert_close(got, exp)


def test_the_audio_of_frames_is_what_plays_under_them(scene: Path) -> None:
    ds = load_dataset(scene)
    per_frame = ds.audio.sample_rate / ds.meta.fps  # 640 samples at 16 kHz and 25 fps
    piece = ds.audio_of(10, 14)
    assert piece.start == 0.0 and len(piece.samples) == round(4 * per_frame)
    np.testing.assert_array_equal(piece.samples, ds.audio.samples[round(10 * per_frame) : round(14 * per_frame)])
    tail = ds.audio_of(ds.meta.n_frames - 1, ds.meta.n_frames + 2)  # past the end: silence
    assert len(tail.samples) == round(3 * per_frame) and not tail.samples[round(2 * per_frame) :].any()


# ---- the folders' formats


def test_every_file_a_dataset_holds_is_named_by_its_folder_class(scene: Path) -> None:
    """The synthetic writer goes through :class:`DatasetFolder`: each file it wrote is one of the
    class's paths (a writer that spelled a name of its own would leave a file the class does not
    know, and readers would not find it)."""
    from adnerf.formats.dataset import TRUTH_FILES, DatasetFolder

    files = DatasetFolder(scene)
    named = {getattr(files, name) for name, member in vars(DatasetFolder).items() if isinstance(member, property)}
    meta = load_dataset(scene, truth=False).meta
    named |= {files.frame(i) for i in range(meta.n_frames)} | {files.labels(i) for i in range(meta.n_frames)}
    named |= {files.truth_file(k) for k in TRUTH_FILES}
    written = {p for p in scene.rglob("*") if p.is_file()}
    assert written and written <= named, sorted(str(p.relative_to(scene)) for p in written - named)
    assert files.is_dataset() and not DatasetFolder(scene / "nowhere").is_dataset()


def test_a_run_folder_gives_its_scene_and_training_seconds(scene: Path, run: Path) -> None:
    """``RunFolder.meta()`` is the dataset's scene (camera, boxes, feature kind) with every frame
    a training frame (a run stores no split); ``elapsed()`` the checkpoint's seconds per stage."""
    from adnerf.formats.run_folder import RunError, RunFolder

    folder, ds = RunFolder(run), load_dataset(scene, truth=False)
    got = folder.meta()
    assert got.intrinsics == ds.meta.intrinsics and got.head_aabb == ds.meta.head_aabb and got.feature_kind == ds.meta.feature_kind
    assert got.train == list(range(ds.meta.n_frames)) and got.test == []
    assert torch.equal(got.camera().K, ds.meta.camera().K)
    seconds = folder.elapsed()
    assert set(seconds) == {"head", "torso"} and seconds["head"] > 0 and seconds["torso"] > 0
    assert folder.is_run() and not RunFolder(scene).is_run()
    with pytest.raises(RunError, match="no run.json"):
        RunFolder(scene).doc()
