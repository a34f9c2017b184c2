"""The head poses a run was taught, and edits outside them (``render --yaw/--pitch/--roll``,
``--strict-pose``, ``sway:``): the range round-trips through the run folder, a run trained within
+-2 degrees of yaw warns at 15 degrees and not at 1, ``--strict-pose`` refuses, per-frame tracks
reach the right frames, and the idle motion stays inside the range."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.cli import main
from adnerf.model import render_clip  # the render loop: what the spies replace
from adnerf.commands.pose_edits import angle_tracks, edit_poses, parse_angle, sway
from adnerf.commands.render_video import RenderError, render_audio_video, render_frames
from adnerf.io import AudioTrack, write_video
from adnerf.formats.dataset import load_dataset
from adnerf.model.pose_range import PoseRange
from adnerf.model.run_folder import load_run, taught_pose_range
from adnerf.model.train import TrainConfig, train
from adnerf.pose import HeadPose, euler_rotation
from adnerf.synth import SynthConfig, synthesize

SCENE = SynthConfig(seconds=1.6, size=32, voice="formant", seed=5, max_yaw=2.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("range") / "data", SCENE)


@pytest.fixture(scope="module")
def run(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg = TrainConfig(head_iters=4, torso_iters=2, rays=64, log_every=2, checkpoint_every=4)
    return train(scene, tmp_path_factory.mktemp("rangerun") / "run", config=cfg, progress=False)


@pytest.fixture(scope="module")
def speech(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.4 s of a loud tone with a pulse (check_speech wants sound), as an mp4's audio."""
    sr = 16000
    t = np.arange(int(0.4 * sr)) / sr
    path = tmp_path_factory.mktemp("speech") / "speech.mp4"
    write_video(path, np.zeros((10, 16, 16, 3), np.uint8), 25.0, AudioTrack((0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), sr, 0.0))
    return path


def _poses(yaw_deg: np.ndarray, base: tuple[float, float, float] = (0.4, 0.1, 0.0)) -> np.ndarray:
    """Poses whose rotation is ``R_y(yaw) @ B`` for a fixed ``B``, at a fixed translation."""
    like = torch.zeros((), dtype=torch.float64)
    B = euler_rotation(*base, like=like).numpy()
    out = np.tile(np.eye(4), (len(yaw_deg), 1, 1))
    out[:, :3, :3] = euler_rotation(torch.as_tensor(np.radians(yaw_deg)), 0.0, 0.0, like=like).numpy() @ B
    out[:, :3, 3] = [0.0, 0.1, 5.0]
    return out


def test_the_range_is_measured_about_the_mean_rotation_and_in_the_edits_axes() -> None:
    """Yaws of -2..+2 degrees about a tilted base pose read back as yaw -2..+2, pitch and roll 0
    (so a range is not an artefact of the canonical frame's orientation), with a 1-degree
    histogram of 4 bins."""
    yaws = np.linspace(-2.0, 2.0, 41)
    r = PoseRange.from_poses(_poses(yaws), head_width=2.0)
    np.testing.assert_allclose(r.rotation[0], [-2.0, 2.0], atol=1e-9)
    np.testing.assert_allclose(r.rotation[1:], 0.0, atol=1e-9)
    assert sum(r.histogram[0]) == 41 and len(r.histogram[0]) == 5  # bins -2..-1, ..., 2..3 (the max on an edge)
    rot, trans = r.excess(_poses(np.array([0.0, 3.0, -7.0])))
    np.testing.assert_allclose(rot[:, 0], [0.0, 1.0, 5.0], atol=1e-9)
    assert not trans.any()
    assert r.check(_poses(np.array([6.9]))) is None  # 4.9 past: inside the 5-degree margin
    assert "yaw +7.5" in r.check(_poses(np.array([7.5])))


def test_the_range_round_trips_through_its_dict_and_json() -> None:
    r = PoseRange.from_poses(_poses(np.linspace(-1.5, 3.0, 10)), head_width=1.5)
    back = PoseRange.from_dict(json.loads(json.dumps(r.to_dict())))
    for name in ("reference", "translation"):
        np.testing.assert_array_equal(getattr(back, name), getattr(r, name))
    np.testing.assert_allclose(back.rotation, r.rotation, atol=1e-4)
    assert back.histogram == r.histogram and back.frames == r.frames and back.head_width == r.head_width
    with pytest.raises(ValueError, match="not a stored pose range"):
        PoseRange.from_dict({"reference": [1, 0, 0]})


def test_a_run_records_its_training_frames_pose_range(scene: Path, run: Path) -> None:
    """run.json holds the training frames' range (not the held-out ones'), and a run written before
    the range was stored gets the same from its dataset."""
    ds = load_dataset(scene)
    doc = json.loads((run / "run.json").read_text())
    stored = PoseRange.from_dict(doc["pose_range"])
    assert stored.frames == len(ds.meta.train) < ds.meta.n_frames
    np.testing.assert_allclose(stored.rotation, taught_pose_range(ds.poses, ds.meta).rotation, atol=1e-4)
    assert np.abs(stored.rotation[0]).max() < 2.5  # the scene's yaw spans +-2 degrees
    del doc["pose_range"]
    (run / "run.json").write_text(json.dumps(doc))
    try:
        older = load_run(run).pose_range
    finally:
        doc["pose_range"] = stored.to_dict()
        (run / "run.json").write_text(json.dumps(doc))
    assert older is not None
    np.testing.assert_allclose(older.rotation, stored.rotation, atol=1e-4)


def test_render_warns_far_outside_the_taught_yaw_and_strict_pose_refuses(run: Path, speech: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    argv = ["render", str(run), "--audio", str(speech)]
    assert main([*argv, "--yaw", "1", "-o", str(tmp_path / "near.mp4")]) == 0
    assert "outside what the training frames showed" not in capsys.readouterr().err
    assert main([*argv, "--yaw", "15", "-o", str(tmp_path / "far.mp4")]) == 0
    err = capsys.readouterr().err
    assert "adnerf: warning:" in err and "outside what the training frames showed" in err and "yaw +1" in err
    assert main([*argv, "--yaw", "15", "--strict-pose", "-o", str(tmp_path / "refused.mp4")]) != 0
    assert "--strict-pose refuses" in capsys.readouterr().err
    assert not (tmp_path / "refused.mp4").exists()


def test_a_per_frame_yaw_file_turns_each_frame_by_its_own_angle(scene: Path, run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Frame k of a track gets the track's k-th angle: the rendered poses equal the constant edit
    of that angle, frame by frame (a track read in the wrong order or applied to every frame fails)."""
    ds, r = load_dataset(scene), load_run(run)
    seen: list[HeadPose] = []
    real = render_clip.render_frame

    def spy(model, camera, pose, code, plate, **kw):  # noqa: ANN001, ANN003, ANN202
        seen.append(pose)
        return real(model, camera, pose, code, plate, **kw)

    monkeypatch.setattr(render_clip, "render_frame", spy)
    idx = ds.meta.test[:3]
    plate = ds.background.astype(np.float32) / 255.0
    render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=np.array([0.0, 10.0, -4.0]))
    tracked = [p.R.clone() for p in seen]
    for k, angle in enumerate((0.0, 10.0, -4.0)):
        seen.clear()
        render_frames(r, ds.features[idx[k : k + 1]], ds.poses[idx[k : k + 1]], plate, yaw=angle)
        torch.testing.assert_close(tracked[k], seen[0].R, atol=1e-12, rtol=0)
    with pytest.raises(RenderError, match="one angle per frame"):
        render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=np.zeros(2))


def test_the_idle_sway_stays_inside_the_taught_range(scene: Path) -> None:
    """An amplitude far larger than the range is held inside it on every frame and axis swayed,
    for yaw (an exactly additive edit) and pitch (not additive: held by iterating)."""
    ds = load_dataset(scene)
    taught = taught_pose_range(ds.poses, ds.meta)
    poses = ds.poses[np.arange(200) % ds.meta.n_frames]
    tracks = {"yaw": parse_angle("sway:20,3"), "pitch": parse_angle("sway:20,5")}
    angles = angle_tracks(tracks, poses, 25.0, taught)
    got = taught.angles(edit_poses(poses, angles))
    for k in (0, 1):
        assert got[:, k].min() >= taught.rotation[k, 0] - 1e-6 and got[:, k].max() <= taught.rotation[k, 1] + 1e-6
        assert np.ptp(angles[:, k]) > 0.5 * np.ptp(taught.rotation[k])  # it moves, not clamped to nothing
    assert taught.check(edit_poses(poses, angles)) is None


def test_sway_is_smooth_bounded_and_starts_at_rest() -> None:
    a = sway(250, 25.0, 3.0, 6.0)
    assert a[0] == 0.0 and np.abs(a).max() <= 3.0
    assert np.abs(np.diff(a)).max() < 2 * math.pi * 3.0 * 2.71 / 6.0 / 25.0 + 1e-9  # no jumps: bounded by the fastest term's slope


@pytest.mark.parametrize("bad", ["sway:0,5", "sway:2", "sway:40,5", "sway:2,-1", "200", "left", "nan"])
def test_bad_angle_specs_are_refused_with_what_is_accepted(bad: str) -> None:
    with pytest.raises(ValueError, match="sway|degrees"):
        parse_angle(bad)


def test_a_sway_needs_a_known_range(run: Path, speech: Path, tmp_path: Path) -> None:
    r = load_run(run)
    r.pose_range = None
    with pytest.raises(RenderError, match="pose range the run was taught"):
        render_audio_video(r, speech, tmp_path / "x.mp4", yaw="sway:2,5")


def test_the_sweeps_lifted_landmarks_turn_with_the_head() -> None:
    """Landmarks lifted with the head layer's depth and turned with the head land where the turned
    head's points project: an exact depth map of points on a sphere, landmarks at pixel centres,
    a 12-degree yaw. A depth taken as z instead of the distance along the unit ray moves them by
    pixels."""
    from adnerf.evaluation.pose_sweep import _FACE, _lifted, _project

    from adnerf.cameras import Camera, intrinsics_matrix

    h = w = 64
    camera = Camera(intrinsics_matrix(120.0, 120.0, 32.0, 32.0), h, w)
    pose = HeadPose(euler_rotation(0.1, -0.05, 0.02, like=torch.zeros((), dtype=torch.float64)), torch.tensor([0.05, -0.02, 4.0], dtype=torch.float64))
    fx, fy, cx, cy = 120.0, 120.0, 32.0, 32.0
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([(jj - cx) / fx, (ii - cy) / fy, np.ones_like(jj)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    centre = pose.t.numpy()  # a sphere of radius 1 about the head centre: distance along each ray to it
    b = d @ centre
    disc = b**2 - (centre @ centre - 1.0)
    depth = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), 0.0)
    opacity = (disc > 0).astype(np.float32)
    landmarks = np.zeros((68, 2))
    rng = np.random.default_rng(0)
    landmarks[_FACE] = rng.integers(24, 40, size=(len(_FACE), 2)) + 0.5  # pixel centres on the sphere's face
    points, kept = _lifted(camera, landmarks, depth, opacity, pose)
    assert len(kept) == len(_FACE)
    np.testing.assert_allclose(_project(camera, points, pose), landmarks[kept], atol=1e-9)
    turned = pose.perturbed(yaw=math.radians(12.0))
    cam = depth[landmarks[kept, 1].astype(int), landmarks[kept, 0].astype(int), None] * d[landmarks[kept, 1].astype(int), landmarks[kept, 0].astype(int)]
    moved = ((turned.R @ pose.R.T @ (torch.as_tensor(cam) - pose.t).T).T + turned.t).numpy()
    expected = np.stack([fx * moved[:, 0] / moved[:, 2] + cx, fy * moved[:, 1] / moved[:, 2] + cy], 1)
    np.testing.assert_allclose(_project(camera, points, turned), expected, atol=1e-9)
    assert np.abs(expected - landmarks[kept]).max() > 3.0  # the turn moved them: the check above is not trivial


def test_clamping_moves_poses_into_the_range_and_leaves_those_inside() -> None:
    r = PoseRange.from_poses(_poses(np.linspace(-2.0, 2.0, 21)), head_width=2.0)
    inside = _poses(np.array([-1.5, 0.3, 2.0]))
    np.testing.assert_allclose(r.clamp(inside), inside, atol=1e-12)
    far = _poses(np.array([9.0, -7.0]))
    far[:, :3, 3] += [0.5, 0.0, 0.0]
    got = r.clamp(far)
    np.testing.assert_allclose(r.angles(got)[:, 0], [2.0, -2.0], atol=1e-9)
    np.testing.assert_allclose(got[:, :3, 3], [[0.0, 0.1, 5.0]] * 2, atol=1e-12)
    assert r.excess(got)[0].max() < 1e-9 and r.excess(got)[1].max() < 1e-9


def test_the_torso_reads_the_track_not_the_edit_by_default(scene: Path, run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Under a yaw edit the head's rays move with the edited pose while the torso reads the track's
    own pose; "clamped" hands it the edited pose clamped to the range, "edited" the edited pose;
    the pose signal a layer reads is the override's code."""
    from adnerf.model.conditions import FrameCondition
    from adnerf.model.pose_range import torso_reads

    ds, r = load_dataset(scene), load_run(run)
    seen: list[tuple[HeadPose, HeadPose | None]] = []
    real = render_clip.render_frame

    def spy(model, camera, pose, code, plate, **kw):  # noqa: ANN001, ANN003, ANN202
        seen.append((pose, kw.get("read_pose")))
        return real(model, camera, pose, code, plate, **kw)

    monkeypatch.setattr(render_clip, "render_frame", spy)
    idx = ds.meta.test[:1]
    plate = ds.background.astype(np.float32) / 255.0
    render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=15.0)
    moved, read = seen[-1]
    np.testing.assert_allclose(read.matrix().numpy(), ds.poses[idx][0], atol=1e-12)
    assert r.pose_range.angles(moved.matrix()[None].numpy())[0, 0] > 10.0
    render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=15.0, torso_pose="clamped")
    clamped = seen[-1][1].matrix()[None].numpy()
    np.testing.assert_allclose(r.pose_range.angles(clamped)[0, 0], r.pose_range.rotation[0, 1], atol=1e-9)
    render_frames(r, ds.features[idx], ds.poses[idx], plate, yaw=15.0, torso_pose="edited")
    assert seen[-1][1] is None
    with pytest.raises(ValueError, match="torso's pose"):
        torso_reads("head", ds.poses[idx], ds.poses[idx], r.pose_range)
    cond = FrameCondition(torch.zeros(4), moved, {"pose": read.code()})
    torch.testing.assert_close(cond.signal("pose"), read.code())
    assert not torch.equal(cond.signal("pose"), moved.code())


def test_density_says_how_often_the_training_frames_came_near_a_pose() -> None:
    """Yaws of 20 frames at -1.9..-1.1 degrees and 20 at +1.1..+1.9 (mean 0): half the frames lie
    within half a degree of -1.5 and of +1.5, none near -0.3 or +9 (bins a degree off, or a
    histogram read from the wrong end, give other shares)."""
    yaws = np.concatenate([np.linspace(-1.9, -1.1, 20), np.linspace(1.1, 1.9, 20)])
    r = PoseRange.from_poses(_poses(yaws), head_width=2.0)
    np.testing.assert_allclose(r.density(_poses(np.array([-1.5, 1.5, -0.3, 9.0])), within_deg=0.5), [0.5, 0.5, 0.0, 0.0], atol=1e-12)
