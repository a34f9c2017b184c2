"""Radiance layers: a frame is its layers composited front to back over the plate, with known
answers from constant fields, and a new layer plugs into a model without editing it."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from torch import Tensor, nn

from adnerf.cameras import Camera
from adnerf.fields import FieldOutput
from adnerf.model.conditions import FrameCondition
from adnerf.formats.dataset import SceneMeta
from adnerf.model.layers import RadianceLayer
from adnerf.model.talking_head import (
    ModelConfig,
    TalkingHead,
    model_config,
    render_frame,
    render_layers,
    render_on_plate,
)
from adnerf.pose import HeadPose, euler_rotation

SIZE = 24


class Constant(nn.Module):
    """A field of one colour and one density everywhere (what the layer's box cuts out of it)."""

    def __init__(self, rgb: tuple[float, float, float], density: float) -> None:
        super().__init__()
        self.anchor = nn.Parameter(torch.zeros(()))  # a parameter, for the layer to read the dtype from
        self.rgb, self.density = torch.tensor(rgb), density
        self.conditions_seen: list[Tensor | None] = []

    def forward(self, positions: Tensor, directions: Tensor, condition: Tensor | None = None) -> FieldOutput:
        self.conditions_seen.append(condition)
        shape = positions.shape[:-1]
        return FieldOutput(self.rgb.to(positions).expand(*shape, 3), torch.full(shape, self.density, dtype=positions.dtype, device=positions.device))


def _scene(head_in_front: bool = True) -> tuple[TalkingHead, Camera, HeadPose, Tensor]:
    meta = SceneMeta(
        width=SIZE, height=SIZE, intrinsics=(30.0, 30.0, SIZE / 2, SIZE / 2), fps=25.0, near=4.0, far=8.0, head_aabb=((-0.6, -0.7, -0.6), (0.6, 0.7, 0.6)),
        torso_aabb=((-1.2, 0.3, 4.5), (1.2, 2.0, 6.5)), mouth=(0.0, 0.3, -0.5), feature_kind="logmel", feature_dim=8, n_frames=1, train=[0], test=[],
    )  # fmt: skip
    torch.manual_seed(0)
    model = TalkingHead(replace(model_config(meta), head_in_front=head_in_front)).eval()
    pose = HeadPose(euler_rotation(0.2, -0.1, 0.05, like=torch.zeros((), dtype=torch.float64)), torch.tensor([0.0, 0.2, 6.0], dtype=torch.float64))
    plate = torch.rand(SIZE, SIZE, 3, generator=torch.Generator().manual_seed(1))
    return model, meta.camera(), pose, plate


def _opacity(layer: RadianceLayer, rays, pose: HeadPose, density: float) -> Tensor:  # noqa: ANN001
    """``1 - exp(-density * length of the ray inside the box)``: constant density, exactly."""
    near, far = layer.crossing(rays, pose)
    return -torch.expm1(-density * (far - near).clamp(min=0)).float()


@pytest.mark.parametrize("head_in_front", [True, False])
def test_a_frame_is_its_layers_in_order_over_the_plate(head_in_front: bool) -> None:
    model, cam, pose, plate = _scene(head_in_front)
    head, torso = model.layers["head"], model.layers["torso"]
    head.coarse = head.fine = Constant((1.0, 0.0, 0.0), 3.0)
    torso.coarse = torso.fine = Constant((0.0, 0.0, 1.0), 2.0)
    code = torch.zeros(model.config.audio_dim)
    out = render_frame(model, cam, pose, code, plate)
    rays = cam.rays().flatten()
    a_h, a_t = _opacity(head, rays, pose, 3.0), _opacity(torso, rays, pose, 2.0)
    both = (a_h > 0.3) & (a_t > 0.3)
    assert both.any() and ((a_h > 0.3) & (a_t == 0)).any()  # the boxes overlap on screen, and not everywhere
    red, blue = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0])
    head_on_plate = red * a_h[:, None] + (1 - a_h[:, None]) * plate.reshape(-1, 3)
    torso_on_plate = blue * a_t[:, None] + (1 - a_t[:, None]) * plate.reshape(-1, 3)
    if head_in_front:  # RAD-NeRF's order
        want = red * a_h[:, None] + (1 - a_h[:, None]) * torso_on_plate
    else:  # AD-NeRF's
        want = blue * a_t[:, None] + (1 - a_t[:, None]) * head_on_plate
    torch.testing.assert_close(out.rgb.reshape(-1, 3), want, rtol=0, atol=2e-5)
    assert list(model.layers) == (["torso", "head"] if head_in_front else ["head", "torso"])
    torch.testing.assert_close(out.head_opacity.reshape(-1), a_h, rtol=0, atol=2e-5)
    torch.testing.assert_close(out.torso_opacity.reshape(-1), a_t, rtol=0, atol=2e-5)
    # The head alone (the stage-1 picture), and the same along a subset of rays.
    alone = render_frame(model, cam, pose, code, plate, layers=("head",))
    torch.testing.assert_close(alone.rgb.reshape(-1, 3), head_on_plate, rtol=0, atol=2e-5)
    some = torch.arange(0, SIZE * SIZE, 7)
    part = render_on_plate(model, rays[some], FrameCondition(code, pose), plate.reshape(-1, 3)[some], layers=("head",))
    torch.testing.assert_close(part, alone.rgb.reshape(-1, 3)[some], rtol=0, atol=1e-6)
    # Each layer alone, premultiplied: the head's colour is red times its opacity.
    each = render_layers(model, rays[some], FrameCondition(code, pose))
    assert list(each) == list(model.layers)
    torch.testing.assert_close(each["head"].rgb, red * a_h[some, None], rtol=0, atol=2e-5)
    torch.testing.assert_close(each["torso"].opacity, a_t[some], rtol=0, atol=2e-5)
    with pytest.raises(ValueError, match="no layer 'hat'"):
        render_frame(model, cam, pose, code, plate, layers=("hat",))


def test_each_layer_reads_its_own_conditions() -> None:
    model, cam, pose, plate = _scene()
    head, torso = model.layers["head"], model.layers["torso"]
    head.coarse = head.fine = Constant((1.0, 0.0, 0.0), 3.0)
    torso.coarse = torso.fine = Constant((0.0, 0.0, 1.0), 2.0)
    code = torch.arange(model.config.audio_dim, dtype=torch.float32)
    render_frame(model, cam, pose, code, plate)
    assert all(torch.equal(c, code) for c in head.coarse.conditions_seen)  # the head: audio only
    want = torch.cat([code, pose.code().float()])  # the torso: audio, then the pose's 9-d code
    assert torso.coarse.conditions_seen and all(torch.equal(c, want) for c in torso.coarse.conditions_seen)


def test_a_new_layer_plugs_in_without_editing_the_model() -> None:
    """A toy "hat" layer (canonical, so it moves with the head; it reads a new signal) is added to
    a model as it is; in front of everything it covers the head, behind the head it is covered."""
    model, cam, pose, plate = _scene()
    code = torch.zeros(model.config.audio_dim)
    hat_field = Constant((0.0, 1.0, 0.0), 1e4)  # opaque green
    hat = RadianceLayer("hat", hat_field, None, ((-0.3, -1.2, -0.3), (0.3, -0.6, 0.3)), (8, 0), space="canonical", conditions=("hat_style",))
    style = torch.tensor([0.5, 0.25])
    cond_extra = {"hat_style": style}
    rays = cam.rays().flatten()
    near, far = hat.crossing(rays, pose)
    deep = (far - near) > 0.05  # rays that cross the hat for real: opaque there
    assert deep.any()

    model.layers["hat"] = hat  # on top of the stack
    cond = FrameCondition(code, pose, cond_extra)
    front = render_on_plate(model, rays, cond, plate.reshape(-1, 3))
    torch.testing.assert_close(front[deep], torch.tensor([0.0, 1.0, 0.0]).expand(int(deep.sum()), 3), rtol=0, atol=1e-4)
    assert all(torch.equal(c, style) for c in hat_field.conditions_seen)
    # The hat moves with the head: under another pose it lies elsewhere on screen.
    turned = HeadPose(pose.R, pose.t + torch.tensor([0.4, 0.0, 0.0], dtype=torch.float64))
    assert not torch.equal(hat.crossing(rays, turned)[1] > hat.crossing(rays, turned)[0], far > near)

    # Behind everything: the head's own layers now cover it where they are opaque.
    model.layers = nn.ModuleDict({"hat": hat, "head": model.layers["head"], "torso": model.layers["torso"]})
    model.layers["head"].coarse = model.layers["head"].fine = Constant((1.0, 0.0, 0.0), 1e4)
    behind = render_on_plate(model, rays, cond, plate.reshape(-1, 3))
    head_near, head_far = model.layers["head"].crossing(rays, pose)
    covered = deep & ((head_far - head_near) > 0.05)
    assert covered.any()
    assert (behind[covered, 0] > 0.99).all()  # red head in front of the green hat
    assert math.isclose(float(front[covered, 1].min()), 1.0, abs_tol=1e-4)


def test_layers_refuse_what_they_cannot_render() -> None:
    with pytest.raises(ValueError, match="space"):
        RadianceLayer("x", Constant((0, 0, 0), 1.0), None, ((0, 0, 0), (1, 1, 1)), (4, 0), space="world", conditions=())
    model, cam, pose, plate = _scene()
    cfg = model.config
    with pytest.raises(ValueError, match="condition values"):
        TalkingHead(type(cfg)(**{**cfg.__dict__, "audio_dim": cfg.audio_dim + 1}))
    with pytest.raises(KeyError, match="no 'eye' signal"):
        FrameCondition(torch.zeros(3), pose).signal("eye")


def test_runs_stored_before_the_layer_order_keep_the_torso_in_front() -> None:
    model, cam, pose, plate = _scene()
    stored = model.config.to_dict()
    assert stored["head_in_front"] is True  # new models: the head over the torso
    assert ModelConfig.from_dict(stored) == model.config
    del stored["head_in_front"]  # run.json of a run trained before the option
    old = ModelConfig.from_dict(stored)
    assert old.head_in_front is False and list(TalkingHead(old).layers) == ["head", "torso"]


def test_a_new_signal_is_one_registration_and_the_head_trains_on_it() -> None:
    """A made-up ``brow`` signal (a value a frame carries, encoded to 3 inputs): registered once, a
    head layer that lists it is built (its fields' input widened by 3), reads its code in every
    sample, and two optimiser steps on a frame change the weights that read it and lower the loss.
    Unregistered, a layer that names it is refused."""
    from adnerf.model.conditions import SIGNALS, Signal, register_signal, signal_width
    from adnerf.model.talking_head import LayerConfig, _layer

    model, cam, pose, plate = _scene()
    cfg = model.config
    with pytest.raises(KeyError, match="brow"):
        signal_width("brow", cfg.audio_dim)
    register_signal(Signal("brow", 3, lambda v: torch.cat([v, v * v, torch.sin(3 * v)], dim=-1)))
    try:
        conditions = (*cfg.head_conditions, "brow")
        width = sum(signal_width(c, cfg.audio_dim) for c in conditions)
        assert width == cfg.head.cond_dim + 3
        head = _layer(cfg, LayerConfig("head", "canonical", cfg.head_aabb, cfg.head_samples, replace(cfg.head, cond_dim=width), replace(cfg.head_fine, cond_dim=width), conditions))
        model.layers["head"] = head
        brow = torch.tensor([0.4])
        cond = FrameCondition(torch.zeros(cfg.audio_dim), pose, {"brow": brow})
        assert torch.equal(cond.vector(conditions, torch.float32)[-3:], torch.cat([brow, brow * brow, torch.sin(3 * brow)]))
        rays = cam.rays().flatten()
        hit = head.crossing(rays, pose)
        rays = rays[(hit[1] - hit[0]) > 0.05]  # the rays that cross the head's box
        assert rays.origins.shape[0] > 20
        target = torch.full((rays.origins.shape[0], 3), 0.8)

        def loss() -> Tensor:
            return ((head.render(rays, cond, background=torch.zeros_like(target)).final.rgb - target) ** 2).mean()

        reads = [p for p in head.parameters() if p.ndim == 2 and p.shape[1] >= width]  # the first linear maps of the fields
        before = [p.detach().clone() for p in reads]
        opt = torch.optim.Adam(head.parameters(), lr=1e-2)
        first = float(loss().detach())
        for _ in range(2):
            opt.zero_grad()
            loss().backward()
            opt.step()
        assert reads and any(not torch.equal(p[:, -3:], b[:, -3:]) for p, b in zip(reads, before))  # the columns that read the brow moved
        assert float(loss().detach()) < first
    finally:
        SIGNALS.pop("brow", None)


@pytest.mark.parametrize("head_in_front", [True, False])
def test_the_model_is_built_from_its_layer_configs(head_in_front: bool) -> None:
    """Each :class:`LayerConfig` of ``ModelConfig.layers`` is a layer of the model, in the same
    drawing order, with its space, box, samples, conditions and fields' widths."""
    model, _, _, _ = _scene(head_in_front)
    cfg = replace(model.config, eye_dim=8)
    layers = cfg.layers
    assert [c.name for c in layers] == (["torso", "head"] if head_in_front else ["head", "torso"])
    by = {c.name: c for c in layers}
    assert (by["head"].space, by["torso"].space) == ("canonical", "camera")
    assert by["head"].conditions == ("audio", "eye") and by["torso"].conditions == ("audio", "pose")
    for c in model.config.layers:
        layer = model.layers[c.name]
        assert (layer.space, layer.aabb, layer.samples, layer.conditions) == (c.space, c.aabb, c.samples, c.conditions)
        assert layer.coarse.config == c.coarse and layer.fine.config == c.fine


def test_a_registered_signal_is_trained_from_the_dataset_and_rendered_at_rest(tmp_path) -> None:  # noqa: ANN001
    """A made-up ``brow`` signal with a track (here the synthetic scene's true jaw) and a rest
    value: a model config that names it widens the head's input by its width and stores it; the
    Trainer hands each frame its own value and two steps move the weights that read it; a frame
    rendered without one gets the rest value; a dataset without values is refused."""
    import json

    from adnerf.formats.dataset import load_dataset
    from adnerf.model.conditions import SIGNALS, Signal, register_signal
    from adnerf.model.run_folder import RunError
    from adnerf.model.talking_head import ModelConfig
    from adnerf.model.train import TrainConfig, Trainer
    from adnerf.synth import SynthConfig, synthesize

    data = synthesize(tmp_path / "data", SynthConfig(seconds=1.2, size=24, seed=2))
    ds = load_dataset(data)
    register_signal(Signal("brow", 3, lambda v: torch.cat([v, v * v, torch.sin(3 * v)], dim=-1), track=lambda d: None if d.truth is None else d.truth.jaw, rest=(0.25,)))
    try:
        mcfg = model_config(ds.meta, signals=("brow",))
        assert mcfg.head_conditions[-1] == "brow" and mcfg.head.cond_dim == model_config(ds.meta).head.cond_dim + 3
        assert ModelConfig.from_dict(json.loads(json.dumps(mcfg.to_dict()))) == mcfg  # stored with the run
        tr = Trainer(tmp_path, ds, mcfg, TrainConfig(head_iters=2, torso_iters=0, rays=64), "cpu", False)
        code = torch.zeros(mcfg.audio_dim)
        for f in (0, 7, 20):
            assert torch.equal(tr.condition(f, code, ds.head_pose(f)).extra["brow"], torch.tensor([ds.truth.jaw[f]], dtype=torch.float32))
        head = tr.model.layers["head"]
        reads = [p for p in head.parameters() if p.ndim == 2 and p.shape[1] >= mcfg.head.cond_dim]  # the first linear maps of the fields
        before = [p.detach()[:, -3:].clone() for p in reads]
        tr.fit()
        assert tr.head_step == 2 and reads and any(not torch.equal(p[:, -3:], b) for p, b in zip(reads, before))  # the columns reading the brow moved
        assert torch.equal(tr.model.condition(code, ds.head_pose(0)).extra["brow"], torch.tensor([0.25]))  # rendering new audio: at rest
        with pytest.raises(RunError, match="'brow' signal"):
            Trainer(tmp_path, load_dataset(data, truth=False), mcfg, TrainConfig(head_iters=2, torso_iters=0, rays=64), "cpu", False)
    finally:
        SIGNALS.pop("brow", None)
