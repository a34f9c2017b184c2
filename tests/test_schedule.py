"""Schedules: scaled to larger steps (the same rays in fewer, larger iterations) and rays drawn
from several frames a step."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from adnerf.model.data import load_dataset
from adnerf.model.layers import RadianceLayer
from adnerf.model.train import TrainConfig, Trainer, train
from adnerf.synth import SynthConfig, synthesize


def test_scaled_schedule_draws_the_same_rays_in_fewer_steps() -> None:
    base = TrainConfig()
    s = base.scaled(4)
    assert (s.rays, s.head_iters, s.torso_iters, s.occupancy_every) == (4096, 900, 750, 4)
    assert (s.checkpoint_every, s.log_every) == (round(250 / 4), round(25 / 4))
    # As many rays in all, and every fraction, rate and switch of the schedule kept.
    assert s.rays * (s.head_iters + s.torso_iters) == base.rays * (base.head_iters + base.torso_iters)
    scaled_keys = ("rays", "head_iters", "torso_iters", "occupancy_every", "checkpoint_every", "log_every")
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
    seen: list[tuple[int, int, int]] = []  # (speech's frame, pose's frame, rays) of each head render
    real = RadianceLayer.render

    def spy(self: RadianceLayer, rays, cond, **kw):  # noqa: ANN001, ANN003, ANN202
        if self.name == "head":
            frame = int(np.argmin(np.linalg.norm(ds.poses[:, :3, 3] - cond.pose.t.numpy(), axis=1)))
            seen.append((int(cond.audio[0]), frame, rays.origins.shape[0]))
        return real(self, rays, cond, **kw)

    monkeypatch.setattr(RadianceLayer, "render", spy)
    # An audio code that names its frame, to see whose speech each part is rendered under.
    monkeypatch.setattr(Trainer, "code", lambda self, frame: torch.full((self.model.config.audio_dim,), float(frame)))
    cfg = TrainConfig(head_iters=3, torso_iters=0, rays=64, frames=4, eye_rays=0.0, log_every=1)
    train(data, tmp_path / "run", config=cfg, progress=False)
    assert len(seen) == 4 * cfg.head_iters and all(n == 16 for _, _, n in seen)
    assert all(speech == frame and frame in ds.meta.train for speech, frame, _ in seen)
    assert len({frame for _, frame, _ in seen}) > cfg.head_iters  # not one frame a step
    for bad in (0, 3):  # none, or a count that does not divide the 1024 rays
        with pytest.raises(ValueError, match="frames"):
            TrainConfig(frames=bad).validate()
