"""Rays of several frames rendered in one call, each under its own frame's condition: the same
colours, opacities and gradients as a call per frame, and the same loss for training."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from adnerf.fields import (
    FieldConfig,
    RadianceField,
    SampleRows,
    fast_config,
    paper_config,
)
from adnerf.model.conditions import FrameCondition
from adnerf.formats.dataset import SceneMeta, load_dataset
from adnerf.model.distributed import Ranks
from adnerf.model.talking_head import TalkingHead, model_config
from adnerf.model.train import TrainConfig, Trainer, _optimise
from adnerf.pose import HeadPose, euler_rotation
from adnerf.renderer import PerRay
from adnerf.rng import uniform
from adnerf.synth import SynthConfig, synthesize

SIZE = 20
FRAMES = 3


def _model(eye: bool = False) -> tuple[TalkingHead, SceneMeta]:
    meta = SceneMeta(
        width=SIZE, height=SIZE, intrinsics=(26.0, 26.0, SIZE / 2, SIZE / 2), fps=25.0, near=4.0, far=8.0, head_aabb=((-0.6, -0.7, -0.6), (0.6, 0.7, 0.6)),
        torso_aabb=((-1.2, 0.3, 4.5), (1.2, 2.0, 6.5)), mouth=(0.0, 0.3, -0.5), feature_kind="logmel", feature_dim=8, n_frames=FRAMES, train=list(range(FRAMES)), test=[],
    )  # fmt: skip
    torch.manual_seed(0)
    model = TalkingHead(model_config(meta, eye=eye))
    for p in model.parameters():  # away from the initial transparent head, so every ray carries colour
        p.data.add_(0.3 * torch.randn_like(p))
    return model, meta


def _conditions(model: TalkingHead) -> list[FrameCondition]:
    """Three frames with different speech, poses (turned by up to 12 degrees) and eye openings."""
    like = torch.zeros((), dtype=torch.float64)
    conds = []
    for k in range(FRAMES):
        R = euler_rotation(0.1 * k, -0.2 + 0.1 * k, 0.05 * k, like=like)
        pose = HeadPose(R, torch.tensor([0.02 * k, 0.2, 6.0 - 0.1 * k], dtype=torch.float64))
        code = torch.randn(model.config.audio_dim, generator=torch.Generator().manual_seed(k), requires_grad=True)
        conds.append(model.condition(code, pose, 1.0 - 0.4 * k))
    return conds


def _frames_of_rays(meta: SceneMeta) -> tuple[object, object, torch.Tensor]:
    """One frame's rays (every pixel), the rays of all frames side by side as one batch, and the
    frame of each ray of that batch."""
    rays = meta.camera().rays().flatten()
    n = rays.origins.shape[0]
    return rays, rays[torch.arange(FRAMES * n) % n], torch.arange(FRAMES).repeat_interleave(n)


@pytest.mark.parametrize("layer", ["head", "torso"])
@pytest.mark.parametrize("occupancy", [False, True])
def test_one_call_for_several_frames_renders_what_a_call_per_frame_does(layer: str, occupancy: bool) -> None:
    model, meta = _model(eye=True)
    conds = _conditions(model)
    lay = model.layers[layer]
    if occupancy:  # empty-space skipping packs the samples: each must keep its own ray's condition
        lay.update_occupancy(conds[0], generator=torch.Generator().manual_seed(0))  # the grid counts as estimated
        grid = lay.occupancy
        grid.occupied = torch.rand(grid.occupied.shape, generator=torch.Generator().manual_seed(2)) < 0.5  # half the cells empty
    else:
        lay.occupancy = None
    rays, batch, which = _frames_of_rays(meta)
    apart = [lay.render(rays, c) for c in conds]
    per_ray = FrameCondition.of_rays(conds, which)
    together = lay.render(batch, per_ray)
    same = torch.ones(len(which), dtype=torch.bool)
    if occupancy:
        # A coarse sample that lies on a face between an occupied and an empty cell (the samples'
        # regular spacing puts some there) is classified by rounding at 1e-14, which a batched and
        # a single pose transform do differently: either answer is right. Such rays are compared
        # only after showing that every disagreement of the two is such a tie.
        sampler = lay.renderer(rays.origins).coarse_sampler
        at_once = sampler(lay.to_space(batch, per_ray.pose)).positions()
        one_by_one = torch.cat([sampler(lay.to_space(rays, c.pose)).positions() for c in conds])
        flip = grid.is_occupied(at_once) != grid.is_occupied(one_by_one)
        rel = (at_once[flip] - grid.aabb_min) / grid.cell_size
        assert not flip.any() or float((rel - rel.round()).abs().min(dim=-1).values.max()) < 1e-9  # ties only
        same = ~flip.any(dim=-1)
        assert float(same.double().mean()) > 0.97
    for part in ("coarse", "fine"):
        for key in ("rgb", "opacity", "depth"):
            want = torch.cat([getattr(getattr(o, part), key) for o in apart])[same]
            got = getattr(getattr(together, part), key)[same]
            assert torch.allclose(got, want, atol=1e-5, rtol=1e-5), (part, key, float((got - want).abs().max()))
    # The frames differ, so a batch rendered under one frame's condition would not pass.
    first = torch.cat([apart[0].final.rgb] * FRAMES)
    assert float((together.final.rgb - first).detach().abs().max()) > 0.05
    # Gradients reach each frame's own audio code as they do from its own call.
    (torch.cat([o.final.rgb for o in apart])[same].sum()).backward()
    want_grads = [c.audio.grad.clone() for c in conds]
    for c in conds:
        c.audio.grad = None
    together.final.rgb[same].sum().backward()
    for c, want in zip(conds, want_grads):
        assert want.abs().max() > 0
        assert torch.allclose(c.audio.grad, want, atol=1e-5, rtol=1e-4)


def test_render_hits_takes_each_rays_condition_through_its_chunks() -> None:
    model, meta = _model()
    conds = _conditions(model)
    head = model.layers["head"]
    rays, batch, which = _frames_of_rays(meta)
    with torch.no_grad():
        hit, got = head.render_hits(batch, FrameCondition.of_rays(conds, which), chunk=37)
        for k, c in enumerate(conds):
            hit_k, want = head.render_hits(rays, c, chunk=1000)
            assert torch.equal(hit[which == k], hit_k)
            assert torch.allclose(got.rgb[which[hit] == k], want.rgb, atol=1e-5, rtol=0)


def test_per_ray_conditions_are_each_rays_frame_and_refused_where_they_cannot_be() -> None:
    model, _ = _model(eye=True)
    conds = _conditions(model)
    which = torch.tensor([2, 0, 0, 1])
    c = FrameCondition.of_rays(conds, which)
    assert c.per_ray and not conds[0].per_ray
    for i, k in enumerate(which.tolist()):
        assert torch.equal(c.audio[i], conds[k].audio) and torch.equal(c.pose.R[i], conds[k].pose.R)
        assert torch.equal(c.vector(("audio", "eye"), torch.float32)[i], conds[k].vector(("audio", "eye"), torch.float32))
    assert c.pose.code().shape == (4, 9)
    with pytest.raises(ValueError, match="at least one"):
        FrameCondition.of_rays([], which)
    with pytest.raises(ValueError, match="different signals"):
        FrameCondition.of_rays([conds[0], FrameCondition(conds[1].audio, conds[1].pose)], which)
    with pytest.raises(ValueError, match="one-frame"):
        FrameCondition.of_rays([c], which)
    with pytest.raises(ValueError, match="one frame's condition"):
        model.layers["head"].update_occupancy(c)
    with pytest.raises(ValueError, match="batch shape"):
        PerRay(torch.zeros(5, 2)).at_samples(torch.Size([4, 8]), None)


def test_one_part_of_several_frames_is_the_loss_of_a_part_per_frame() -> None:
    """``_optimise`` weights each part's means by its rays, so joining equal parts changes nothing."""
    model, meta = _model()
    conds = _conditions(model)
    head = model.layers["head"]
    rays, batch, which = _frames_of_rays(meta)
    n = rays.origins.shape[0]
    target = torch.rand(FRAMES * n, 3, generator=torch.Generator().manual_seed(5))
    mask = torch.rand(FRAMES * n, generator=torch.Generator().manual_seed(6)) > 0.5

    def step(joined: bool) -> tuple[float, list[torch.Tensor]]:
        opt = torch.optim.SGD(head.parameters(), lr=0.0)  # a step that moves nothing: only the loss and gradients are read
        if joined:
            parts = [(head.render(batch, FrameCondition.of_rays(conds, which)), target, mask, None)]
        else:
            parts = [(head.render(rays, conds[k]), target[which == k], mask[which == k], None) for k in range(FRAMES)]
        loss, _ = _optimise(parts, 0.1, opt)
        return loss, [p.grad.clone() for p in head.parameters() if p.grad is not None]

    loss_apart, grads_apart = step(False)
    loss_joined, grads_joined = step(True)
    assert math.isclose(loss_joined, loss_apart, rel_tol=1e-5)
    assert len(grads_joined) == len(grads_apart) > 0
    for g, h in zip(grads_joined, grads_apart):
        assert torch.allclose(g, h, atol=1e-6, rtol=1e-3)


@pytest.mark.parametrize("config", ["paper", "fast", "paper gated", "fast gated"])
def test_a_field_folds_each_rays_condition_as_the_per_point_condition_reads(config: str) -> None:
    """``SampleRows`` (a row per ray, folded into the conditioned layers' biases, at the input and
    at the skip; a gated field's projection taken per ray and gathered per point) against the same
    condition copied to every point; values and gradients."""
    cond_dim = 7
    cfg = paper_config(cond_dim) if config.startswith("paper") else fast_config(cond_dim)
    gate = 3 if config.endswith("gated") else 0
    cfg = FieldConfig.from_dict({**cfg.to_dict(), "depth": 6, "width": 32, "density_activation": "softplus", "cond_gate": gate})  # no dead densities
    torch.manual_seed(3)
    field = RadianceField(cfg).double()
    assert config.startswith("fast") or cfg.skips == (4,)
    rows = torch.randn(5, cond_dim, dtype=torch.float64, requires_grad=True)
    ray = torch.tensor([[0, 0, 3], [4, 1, 1], [2, 2, 0], [3, 4, 4]])  # the points' rays, shape (4, 3)
    points = torch.rand(4, 3, 3, dtype=torch.float64) * 1.6 - 0.8
    dirs = torch.nn.functional.normalize(torch.randn(4, 3, 3, dtype=torch.float64), dim=-1)
    folded = field(points, dirs, SampleRows(rows, ray))
    grads = torch.autograd.grad(folded.rgb.sum() + folded.density.sum(), [rows, *field.parameters()])
    dense = field(points, dirs, rows[ray])
    want = torch.autograd.grad(dense.rgb.sum() + dense.density.sum(), [rows, *field.parameters()])
    assert torch.allclose(folded.rgb, dense.rgb, atol=1e-12) and torch.allclose(folded.density, dense.density, atol=1e-12)
    assert float(dense.density.detach().std()) > 0 and float(grads[0].abs().max()) > 0
    for g, w in zip(grads, want):
        assert torch.allclose(g, w, atol=1e-12)
    # Another row for one point changes that point only.
    moved = ray.clone()
    moved[1, 0] = 2
    other = field(points, dirs, SampleRows(rows, moved))
    changed = (other.rgb - folded.rgb).abs().amax(dim=-1) > 1e-9
    assert changed[1, 0] and changed.sum() == 1
    with pytest.raises(ValueError, match="ray index"):
        field(points, dirs, SampleRows(rows, ray[:2]))


def test_per_ray_gradients_are_the_same_every_time() -> None:
    """A step's rays share a few frames' codes, so the backward of the per-ray gathers (frame ->
    ray in ``of_rays``, ray -> point in the field's fold) sums many gradients into each row.
    Indexing's backward adds them atomically across CPU threads, in whatever order the threads
    run: the same step gave gradients that differed in the last bits from one run to the next.
    The gathers sum in a fixed order, so repeating the backward gives identical gradients."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # the adds race only with more than one thread
    try:
        torch.manual_seed(0)
        field = RadianceField(FieldConfig.from_dict({**fast_config(64).to_dict(), "depth": 2, "width": 64}))
        codes = torch.randn(2, 64, requires_grad=True)  # the audio code's width: the gathers are large enough to run on threads
        pose = HeadPose(torch.eye(3), torch.zeros(3))
        which = torch.tensor([0] * 1024 + [1] * 256)  # a frame's rays and an eye batch's
        points = torch.rand(1280, 16, 3) - 0.5
        dirs = torch.nn.functional.normalize(torch.randn(1280, 16, 3), dim=-1)
        ray = torch.randint(0, 1280, (1280, 16))  # each point's ray, in any order (the threads' shares overlap)
        grads = []
        for _ in range(12):
            cond = FrameCondition.of_rays([FrameCondition(codes[0], pose), FrameCondition(codes[1], pose)], which)
            out = field(points, dirs, SampleRows(cond.audio, ray))
            grads.append(torch.autograd.grad(out.rgb.sum() + out.density.sum(), [codes, *field.parameters()]))
        assert float(grads[0][0].abs().max()) > 0
        for other in grads[1:]:
            assert all(torch.equal(g, h) for g, h in zip(grads[0], other))
    finally:
        torch.set_num_threads(threads)


def test_processes_split_each_frames_rays_and_draw_what_one_process_draws(tmp_path: Path) -> None:
    """Under two processes each renders its half of every frame's rays of a step, with the random
    numbers one process draws for those rays: together they are the one-process batch."""
    data = synthesize(tmp_path / "data", SynthConfig(seconds=1.2, size=24, voice="formant", seed=2))
    ds = load_dataset(data, truth=False)
    sizes = (8, 4, 12)  # the rays of three frames (an eye batch may be smaller than a frame's)
    batches = {}
    for ranks in (Ranks(), Ranks(0, 2, "gloo"), Ranks(1, 2, "gloo")):
        tr = Trainer(tmp_path / f"run{ranks.rank}{ranks.world}", ds, model_config(ds.meta), TrainConfig(seed=5), "cpu", False, ranks)
        frames = ds.meta.train[:3]
        groups = [(f, torch.arange(100 * k, 100 * k + n), tr.condition(f, torch.full((64,), float(f)), ds.head_pose(f))) for k, (f, n) in enumerate(zip(frames, sizes))]
        b = tr.batch_of(groups)
        draws = uniform((len(b.pixels), 5), dtype=torch.float64, device="cpu", generator=b.generator)
        batches[(ranks.rank, ranks.world)] = (b, draws)
    one, one_draws = batches[(0, 1)]
    halves = [batches[(r, 2)] for r in (0, 1)]
    # Reassemble the halves group by group: process 0's part of a group, then process 1's.
    order, start = [], 0
    for n in sizes:
        order += [(r, start // 2 + i) for r in (0, 1) for i in range(n // 2)]
        start += n
    pixels = torch.stack([halves[r][0].pixels[i] for r, i in order])
    frames = torch.stack([halves[r][0].frame[i] for r, i in order])
    audio = torch.stack([halves[r][0].condition.audio[i] for r, i in order])
    draws = torch.stack([halves[r][1][i] for r, i in order])
    assert torch.equal(pixels, one.pixels) and torch.equal(frames, one.frame) and torch.equal(audio, one.condition.audio)
    assert torch.equal(draws, one_draws)
    assert not torch.equal(halves[0][1], one_draws[: len(halves[0][1])])  # not simply the first half of the draw
