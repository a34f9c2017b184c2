"""Schedules: scaled to larger steps (the same rays in fewer, larger iterations) and rays drawn
from several frames a step."""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.model import train as train_module
from adnerf.formats.dataset import LABEL_HEAD, load_dataset
from adnerf.model.layers import RadianceLayer
from adnerf.model.talking_head import MOUTH_PLANES_BOX, MOUTH_PLANES_RESOLUTION, TalkingHead, model_config
from adnerf.model.train import TrainConfig, Trainer, train
from adnerf.synth import SynthConfig, synthesize


def test_scaled_schedule_draws_the_same_rays_in_fewer_steps() -> None:
    base = TrainConfig()
    s = base.scaled(4)
    assert (s.rays, s.frames, s.head_iters, s.torso_iters, s.occupancy_every) == (4096, 4, 900, 750, 4)
    assert (s.checkpoint_every, s.log_every) == (round(250 / 4), round(25 / 4))
    # As many rays in all, as many rays per frame drawn (so every frame is drawn as often), and
    # every fraction, rate and switch of the schedule kept.
    assert s.rays * (s.head_iters + s.torso_iters) == base.rays * (base.head_iters + base.torso_iters)
    assert s.rays // s.frames == base.rays // base.frames
    assert TrainConfig(frames=2).scaled(4).frames == 8
    # Learning rates times sqrt(k): what recovered the real clip's held-out quality at k = 4.
    assert (s.lr, s.lr_audio) == (2 * base.lr, 2 * base.lr_audio)
    assert math.isclose(base.scaled(2).lr, math.sqrt(2) * base.lr)
    scaled_keys = ("rays", "frames", "lr", "lr_audio", "head_iters", "torso_iters", "occupancy_every", "checkpoint_every", "log_every")
    kept = {k: v for k, v in asdict(base).items() if k not in scaled_keys}
    assert {k: asdict(s)[k] for k in kept} == kept
    assert base.scaled(1) == base
    # A stage of no iterations stays empty; a short one keeps at least one iteration.
    short = TrainConfig(head_iters=3, torso_iters=0, occupancy_every=2).scaled(4)
    assert (short.head_iters, short.torso_iters, short.occupancy_every) == (1, 0, 1)
    short.validate()
    for bad in (0, -2, 2.0, True):
        with pytest.raises(ValueError, match="positive integer"):
            base.scaled(bad)  # type: ignore[arg-type]


def test_frames_per_step_splits_the_rays_over_frames_each_under_its_own_speech(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = synthesize(tmp_path / "data", SynthConfig(seconds=2.0, size=48, seed=3))
    ds = load_dataset(data)
    seen: dict[str, list[tuple[list[int], list[int]]]] = {"head": [], "torso": []}  # per training render: each ray's speech's frame and pose's frame
    real = RadianceLayer.render

    def spy(self: RadianceLayer, rays, cond, **kw):  # noqa: ANN001, ANN003, ANN202
        if self.training:  # not stage 2's renders of the frozen head
            n = rays.origins.shape[0]
            t = cond.pose.t.detach().expand(n, 3).numpy()  # a learning pose has gradients
            poses = np.argmin(np.linalg.norm(ds.poses[None, :, :3, 3] - t[:, None], axis=2), axis=1)
            seen[self.name].append((cond.audio.expand(n, -1)[:, 0].long().tolist(), poses.tolist()))
            # Each ray's pixel (the camera's rays differ in direction only).
            pixels.append(torch.cdist(rays.directions.float(), camera_dirs).argmin(dim=1))
        return real(self, rays, cond, **kw)

    targets: list[torch.Tensor] = []
    real_optimise = train_module._optimise

    def optimise_spy(parts, *args, **kw):  # noqa: ANN001, ANN002, ANN003, ANN202
        targets.extend(target for _, target, _, _ in parts)
        return real_optimise(parts, *args, **kw)

    def naming_codes(self: TalkingHead, windows: torch.Tensor, frames=None, batch: int = 512) -> torch.Tensor:  # noqa: ANN001
        """Audio codes that name their frame, to see whose speech each ray is rendered under."""
        index = torch.arange(windows.shape[0]) if frames is None else torch.as_tensor(frames).reshape(-1)
        code_calls.append(None if frames is None else len(index))
        return index.float()[:, None].expand(-1, self.config.audio_dim)

    camera_dirs = ds.meta.camera().rays().flatten().directions.float()
    pixels: list[torch.Tensor] = []
    code_calls: list[int | None] = []  # frames per audio network call; None: every frame (stage 2's start)
    monkeypatch.setattr(RadianceLayer, "render", spy)
    monkeypatch.setattr(TalkingHead, "frame_codes", naming_codes)
    monkeypatch.setattr(train_module, "_optimise", optimise_spy)
    cfg = TrainConfig(head_iters=3, torso_iters=3, rays=64, frames=4, eye_rays=0.0, log_every=1)
    train(data, tmp_path / "run", config=cfg, progress=False)
    for stage, iters in (("head", cfg.head_iters), ("torso", cfg.torso_iters)):
        renders = seen[stage]
        assert len(renders) == iters, stage  # a step's frames are rendered in one call
        for speech, poses in renders:
            assert speech == poses and set(poses) <= set(ds.meta.train), stage  # each ray under its own frame's speech and pose
            assert len(poses) == 64 and all(len(set(poses[k : k + 16])) == 1 for k in range(0, 64, 16)), stage  # 16 rays a frame
        assert len({f for _, poses in renders for f in poses}) > iters, stage  # not one frame a step
    # One audio network pass a head step for its four frames, not one a frame; stage 2 encodes
    # every frame once at its start.
    assert code_calls[: cfg.head_iters + 1] == [4] * cfg.head_iters + [None], code_calls
    # Each ray's target is its own frame's pixel (stage 1: the plate off the head).
    frames = torch.as_tensor(ds.frames).reshape(len(ds.frames), -1, 3).float() / 255
    plate = torch.as_tensor(ds.background).reshape(-1, 3).float() / 255
    head = torch.as_tensor(ds.parsing).reshape(len(ds.frames), -1) == LABEL_HEAD
    for k, ((_, poses), pix, target) in enumerate(zip(seen["head"] + seen["torso"], pixels, targets)):
        f = torch.tensor(poses)
        want = torch.where(head[f, pix, None], frames[f, pix], plate[pix]) if k < cfg.head_iters else frames[f, pix]
        assert torch.allclose(target, want), k
    for bad in (0, 3):  # none, or a count that does not divide the 1024 rays
        with pytest.raises(ValueError, match="frames"):
            TrainConfig(frames=bad).validate()


def test_each_frames_head_box_pixels_are_kept_from_its_first_draw(tmp_path: Path) -> None:
    data = synthesize(tmp_path / "data", SynthConfig(seconds=1.2, size=40, seed=4))
    ds = load_dataset(data, truth=False)
    tr = Trainer(tmp_path / "run", ds, model_config(ds.meta), TrainConfig(), "cpu", False)
    head = tr.model.layers["head"]
    sets = []
    for _ in range(2):  # made, then kept
        for f in ds.meta.train:
            pose = ds.head_pose(f)
            near, far = head.crossing(tr.rays, pose)
            want = torch.nonzero(far > near)[:, 0]
            got = tr.head_box_pixels(f, pose)
            assert torch.equal(got, want), f
            sets.append(frozenset(got.tolist()))
    assert len(set(sets)) > 1  # the head moves: frames differ, so one frame's pixels kept for all would fail


def test_sample_counts_head_grid_width_and_gate_from_the_schedule_are_trained_stored_and_rendered(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from adnerf.model.run_folder import load_run
    from adnerf.renderer import VolumeRenderer

    data = synthesize(tmp_path / "data", SynthConfig(seconds=1.2, size=40, seed=5))
    made: list[tuple[int, int]] = []
    real_init = VolumeRenderer.__init__

    def spy(self, bounds, n_coarse, n_fine=0, *args, **kw):  # noqa: ANN001, ANN002, ANN003, ANN202
        made.append((n_coarse, n_fine))
        return real_init(self, bounds, n_coarse, n_fine, *args, **kw)

    monkeypatch.setattr(VolumeRenderer, "__init__", spy)
    cfg = TrainConfig(head_iters=2, torso_iters=2, rays=32, log_every=1, head_samples=6, torso_samples=4, head_grid=32, head_width=48, head_gate=4, head_planes=2)
    train(data, tmp_path / "run", config=cfg, progress=False)
    assert set(made) == {(6, 6), (4, 4)}  # each layer trained with its own count, coarse and fine
    run = load_run(tmp_path / "run")
    assert run.model.layers["head"].samples == (6, 6) and run.model.layers["torso"].samples == (4, 4)
    assert run.model.config.head_fine.grid_max_resolution == 32 and run.model.config.torso_fine.grid_max_resolution == 128
    assert [p.shape[-1] for p in run.model.layers["head"].fine.position_encoding.planes][-1] == 32
    widths = {name: (layer.coarse.config.width, layer.fine.config.width) for name, layer in run.model.layers.items()}
    assert widths == {"head": (32, 48), "torso": (32, 64)}  # only the head's fine MLP is wider
    gates = {name: (layer.coarse.config.cond_gate, layer.fine.config.cond_gate) for name, layer in run.model.layers.items()}
    assert gates == {"head": (4, 4), "torso": (0, 0)}  # both head fields gate the code; the torso does not
    assert run.model.layers["head"].fine.gate is not None and run.model.layers["torso"].fine.gate is None
    # The residual planes: the head's fine field alone, about the dataset's mouth, and trained.
    head = run.model.layers["head"]
    assert head.coarse.cond_residual is None and run.model.layers["torso"].fine.cond_residual is None
    assert head.fine.cond_residual is not None and tuple(head.fine.cond_residual.shape) == (2, 3, 8, MOUTH_PLANES_RESOLUTION, MOUTH_PLANES_RESOLUTION)
    meta = load_dataset(data, truth=False).meta
    assert head.fine.config.cond_planes_min == pytest.approx([m + d for m, d in zip(meta.mouth, MOUTH_PLANES_BOX[0])])
    assert head.fine.config.cond_planes_max == pytest.approx([m + d for m, d in zip(meta.mouth, MOUTH_PLANES_BOX[1])])
    assert float(head.fine.cond_residual.detach().abs().max()) > 0  # zero at the start: two steps moved them
    default = model_config(load_dataset(data, truth=False).meta)
    assert (default.head_samples, default.torso_samples, default.head_fine.grid_max_resolution, default.head_fine.width) == ((16, 16), (16, 16), 256, 64)
    for bad, message in (({"head_samples": 1}, "head_samples"), ({"head_grid": 8}, "head_grid"), ({"head_grid": 64, "preset": "paper"}, "head_grid"), ({"head_width": -1}, "head_width"), ({"head_width": 128, "preset": "paper"}, "head_width"), ({"head_gate": -1}, "head_gate"), ({"head_planes": -1}, "head_planes"), ({"head_planes": 2, "preset": "paper"}, "head_planes")):
        with pytest.raises(ValueError, match=message):
            TrainConfig(**bad).validate()
