"""Training stages as data: a stage's parameter groups decide what moves, stages run in the order
given, a stage waits for the layers it draws frozen, and checkpoints of the layout before the
stages were named resume to the same steps."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from adnerf.formats.dataset import load_dataset
from adnerf.model.run_folder import RunError, load_run, migrate_checkpoint, read_checkpoint
from adnerf.model.stages import AUDIO, ParamGroup, Stage, default_stages, group_parameters
from adnerf.model.talking_head import TalkingHead, model_config
from adnerf.model.train import TrainConfig, Trainer, train
from adnerf.synth import SynthConfig, synthesize


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("stages") / "data", SynthConfig(seconds=1.2, size=24, seed=2))


def _snapshot(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def _moved(before: list[torch.Tensor], module: torch.nn.Module) -> bool:
    return any(not torch.equal(a, b) for a, b in zip(before, module.parameters()))


def test_default_stages_are_adnerfs_two(tiny: Path) -> None:
    cfg = TrainConfig(head_iters=7, torso_iters=5, lr=0.02, lr_audio=0.003)
    head, torso = default_stages(cfg)
    assert (head.name, head.layer, head.iters, head.frozen, head.trains_audio) == ("head", "head", 7, (), True)
    assert [(g.modules, g.lr) for g in head.groups] == [(("head",), 0.02), ((AUDIO,), 0.003)]
    assert (torso.name, torso.layer, torso.iters, torso.frozen, torso.trains_audio) == ("torso", "torso", 5, ("head",), False)
    model = TalkingHead(model_config(load_dataset(tiny, truth=False).meta))
    audio = group_parameters(model, ParamGroup((AUDIO,), 1.0))
    assert len(audio) == len(list(model.audio_net.parameters())) + len(list(model.att_net.parameters()))
    with pytest.raises(ValueError, match="no layer 'neck'"):
        group_parameters(model, ParamGroup(("neck",), 1.0))


def test_a_stage_moves_only_its_parameter_groups(tiny: Path, tmp_path: Path) -> None:
    """A head stage whose only group is the head layer leaves the audio encoders as they were
    (the default head stage moves both); the torso stays untouched by either."""
    ds = load_dataset(tiny, truth=False)
    cfg = TrainConfig(head_iters=3, torso_iters=0, rays=64)
    for groups, audio_moves in (((ParamGroup(("head",), cfg.lr),), False), (default_stages(cfg)[0].groups, True)):
        stage = Stage("head", "head", 3, groups)
        tr = Trainer(tmp_path, ds, model_config(ds.meta), cfg, "cpu", False, stages=[stage])
        audio, head, torso = _snapshot(tr.model.audio_net), _snapshot(tr.model.layers["head"]), _snapshot(tr.model.layers["torso"])
        tr.fit()
        assert tr.steps["head"] == 3 and _moved(head, tr.model.layers["head"])
        assert _moved(audio, tr.model.audio_net) == audio_moves
        assert not _moved(torso, tr.model.layers["torso"])


def test_fit_runs_stages_in_order_within_the_budget_and_waits_for_frozen_layers(tiny: Path, tmp_path: Path) -> None:
    ds = load_dataset(tiny, truth=False)
    cfg = TrainConfig(head_iters=3, torso_iters=2, rays=64)
    tr = Trainer(tmp_path, ds, model_config(ds.meta), cfg, "cpu", False)
    with pytest.raises(ValueError, match="not one of this trainer's"):
        tr.fit([Stage("neck", "torso", 2, ())])
    with pytest.raises(RunError, match=r"stage 2 \(torso\) needs a finished stage 1 \(0/3 head iterations\)"):
        tr.fit([tr.stages["torso"]])  # draws the head frozen before it was trained
    tr.fit(max_steps=4)  # three head steps, then one torso step
    assert tr.steps == {"head": 3, "torso": 1}
    tr.fit()
    assert tr.steps == {"head": 3, "torso": 2}
    tr.set_iterations("torso", 4)  # stretched (bench fields fits its schedule as it goes): the stage and the schedule
    assert (tr.stages["torso"].iters, tr.tcfg.torso_iters) == (4, 4)
    tr.fit()
    assert tr.steps == {"head": 3, "torso": 4}


def test_a_checkpoint_of_the_earlier_layout_resumes_to_the_same_steps(tiny: Path, tmp_path: Path) -> None:
    """A run whose checkpoint has the layout before stages were named (``head_step``, ``opt_head``,
    ...) loads with the same steps and resumes to the weights of an uninterrupted run."""
    cfg = TrainConfig(head_iters=4, torso_iters=2, rays=64, log_every=1, checkpoint_every=2)
    straight = train(tiny, tmp_path / "straight", config=cfg, progress=False)
    old = tmp_path / "old"
    train(tiny, old, config=cfg, progress=False, max_steps=3)  # checkpoint after head step 2
    ckpt = torch.load(old / "checkpoint.pt", weights_only=False)
    stages = ckpt.pop("stages")
    ckpt.update({f"{n}_step": s["step"] for n, s in stages.items()} | {f"opt_{n}": s["optimizer"] for n, s in stages.items()})
    torch.save(ckpt, old / "checkpoint.pt")
    assert migrate_checkpoint(ckpt)["stages"] == stages and migrate_checkpoint(migrate_checkpoint(ckpt)) == migrate_checkpoint(ckpt)
    assert read_checkpoint(old / "checkpoint.pt", "cpu")["stages"]["head"]["step"] == 2
    run = load_run(old)
    assert (run.head_step, run.torso_step, run.trained_layers) == (2, 0, ("head",))
    train(tiny, old, progress=False, resume=True)
    a, b = torch.load(straight / "checkpoint.pt", weights_only=False), torch.load(old / "checkpoint.pt", weights_only=False)
    assert {n: s["step"] for n, s in b["stages"].items()} == {"head": 4, "torso": 2}
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key
    assert load_run(old).trained_layers == tuple(load_run(old).model.layers)
