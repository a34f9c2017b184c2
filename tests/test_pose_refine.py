"""Per-frame head-pose corrections: the correction's algebra, what training learns and keeps, the
fit of frames training did not see, and the poses a run is judged and rendered under."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.evaluation.evaluate import evaluate_run
from adnerf.evaluation.fitted_poses import judged_poses
from adnerf.formats.dataset import load_dataset
from adnerf.model.pose_refine import PoseCorrections, _inside, composed, corrected, corrected_matrices, fit_corrections, fit_frames
from adnerf.model.render_clip import dataset_track, frame_setup, frame_signals, render_frames
from adnerf.model.run_folder import load_run
from adnerf.model.train import TrainConfig, train
from adnerf.model.train_config import LATER_KEYS
from adnerf.pose import HeadPose, euler_rotation
from adnerf.synth import SynthConfig, synthesize

SCENE = SynthConfig(seconds=1.6, size=32, voice="formant", seed=3)
LEARN = TrainConfig(head_iters=40, torso_iters=4, rays=128, log_every=10, checkpoint_every=20, pose_start=0.5)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("poses") / "data", SCENE)


@pytest.fixture(scope="module")
def run(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train(scene, tmp_path_factory.mktemp("poses_run") / "run", config=LEARN, progress=False)


def _pose(seed: int) -> HeadPose:
    g = torch.Generator().manual_seed(seed)
    angles = (torch.rand(3, generator=g, dtype=torch.float64) - 0.5) * 0.6
    R = euler_rotation(angles[0], angles[1], angles[2], like=angles)
    return HeadPose(R, torch.tensor([0.1, -0.2, 4.0], dtype=torch.float64))


def test_a_correction_turns_and_shifts_the_head_in_its_own_frame() -> None:
    pose = _pose(1)
    same = corrected(pose, torch.zeros(6, dtype=torch.float64))
    assert torch.equal(same.R, pose.R) and torch.equal(same.t, pose.t)  # zero is the tracked pose, exactly
    theta = 0.03
    turned = corrected(pose, torch.tensor([0.0, theta, 0.0, 0.01, -0.02, 0.005], dtype=torch.float64))
    c, s = np.cos(theta), np.sin(theta)
    about_y = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    # R exp(omega): the turn about the head's own y axis, applied before the pose (a swapped
    # product, exp(omega) R, turns about the camera's axis instead and fails here).
    torch.testing.assert_close(turned.R, pose.R @ about_y, rtol=0, atol=1e-15)
    # t + R tau: the shift along the head's own axes; the canonical origin lands there.
    torch.testing.assert_close(turned.t, pose.t + pose.R @ torch.tensor([0.01, -0.02, 0.005], dtype=torch.float64), rtol=0, atol=1e-15)
    torch.testing.assert_close(turned.from_canonical(torch.zeros(3, dtype=torch.float64)), turned.t)
    # The numpy form agrees, frame by frame.
    m = corrected_matrices(np.stack([pose.matrix().numpy()] * 2), np.array([[0, theta, 0, 0.01, -0.02, 0.005], [0] * 6]))
    np.testing.assert_allclose(m[0], turned.matrix().numpy(), atol=1e-15)
    np.testing.assert_array_equal(m[1], pose.matrix().numpy())


def test_the_correction_is_differentiable_at_and_away_from_zero() -> None:
    pose = _pose(2)

    def moved(delta: torch.Tensor) -> torch.Tensor:
        p = corrected(pose, delta)
        return p.from_canonical(torch.tensor([0.3, -0.1, 0.2], dtype=torch.float64))

    for start in (torch.zeros(6), torch.tensor([0.2, -0.1, 0.05, 0.01, 0.0, -0.02])):
        assert torch.autograd.gradcheck(moved, (start.double().requires_grad_(),))
    with pytest.raises(ValueError, match="corrections must be"):
        corrected(pose, torch.zeros(3, dtype=torch.float64))


def test_frames_never_drawn_keep_a_zero_correction() -> None:
    fixes = PoseCorrections(5)
    opt = torch.optim.Adam(fixes.parameters(), lr=1e-2)
    for frame in (1, 3, 1):
        opt.zero_grad()
        fixes(frame, _pose(frame)).t.sum().backward()
        opt.step()
    delta = fixes.delta.detach()
    assert delta[[1, 3]].abs().sum(1).gt(0).all() and torch.equal(delta[[0, 2, 4]], torch.zeros(3, 6, dtype=torch.float64))


def test_the_inside_of_the_head_label_keeps_its_distance_from_the_outline() -> None:
    is_head = torch.zeros(12, 14, dtype=torch.bool)
    is_head[2:10, 3:12] = True
    expected = torch.zeros_like(is_head)
    expected[4:8, 5:10] = True  # two pixels in from every side (an off-by-one margin fails)
    assert torch.equal(_inside(is_head, 2), expected)
    assert not _inside(is_head, 4).any()


def test_training_learns_the_drawn_frames_corrections_and_keeps_them(scene: Path, run: Path, tmp_path: Path) -> None:
    ds = load_dataset(scene)
    loaded = load_run(run)
    delta = loaded.pose_corrections
    assert delta is not None and delta.shape == (ds.meta.n_frames, 6)
    learnt = np.flatnonzero(delta.any(axis=1))
    assert len(learnt) and set(learnt) <= set(ds.meta.train)  # only training frames move; held-out ones stay
    assert np.abs(delta).max() < 0.1  # a fraction of a degree a step: corrections, not new poses
    # The run's renders of its own dataset's track play the learnt poses; another dataset's are its own.
    track, _ = dataset_track(loaded, scene)
    np.testing.assert_allclose(track, corrected_matrices(ds.poses, delta), atol=1e-12)
    assert not np.allclose(track[learnt], ds.poses[learnt])
    assert loaded.learnt_corrections(scene, ds.meta.n_frames) is delta
    assert loaded.learnt_corrections(scene, ds.meta.n_frames + 1) is None  # not the dataset it learnt on
    other = shutil.copytree(scene, tmp_path / "copy")  # the same frames in another folder: not the run's own
    assert loaded.learnt_corrections(other, ds.meta.n_frames) is None
    np.testing.assert_array_equal(dataset_track(loaded, other)[0], ds.poses)
    # A run written before the corrections existed kept the tracked poses.
    assert LATER_KEYS["pose_lr"] == 0.0 and TrainConfig.from_stored({}).pose_lr == 0.0


def test_a_run_without_pose_learning_keeps_the_tracked_poses(scene: Path, tmp_path: Path) -> None:
    plain = train(scene, tmp_path / "plain", config=TrainConfig(head_iters=4, torso_iters=0, rays=64, pose_lr=0.0), progress=False)
    loaded = load_run(plain)
    assert loaded.pose_corrections is None and "pose_corrections" not in torch.load(plain / "checkpoint.pt", weights_only=False)
    np.testing.assert_array_equal(dataset_track(loaded, scene)[0], load_dataset(scene).poses)
    with pytest.raises(ValueError, match="pose_lr"):
        TrainConfig(pose_lr=-1.0).validate()


def test_resuming_restores_the_corrections_and_their_optimizer(scene: Path, tmp_path: Path) -> None:
    # Long enough that frames drawn before the cut are drawn again after it (their rays must not
    # depend on the correction they had when first drawn).
    cfg = TrainConfig(head_iters=40, torso_iters=0, rays=64, log_every=1, checkpoint_every=20, pose_start=0.0)
    straight = train(scene, tmp_path / "straight", config=cfg, progress=False)
    cut = tmp_path / "cut"
    train(scene, cut, config=cfg, progress=False, max_steps=20)
    train(scene, cut, progress=False, resume=True)
    a, b = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (straight, cut))
    fa, fb = a["pose_corrections"], b["pose_corrections"]
    assert torch.equal(fa["delta"], fb["delta"]) and fa["delta"].abs().sum() > 0
    assert all(torch.equal(x, y) for x, y in zip(fa["opt"]["state"][0].values(), fb["opt"]["state"][0].values()))
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key


def test_the_fit_finds_a_known_pose_error(scene: Path, run: Path) -> None:
    """Frames rendered by the run itself under known poses, handed to the fit under poses moved
    by a known error: the fitted correction undoes most of it (a sign error in the correction or
    in its gradient doubles the error instead)."""
    ds = load_dataset(scene)
    loaded = load_run(run)
    frames = [0, ds.meta.n_frames // 2, ds.meta.n_frames - 1]  # far apart: each frame its own pose
    truth_poses = ds.poses[frames]
    clip = render_frames(loaded, ds.features[frames], truth_poses, ds.background.astype(np.float32) / 255.0)
    labels = np.where(clip.head_opacity > 0.5, 1, 0).astype(np.uint8)  # the render's own head
    error = np.array([[0.0, 0.0, 0.0, 0.04, -0.03, 0.0], [0.0, 0.0, 0.12, 0.03, 0.03, 0.0], [0.05, 0.0, 0.0, -0.04, 0.0, 0.0]])
    tracked = corrected_matrices(truth_poses, error)
    camera, plate = frame_setup(loaded, ds.background.astype(np.float32) / 255.0)
    with torch.no_grad():
        codes = loaded.model.frame_codes(torch.as_tensor(ds.features[frames]))
    delta = fit_corrections(loaded.model, camera, plate, clip.frames, labels, tracked, codes, signals=frame_signals(loaded, ds, frames), steps=150, rays=128, lr=5e-3, rim=0.0, mask_weight=0.1)  # a 32 px head has no inside to speak of: its box and outline
    fitted = corrected_matrices(tracked, delta)
    # Where the head's points land in the image, tracked and fitted, against the truth.
    points = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.2, 0.3], [-0.3, -0.3, 0.2]], dtype=torch.float64)
    K = ds.meta.camera()

    def landed(m: np.ndarray) -> np.ndarray:
        return K.project(HeadPose.from_matrix(torch.as_tensor(m))[:, None].from_canonical(points)).numpy()

    before = np.linalg.norm(landed(tracked) - landed(truth_poses), axis=-1).mean(1)
    after = np.linalg.norm(landed(fitted) - landed(truth_poses), axis=-1).mean(1)
    assert (after < 0.5 * before).all(), (before, after)


def test_evaluation_judges_fitted_or_tracked_poses(scene: Path, run: Path) -> None:
    exact = load_dataset(scene)  # a synthetic scene's poses are exact: nothing to fit
    assert np.array_equal(judged_poses(load_run(run), exact, list(exact.meta.test)), exact.poses[exact.meta.test])
    ds = load_dataset(scene, truth=False)  # as a filmed clip's: poses to fit
    loaded = load_run(run)
    test = list(ds.meta.test)
    np.testing.assert_array_equal(judged_poses(loaded, ds, test, "tracked"), ds.poses[test])
    # Training frames training drew take the corrections it learnt, without a fit.
    learnt = [f for f in ds.meta.train if loaded.pose_corrections[f].any()]
    np.testing.assert_allclose(judged_poses(loaded, ds, learnt, "fitted"), corrected_matrices(ds.poses[learnt], loaded.pose_corrections[learnt]), atol=1e-12)
    fitted = judged_poses(loaded, ds, test, "fitted")
    assert not np.allclose(fitted, ds.poses[test])  # held-out frames are fitted now
    metrics, _ = evaluate_run(loaded, ds, "test", poses="tracked")
    assert metrics["poses"] == "tracked" and evaluate_run(loaded, load_dataset(scene), "test")[0]["poses"] == "exact"
    with pytest.raises(ValueError, match="poses must be"):
        judged_poses(loaded, ds, test, "truth")
    assert json.loads(json.dumps(metrics))["split"] == "test"


def test_composed_corrections_move_a_pose_as_the_two_in_turn() -> None:
    g = torch.Generator().manual_seed(5)
    first, then = ((torch.rand(2, 4, 6, generator=g, dtype=torch.float64) - 0.5) * 0.6 for _ in range(2))
    pose = _pose(3)
    poses = HeadPose(pose.R.expand(2, 4, 3, 3), pose.t.expand(2, 4, 3))
    twice, once = corrected(corrected(poses, first), then), corrected(poses, composed(first, then))
    # A swapped product of the turns, or tau_2 taken along the tracked head's axes, fails here.
    torch.testing.assert_close(once.R, twice.R, rtol=0, atol=1e-14)
    torch.testing.assert_close(once.t, twice.t, rtol=0, atol=1e-14)
    zero = torch.zeros(3, 6, dtype=torch.float64)
    assert torch.equal(composed(zero, zero), zero)  # identity turns: no NaN from the axis-angle log
    torch.testing.assert_close(composed(first[0], torch.zeros_like(first[0])), first[0], rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="alike"):
        composed(zero, torch.zeros(3, 3, dtype=torch.float64))


def _fake_fit(calls: list, move: np.ndarray):
    def fit(model, camera, plate, images, labels, poses, codes, **kw):  # noqa: ANN001, ANN202, ARG001
        calls.append({"n": len(images), "poses": poses.copy(), "exclude": kw["exclude"], "steps": kw["steps"]})
        return np.tile(move, (len(images), 1))

    return fit


def test_fit_frames_fits_a_chunk_at_a_time_without_its_mouth_box(scene: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Seven frames in chunks of three: three fits of 3, 3 and 1 frames, each given its own
    frames, poses, codes, eye and signals, the mouth boxes under its start poses, and its seed
    (``seed + lo``); their moves come back in the frames' order."""
    import adnerf.model.pose_refine as refine_module

    ds = load_dataset(scene, truth=False)
    frames = np.array([9, 2, 5, 11, 0, 7, 3])
    start = ds.poses[frames].astype(np.float64)
    start[:, 0, 3] += np.linspace(-0.05, 0.05, len(frames))  # distinct starts: the boxes follow them, not the dataset's poses
    codes = torch.arange(len(frames) * 2, dtype=torch.float32).reshape(len(frames), 2)
    eye, signals = np.linspace(0.0, 1.0, len(frames)), {"torso": np.arange(len(frames) * 3.0).reshape(-1, 3)}
    calls: list = []

    def fit(model, camera, plate, images, labels, poses, codes, **kw):  # noqa: ANN001, ANN202, ARG001
        calls.append({"images": images, "poses": poses, "codes": codes, **kw})
        return np.repeat(codes[:, :1].numpy().astype(np.float64), 6, axis=1)  # each frame's move names its code

    monkeypatch.setattr(refine_module, "fit_corrections", fit)
    move = fit_frames(None, None, None, ds, frames, start, codes, eye=eye, signals=signals, seed=10, chunk=3, steps=5)
    assert [len(c["images"]) for c in calls] == [3, 3, 1] and [c["seed"] for c in calls] == [10, 13, 16] and all(c["steps"] == 5 for c in calls)
    np.testing.assert_array_equal(move[:, 0], codes[:, 0].numpy())
    boxes = ds.meta.mouth_boxes(HeadPose.from_matrix(torch.as_tensor(start)))
    for k, c in enumerate(calls):
        part = slice(3 * k, 3 * k + 3)
        np.testing.assert_array_equal(c["images"], ds.frames[frames[part]])
        np.testing.assert_array_equal(c["poses"], start[part])
        np.testing.assert_array_equal(c["exclude"], boxes[part])
        np.testing.assert_array_equal(c["eye"], eye[part])
        np.testing.assert_array_equal(c["signals"]["torso"], signals["torso"][part])
    assert not np.array_equal(boxes, ds.meta.mouth_boxes(HeadPose.from_matrix(torch.as_tensor(ds.poses[frames].astype(np.float64)))))


def test_pose_refits_compose_the_fits_move_at_their_steps_and_resume_once(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``pose_refit`` 2 over 8 head iterations: passes before step 4 and at the stage's end, each
    composing the fit's move onto every training frame's correction (pose_start 1: the
    corrections learn nothing else), and a run cut after the first pass and resumed makes the
    second only."""
    import adnerf.model.pose_refine as refine_module

    ds = load_dataset(scene)
    move = np.array([0.01, -0.02, 0.005, 0.003, 0.0, -0.004])
    cfg = TrainConfig(head_iters=8, torso_iters=0, rays=64, log_every=1, checkpoint_every=1, pose_start=1.0, pose_refit=2)
    for name, cut in (("straight", None), ("cut", 5)):
        calls: list = []
        monkeypatch.setattr(refine_module, "fit_corrections", _fake_fit(calls, move))
        root = tmp_path / name
        train(scene, root, config=cfg, progress=False, max_steps=cut)
        if cut is not None:
            assert sum(c["n"] for c in calls) == len(ds.meta.train)  # one pass before step 4, none yet at the end
            train(scene, root, progress=False, resume=True)
        assert sum(c["n"] for c in calls) == 2 * len(ds.meta.train)  # each pass once, resumed or not
        delta = load_run(root).pose_corrections
        twice = composed(torch.as_tensor(move), torch.as_tensor(move)).numpy()
        np.testing.assert_allclose(delta[ds.meta.train], np.tile(twice, (len(ds.meta.train), 1)), atol=1e-15)
        assert not delta[ds.meta.test].any()  # held-out frames are never fitted in training
        # The second pass starts from the poses the first left.
        np.testing.assert_allclose(calls[-1]["poses"], corrected_matrices(ds.poses[ds.meta.train[-calls[-1]["n"]:]], np.tile(move, (calls[-1]["n"], 1))), atol=1e-12)
        rows = [json.loads(line) for line in (root / "log.jsonl").read_text().splitlines()]
        assert [(r["pose_refit"], r["step"]) for r in rows if "pose_refit" in r] == [(1, 4), (2, 8)]
    for bad in (TrainConfig(pose_refit=-1), TrainConfig(pose_refit=1, pose_lr=0.0)):
        with pytest.raises(ValueError, match="pose_refit"):
            bad.validate()


def test_a_pose_refit_aligns_training_frames_given_a_known_error(scene: Path, run: Path, tmp_path: Path) -> None:
    """The real refit on a trained head whose training frames' corrections are set to a known
    error: one pass takes most of the error back out (a sign error in composing the fit's move
    doubles it instead)."""
    from adnerf.formats.dataset import load_dataset as load
    from adnerf.model.train import Trainer, mouth_plan
    from adnerf.model.talking_head import ModelConfig

    ds = load(scene, truth=False)
    doc = json.loads((run / "run.json").read_text())
    tcfg = TrainConfig.from_stored(doc["train"])
    (tmp_path / "refit").mkdir()
    tr = Trainer(tmp_path / "refit", ds, ModelConfig.from_dict(doc["model"]), tcfg, "cpu", False, plan=mouth_plan(ds, tcfg))
    tr.load(torch.load(run / "checkpoint.pt", weights_only=False))
    frames = torch.as_tensor(ds.meta.train)
    before = tr.pose_fix.delta.detach()[frames].clone()
    # Within a pass's reach: 40 steps at a learning rate decaying from 1e-3 move at most ~0.016.
    error = torch.tensor([0.0, 0.012, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    with torch.no_grad():
        tr.pose_fix.delta[frames] = composed(before, error.expand(len(frames), 6))
    tr.refit_poses()
    after = tr.pose_fix.delta.detach()[frames]
    off = (after[:, 1] - before[:, 1]).abs().mean()  # the yaw left of the error, about the learnt one
    assert off < 0.5 * 0.012 and tr.pose_refits == 1, off
    # A pass over some frames (the one a budget's probe times) moves theirs only, and says how long it took.
    some = ds.meta.train[:2]
    seconds = tr.refit_poses(some)
    moved = (tr.pose_fix.delta.detach()[frames] != after).any(dim=1)
    assert moved[:2].all() and not moved[2:].any() and seconds > 0 and tr.pose_refits == 2


def test_timing_a_pose_refit_leaves_the_run_as_it_was(scene: Path, run: Path, tmp_path: Path) -> None:
    """``pose_refit_seconds`` (bench real's budget counts the passes with it): a positive time per
    frame from the run's checkpoint, which it does not rewrite; a folder without one is refused."""
    from adnerf.formats.run_folder import RunError
    from adnerf.model.train import pose_refit_seconds

    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    stored = (copy / "checkpoint.pt").read_bytes()
    per_frame = pose_refit_seconds(copy, scene, frames=2)
    assert 0 < per_frame < 60 and (copy / "checkpoint.pt").read_bytes() == stored
    rows = [json.loads(line) for line in (copy / "log.jsonl").read_text().splitlines()]
    assert rows[-1]["pose_refit"] == 1 and rows[-1]["frames"] == 2  # the timed pass, marked as such
    (copy / "checkpoint.pt").unlink()
    with pytest.raises(RunError, match="no checkpoint"):
        pose_refit_seconds(copy, scene)
