"""Schedules scaled to larger steps: the same rays in fewer, larger iterations."""

from __future__ import annotations

from dataclasses import asdict

import pytest

from adnerf.model.train import TrainConfig


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
