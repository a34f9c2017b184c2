"""The torso follows its own motion: measured in the frames (preprocess), stored with the dataset,
handed to the torso layer as a map of its rays, and given back to the frames whose poses a render
plays."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch

from adnerf.formats.dataset import DatasetError, LABEL_HEAD, LABEL_TORSO, SceneMeta, check_torso, load_dataset
from adnerf.model.conditions import FrameCondition, torso_rays_map
from adnerf.model.talking_head import TalkingHead, model_config, render_frame
from adnerf.pose import HeadPose
from adnerf.preprocess.torso_motion import torso_motion

from test_layers import Constant

SIZE = 72


def _affine(scale: float, angle_deg: float, shift: tuple[float, float], centre: tuple[float, float]) -> np.ndarray:
    """An OpenCV affine map (pixel centres at integers): rotate and scale about ``centre``, then shift."""
    m = cv2.getRotationMatrix2D(centre, angle_deg, scale)
    m[:, 2] += shift
    return m


def _clip() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames whose shoulders (a textured torso under a head disc) move by known maps, with
    four of seven frames at rest so that the clip's median is the picture at rest."""
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (SIZE, SIZE, 3)).astype(np.float32), (0, 0), 1.5) * 3 - 250
    yy, xx = np.mgrid[:SIZE, :SIZE]
    torso = (yy > 40 + 0.25 * np.abs(xx - SIZE / 2)).astype(np.float32)
    maps = [np.eye(2, 3)] * 4 + [_affine(1.03, 2.0, (1.5, -1.0), (36, 60)), _affine(0.98, -1.5, (-2.0, 0.75), (36, 60)), _affine(1.0, 0.0, (0.5, 1.25), (36, 60))]
    frames, labels = [], []
    for m in maps:
        alpha = cv2.warpAffine(torso, m, (SIZE, SIZE), borderMode=cv2.BORDER_REPLICATE)[..., None]  # the outline moved smoothly, not to whole pixels
        picture = alpha * cv2.warpAffine(texture, m, (SIZE, SIZE), borderMode=cv2.BORDER_REFLECT) + (1 - alpha) * 200.0
        label = ((alpha[..., 0] > 0.5) * LABEL_TORSO).astype(np.uint8)
        label[(yy - 22) ** 2 + (xx - 36) ** 2 < 12**2] = LABEL_HEAD
        frames.append(np.clip(picture, 0, 255).astype(np.uint8))
        labels.append(label.astype(np.uint8))
    return np.stack(frames), np.stack(labels), np.stack(maps)


def test_the_torso_motion_is_measured_in_the_cameras_pixels() -> None:
    """Each frame's map is the one that moved its torso, in the camera's pixel convention (centres
    at +0.5): the torso's pixels land within 0.1 px of where the true map puts them (the maps move
    them by up to 2.6 px). Fails when the map is inverted (reference from frame instead of frame
    from reference) or blurred first (a 5-pixel Gaussian prefilter: 0.8 px off)."""
    frames, labels, true_cv = _clip()
    found = torso_motion(frames, labels)
    assert found.failed == [] and found.region_px > 0
    # OpenCV's map moved integer-centred pixels; the same motion of +0.5-centred ones:
    true = true_cv.copy()
    true[:, :, 2] += 0.5 * (1.0 - true_cv[:, :, :2].sum(-1))
    rows, cols = np.nonzero(labels[0] == LABEL_TORSO)
    points = np.stack([cols + 0.5, rows + 0.5], -1)  # camera pixel centres of the torso at rest
    for k in range(len(frames)):
        want = points @ true[k, :, :2].T + true[k, :, 2]
        got = points @ found.maps[k, :, :2].T + found.maps[k, :, 2]
        assert np.abs(got - want).max() < 0.1, k
    # Registered on pictures scaled to 3/4 of the width: the same maps, to within the smaller
    # pictures' precision (the shift scaled back; kept at the small picture's, 0.9 px off).
    small = torso_motion(frames, labels, work_width=SIZE * 3 // 4)
    for k in range(len(frames)):
        want = points @ true[k, :, :2].T + true[k, :, 2]
        assert np.abs(points @ small.maps[k, :, :2].T + small.maps[k, :, 2] - want).max() < 0.35, k
    report = found.report()
    assert report["frames"] == 7 and report["failed"] == 0 and report["shift_px_p95"] > 1.0


def test_a_clip_without_torso_keeps_it_still() -> None:
    frames, labels, _ = _clip()
    found = torso_motion(frames, np.where(labels == LABEL_TORSO, 0, labels).astype(np.uint8))
    assert found.region_px == 0 and len(found.failed) == len(frames) and np.array_equal(found.maps, np.repeat(np.eye(2, 3)[None], len(frames), 0))
    with pytest.raises(ValueError, match="must match"):
        torso_motion(frames, labels[:, :10])


def test_the_rays_map_looks_where_the_pixel_was_in_the_reference() -> None:
    """The direction map of an affine motion sends the ray of the frame's pixel ``u`` to the ray of
    the reference pixel ``A^-1 (u - b)``, keeping its depth; the identity gives the identity."""
    rng = np.random.default_rng(0)
    K = (300.0, 320.0, 128.0, 120.0)
    maps = np.stack([_affine(1.0 + 0.05 * rng.standard_normal(), 5 * rng.standard_normal(), tuple(rng.normal(0, 3, 2)), (100, 200)) for _ in range(4)])
    H = torso_rays_map(maps, K).reshape(-1, 3, 3)
    u = rng.uniform(0, 256, (4, 2))
    d = np.concatenate([(u - K[2:]) / K[:2], np.ones((4, 1))], -1) * 2.5  # any depth
    moved = np.einsum("nij,nj->ni", H, d)
    seen = moved[:, :2] / moved[:, 2:] * K[:2] + K[2:]
    want = np.einsum("nij,nj->ni", np.linalg.inv(maps[:, :, :2]), u - maps[:, :, 2])
    np.testing.assert_allclose(seen, want, atol=1e-9)
    np.testing.assert_allclose(moved[:, 2], d[:, 2])
    np.testing.assert_array_equal(torso_rays_map(np.eye(2, 3)[None], K), np.eye(3).reshape(1, 9))


def test_the_torso_layer_draws_its_reference_where_the_frame_moved_it() -> None:
    """A constant torso box under a shift of 3 px right and 2 px up is the unmoved render moved by
    exactly that (the head's layer is not moved); a frame without a value renders at rest."""
    size = 40
    meta = SceneMeta(
        width=size, height=size, intrinsics=(40.0, 40.0, size / 2, size / 2), fps=25.0, near=4.0, far=8.0, head_aabb=((-0.3, -0.3, -0.3), (0.3, 0.3, 0.3)),
        torso_aabb=((-1.0, 0.2, 5.0), (1.0, 1.5, 6.0)), mouth=(0.0, 0.1, -0.2), feature_kind="logmel", feature_dim=8, n_frames=1, train=[0], test=[],
    )  # fmt: skip
    torch.manual_seed(0)
    model = TalkingHead(model_config(meta, torso_motion=True)).eval()
    assert model.layers["torso"].warp == "torso_motion" and model.layers["head"].warp is None
    model.layers["torso"].coarse = model.layers["torso"].fine = Constant((0.0, 0.0, 1.0), 4.0)
    model.layers["head"].coarse = model.layers["head"].fine = Constant((1.0, 0.0, 0.0), 4.0)
    pose = HeadPose(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, -0.3, 5.0], dtype=torch.float64))
    code, plate = torch.zeros(model.config.audio_dim), torch.zeros(size, size, 3)
    shift = np.array([[[1.0, 0.0, 3.0], [0.0, 1.0, -2.0]]])
    still = render_frame(model, meta.camera(), pose, code, plate)
    moved = render_frame(model, meta.camera(), pose, code, plate, signals={"torso_motion": torso_rays_map(shift, meta.intrinsics)[0]})
    a, b = still.torso_opacity, moved.torso_opacity
    assert (a > 0.5).sum() > 50 and not torch.equal(a, b)
    torch.testing.assert_close(b[:-2, 3:], a[2:, :-3], rtol=0, atol=1e-5)  # row y - 2 and column x + 3 of the moved frame
    torch.testing.assert_close(moved.head_opacity, still.head_opacity, rtol=0, atol=0)
    rest = model.condition(code, pose).extra["torso_motion"]
    assert rest.dtype == torch.float64 and torch.equal(rest, torch.eye(3, dtype=torch.float64).reshape(9))
    with pytest.raises(KeyError, match="torso_motion"):
        model.layers["torso"].warped(meta.camera().rays().flatten(), FrameCondition(code, pose))


def test_the_dataset_keeps_the_torso_motion(tmp_path) -> None:  # noqa: ANN001
    """torso.npy is written, read, checked and fingerprinted; a model follows it only where the
    schedule asks (torso_motion 1) and the dataset has it; training hands each frame its own map,
    and a render of dataset frames gets the same maps back."""
    from adnerf.formats.dataset import read_tracks, save_dataset
    from adnerf.model.render_clip import RenderError, frame_signals, render_frames
    from adnerf.model.train import TrainConfig, Trainer, train
    from adnerf.model.run_folder import load_run
    from adnerf.synth import SynthConfig, synthesize

    plain = load_dataset(synthesize(tmp_path / "plain", SynthConfig(seconds=1.2, size=24, seed=2)))
    n = plain.meta.n_frames
    maps = np.repeat(np.eye(2, 3)[None], n, 0)
    maps[:, 0, 2] = np.linspace(-1.5, 1.5, n)
    for bad, match in ((maps[:-1], "must be"), (np.where(np.arange(n)[:, None, None] == 3, 0.0, maps), "frame 3 is singular")):
        with pytest.raises(DatasetError, match=match):
            check_torso(bad, n, "here")
    fields = {k: getattr(plain, k) for k in ("frames", "parsing", "background", "poses", "features", "audio", "eye", "landmarks")}
    root = save_dataset(tmp_path / "moving", plain.meta, **fields, torso=maps)
    ds = load_dataset(root)
    np.testing.assert_array_equal(ds.torso, maps)
    assert ds.fingerprint() != plain.fingerprint() and np.array_equal(read_tracks(root).torso, maps)
    # Two frames a step: the torso's rays carry each one's own map (per-ray conditions).
    run = train(root, tmp_path / "run", config=TrainConfig(head_iters=2, torso_iters=2, rays=64, frames=2), device="cpu", progress=False)
    loaded = load_run(run)
    assert loaded.model.config.torso_motion and loaded.steps["torso"] == 2
    tr = Trainer(tmp_path / "t", ds, loaded.model.config, TrainConfig(head_iters=1, torso_iters=1, rays=64), "cpu", False)
    code = torch.zeros(loaded.model.config.audio_dim)
    want = torso_rays_map(maps, ds.meta.intrinsics)
    for f in (0, 9):
        torch.testing.assert_close(tr.condition(f, code, ds.head_pose(f)).extra["torso_motion"], torch.as_tensor(want[f]), rtol=0, atol=0)
    np.testing.assert_array_equal(frame_signals(loaded, read_tracks(root), [9, 0])["torso_motion"], want[[9, 0]])
    # Rendered with the frames' own maps, the torso is where each frame had it; a wrong signal is refused.
    plate = ds.background.astype(np.float32) / 255.0
    frames = [0, 9]
    own = render_frames(loaded, ds.features[frames], ds.poses[frames], plate, signals=frame_signals(loaded, ds, frames))
    rest = render_frames(loaded, ds.features[frames], ds.poses[frames], plate)
    assert not np.array_equal(own.torso_opacity, rest.torso_opacity) and np.array_equal(own.head_opacity, rest.head_opacity)
    for bad, match in (({"brow": want[:2]}, "reads no 'brow'"), ({"torso_motion": want[:1]}, r"must be \(2, 9\)")):
        with pytest.raises(RenderError, match=match):
            render_frames(loaded, ds.features[frames], ds.poses[frames], plate, signals=bad)
    off = train(root, tmp_path / "off", config=TrainConfig(head_iters=2, torso_iters=0, rays=64, torso_motion=0), device="cpu", progress=False)
    assert not load_run(off).model.config.torso_motion and load_run(off).model.config.frame_signals == ()
    assert not load_run(train(plain.root, tmp_path / "none", config=TrainConfig(head_iters=2, torso_iters=0, rays=64), device="cpu", progress=False)).model.config.torso_motion
    assert replace(loaded.model.config, torso_motion=False).layers[0].warp is None
