"""Fields (configs, conditioning, canonical warping) and the renderer (chunking, skipping, passes)."""

from __future__ import annotations

import math

import pytest
import torch

from adnerf.analytic import UniformSphere
from adnerf.cameras import intrinsics_matrix, pixel_rays
from adnerf.fields import FieldConfig, RadianceField, SampleRows, fast_config, paper_config
from adnerf.model.conditions import FrameCondition
from adnerf.model.layers import RadianceLayer
from adnerf.occupancy import OccupancyGrid
from adnerf.pose import HeadPose
from adnerf.rays import RayBundle
from adnerf.renderer import VolumeRenderer
from adnerf.samplers import NearFarBounds


def test_paper_config_matches_ad_nerf_architecture() -> None:
    field = RadianceField(paper_config(cond_dim=64))
    # PE(10) of xyz: 63 features, + 64-d audio code = 127 inputs; 8 layers of 256 with the input
    # re-concatenated at layer 4; PE(4) directions: 27 features; view branch of 128.
    assert field.trunk[0].in_features == 63 + 64
    assert field.trunk[4].in_features == 256 + 127
    assert len(field.trunk) == 8 and all(l.out_features == 256 for l in field.trunk)
    assert field.view_layer.in_features == 256 + 27 and field.view_layer.out_features == 128
    n = sum(p.numel() for p in field.parameters())
    expected = (127 * 256 + 256) + 6 * (256 * 256 + 256) + (383 * 256 + 256) + (256 + 1) + (256 * 256 + 256) + (283 * 128 + 128) + (128 * 3 + 3)
    assert n == expected


def test_field_outputs_and_condition_errors() -> None:
    field = RadianceField(fast_config(cond_dim=8))
    out = field(torch.randn(4, 5, 3), None, torch.randn(8))
    assert out.rgb.shape == (4, 5, 3) and out.density.shape == (4, 5)
    assert (out.rgb >= 0).all() and (out.rgb <= 1).all() and (out.density >= 0).all()
    with pytest.raises(ValueError, match="no condition"):
        field(torch.randn(2, 3))
    with pytest.raises(ValueError, match="8 features"):
        field(torch.randn(2, 3), None, torch.randn(7))
    silent = RadianceField(FieldConfig(encoding="pe", depth=2, width=16, skips=(), cond_dim=0))
    with pytest.raises(ValueError, match="view directions"):
        silent(torch.randn(2, 3))
    with pytest.raises(ValueError, match="takes no condition"):
        silent(torch.randn(2, 3), torch.randn(2, 3), torch.randn(4))
    with pytest.raises(ValueError, match="skip"):
        RadianceField(FieldConfig(depth=4, skips=(4,)))
    with pytest.raises(ValueError, match="encoding"):
        RadianceField(FieldConfig(encoding="hash"))  # type: ignore[arg-type]


def test_config_round_trip_and_state_dict(tmp_path) -> None:
    cfg = fast_config(cond_dim=4, aabb_min=(-2, -1, 0), aabb_max=(2, 1, 3))
    assert FieldConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown"):
        FieldConfig.from_dict({**cfg.to_dict(), "typo": 1})
    field = RadianceField(cfg)
    torch.save({"config": cfg.to_dict(), "state": field.state_dict()}, tmp_path / "f.pt")
    blob = torch.load(tmp_path / "f.pt")
    loaded = RadianceField(FieldConfig.from_dict(blob["config"]))
    loaded.load_state_dict(blob["state"])
    x, a = torch.randn(6, 3), torch.randn(4)
    torch.testing.assert_close(loaded(x, None, a).rgb, field(x, None, a).rgb)


def test_a_canonical_layer_sees_the_head_in_its_own_frame() -> None:
    """A head layer's render of camera rays under pose (R, t) is the field's render of the same
    rays moved by the inverse pose; fails if the layer warps by the pose instead of its inverse,
    or leaves the directions unturned."""
    torch.manual_seed(0)
    field = RadianceField(FieldConfig(encoding="pe", pe_frequencies=4, dir_frequencies=2, depth=3, width=32, skips=(2,), cond_dim=4, density_activation="softplus")).double()
    box = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    head = RadianceLayer("head", field, None, box, (16, 0), space="canonical", conditions=("audio",))
    R = torch.linalg.matrix_exp(torch.tensor([[0, 0, 1.0], [0, 0, 0], [-1.0, 0, 0]], dtype=torch.float64) * 0.4)
    pose = HeadPose(R, torch.tensor([0.1, 0.0, 3.0], dtype=torch.float64))
    rays = pixel_rays(intrinsics_matrix(20.0, 20.0, 6.0, 6.0), 12, 12).flatten()
    audio = torch.randn(4, dtype=torch.float64)
    with torch.no_grad():
        posed = head.render(rays, FrameCondition(audio, pose)).final
        moved = RayBundle(pose.to_canonical(rays.origins), rays.directions @ R)  # R^T d, row-wise
        still = RadianceLayer("head", field, None, box, (16, 0), space="camera", conditions=("audio",))
        direct = still.render(moved, FrameCondition(audio, pose)).final
    near, far = head.crossing(rays, pose)
    assert (far > near).sum() > 50 and posed.opacity.max() > 0.3  # the rays do cross the head
    torch.testing.assert_close(posed.rgb, direct.rgb)
    torch.testing.assert_close(posed.opacity, direct.opacity)
    torch.testing.assert_close(posed.depth, direct.depth)


def test_a_camera_layer_reads_the_pose_and_the_audio() -> None:
    """The torso layer: camera space, its field conditioned on the audio code and the pose's code."""
    torch.manual_seed(0)
    field = RadianceField(fast_config(cond_dim=8 + 9, aabb_min=(-1, -1, 2), aabb_max=(1, 1, 4))).double()
    torso = RadianceLayer("torso", field, None, ((-1, -1, 2), (1, 1, 4)), (16, 0), space="camera", conditions=("audio", "pose"))
    rays = pixel_rays(intrinsics_matrix(10.0, 10.0, 4.0, 4.0), 8, 8).flatten()
    pose = HeadPose(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    a = torch.randn(8, dtype=torch.float64)
    with torch.no_grad():
        base = torso.render(rays, FrameCondition(a, pose)).final.rgb
        assert not torch.allclose(base, torso.render(rays, FrameCondition(a, pose.perturbed(yaw=0.3))).final.rgb)
        assert not torch.allclose(base, torso.render(rays, FrameCondition(a + 1, pose)).final.rgb)
        # Its space is the camera's: moving the head moves no sample of the torso.
        moved = HeadPose(pose.R, torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64))
        near, far = torso.crossing(rays, moved)
        near0, far0 = torso.crossing(rays, pose)
    torch.testing.assert_close(near, near0)
    torch.testing.assert_close(far, far0)


def _sphere_setup(size: int = 16):
    K = intrinsics_matrix(18.0, 18.0, size / 2, size / 2)
    rays = pixel_rays(K, size, size)
    sphere = UniformSphere(torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), 0.8, 5.0)
    return rays, sphere


def test_chunked_render_equals_single_batch() -> None:
    rays, sphere = _sphere_setup()
    renderer = VolumeRenderer(NearFarBounds(1.0, 5.0), 16, 16)
    whole = renderer.render_rays(rays.flatten(), sphere)
    bg = torch.rand(16, 16, 3, dtype=torch.float64)
    chunked = renderer.render_chunked(rays, sphere, chunk=37)
    assert chunked.final.rgb.shape == (16, 16, 3) and chunked.final.weights.shape == (16, 16, 32)
    torch.testing.assert_close(chunked.final.opacity.reshape(-1), whole.final.opacity)
    torch.testing.assert_close(chunked.coarse.depth.reshape(-1), whole.coarse.depth)
    with_bg = renderer.render_chunked(rays, sphere, chunk=50, background=bg)
    miss = chunked.final.opacity == 0
    torch.testing.assert_close(with_bg.final.rgb[miss], bg[miss])
    empty = renderer.render_chunked(rays.flatten()[:0], sphere)
    assert empty.final.opacity.shape == (0,)


def test_occupancy_skipping_is_exact_and_cheaper() -> None:
    rays, sphere = _sphere_setup()
    renderer = VolumeRenderer(NearFarBounds(1.0, 5.0), 32, 32)
    full = renderer.render_chunked(rays, sphere)
    grid = OccupancyGrid((-1, -1, 2), (1, 1, 4), resolution=32, threshold=0.1)
    grid.update(sphere.density, jitter=False)
    grid.dilate(1)
    skipped = renderer.render_chunked(rays, sphere, occupancy=grid.is_occupied)
    torch.testing.assert_close(skipped.final.opacity, full.final.opacity)
    torch.testing.assert_close(skipped.final.rgb, full.final.rgb)
    assert skipped.samples_evaluated < full.samples_evaluated / 4
    nothing = OccupancyGrid((10, 10, 10), (11, 11, 11), resolution=2)
    blank = renderer.render_chunked(rays, sphere, occupancy=nothing.is_occupied)
    assert blank.samples_evaluated == 0 and (blank.final.opacity == 0).all()


def test_conditioning_is_forwarded_and_fine_field_used() -> None:
    rays, sphere = _sphere_setup(4)
    seen: list[dict] = []

    def recording(tag: str):
        def field(positions, directions, **cond):
            seen.append({"tag": tag, **cond})
            return sphere(positions, directions)

        return field

    renderer = VolumeRenderer(NearFarBounds(1.0, 5.0), 8, 8)
    out = renderer.render_rays(rays.flatten(), recording("coarse"), recording("fine"), audio="A", pose="P")
    assert [s["tag"] for s in seen] == ["coarse", "fine"]
    assert all(s["audio"] == "A" and s["pose"] == "P" for s in seen)
    assert out.fine is not None and out.fine.weights.shape[-1] == 16
    coarse_only = VolumeRenderer(NearFarBounds(1.0, 5.0), 8, 0).render_rays(rays.flatten(), sphere)
    assert coarse_only.fine is None and coarse_only.final is coarse_only.coarse


def test_jittered_training_render_has_gradients() -> None:
    torch.manual_seed(0)
    field = RadianceField(fast_config(cond_dim=0, aabb_min=(-1, -1, 2), aabb_max=(1, 1, 4)))
    rays, _ = _sphere_setup(8)
    renderer = VolumeRenderer(NearFarBounds(1.5, 4.5), 16, 16)
    out = renderer.render_rays(rays.flatten().map(lambda x: x.float()), lambda p, d: field(p, d), jitter=True, background=torch.ones(3))
    loss = (out.final.rgb - 0.5).square().mean() + (out.coarse.rgb - 0.5).square().mean()
    loss.backward()
    grads = [p.grad for p in field.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)
    assert math.isfinite(loss.item())


def test_shared_condition_equals_per_point_condition() -> None:
    """A single condition vector is folded into the layer biases; the result is the same field."""
    from adnerf.fields import FieldConfig, RadianceField

    torch.manual_seed(0)
    configs = (FieldConfig(depth=4, width=32, skips=(2,), cond_dim=5, pe_frequencies=3), FieldConfig(encoding="triplane", depth=2, width=16, skips=(), cond_dim=5, use_view_dirs=False))
    for cfg in configs + tuple(FieldConfig.from_dict({**c.to_dict(), "cond_gate": 3}) for c in configs):
        field = RadianceField(cfg).double()
        x = torch.rand(7, 3, dtype=torch.float64) * 2 - 1
        d = torch.nn.functional.normalize(torch.randn(7, 3, dtype=torch.float64), dim=-1)
        c = torch.randn(5, dtype=torch.float64)
        shared = field(x, d, c)
        per_point = field(x, d, c.expand(7, 5))
        torch.testing.assert_close(shared.rgb, per_point.rgb, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(shared.density, per_point.density, rtol=1e-12, atol=1e-12)


def _gated_field() -> RadianceField:
    """A tri-plane field whose condition reaches the trunk through the gate alone (the first
    layer's condition columns zeroed), gate open for x > 0 and shut for x < 0."""
    torch.manual_seed(1)
    cfg = FieldConfig(encoding="triplane", depth=2, width=16, skips=(), cond_dim=4, use_view_dirs=False, density_activation="softplus", cond_gate=2)
    field = RadianceField(cfg).double()
    assert field.gate is not None
    with torch.no_grad():
        field.trunk[0].weight[:, -cfg.cond_dim :] = 0.0
        for plane in field.position_encoding.planes:
            plane.zero_()
            plane[0, 0] = torch.linspace(-1.0, 1.0, plane.shape[-1], dtype=torch.float64)[None, :]  # channel 0 of the xy plane: x
        field.gate.weight.zero_()
        field.gate.weight[:, 0] = 200.0  # x > 0: sigmoid -> 1; x < 0: -> 0
        field.gate.bias.zero_()
    return field


def test_a_gated_condition_acts_where_the_gate_is_open_and_nowhere_else() -> None:
    """With the condition's plain columns zeroed, the condition reaches a point only through
    ``P c * sigmoid(G e(x))``: changing the code moves the points the gate opens (x > 0) and
    leaves the shut ones (x < 0) exactly as they were. A gate per ray (or no gate) would move both."""
    field = _gated_field()
    x = torch.tensor([[-0.6, 0.1, 0.2], [-0.3, -0.4, 0.0], [0.4, 0.2, -0.1], [0.7, -0.5, 0.3]], dtype=torch.float64)
    a, b = torch.randn(4, dtype=torch.float64), torch.randn(4, dtype=torch.float64)
    with torch.no_grad():
        one, other = field(x, None, a), field(x, None, b)
    moved = (one.rgb - other.rgb).abs().amax(dim=-1) + (one.density - other.density).abs()
    assert float(moved[:2].max()) < 1e-12 and float(moved[2:].min()) > 1e-4
    # Through rows per ray: the same, point by point.
    rows = torch.stack([a, b])
    ray = torch.tensor([0, 1, 0, 1])
    per_ray = field(x, None, SampleRows(rows, ray))
    torch.testing.assert_close(per_ray.rgb, field(x, None, rows[ray]).rgb, rtol=0, atol=1e-12)


def test_the_gated_condition_passes_gradcheck() -> None:
    torch.manual_seed(2)
    field = RadianceField(FieldConfig(encoding="triplane", depth=2, width=8, skips=(), cond_dim=3, use_view_dirs=False, density_activation="softplus", cond_gate=2)).double()
    x = (torch.rand(5, 3, dtype=torch.float64) * 1.6 - 0.8).requires_grad_()
    rows = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    ray = torch.tensor([0, 1, 1, 0, 1])

    def run(x: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = field(x, None, SampleRows(rows, ray))
        return out.rgb, out.density

    assert torch.autograd.gradcheck(run, (x, rows))


def test_a_gate_needs_a_condition_and_round_trips() -> None:
    with pytest.raises(ValueError, match="cond_gate"):
        RadianceField(FieldConfig(encoding="triplane", depth=2, width=8, skips=(), cond_dim=0, use_view_dirs=False, cond_gate=4))
    with pytest.raises(ValueError, match="cond_gate"):
        RadianceField(FieldConfig(encoding="triplane", depth=2, width=8, skips=(), cond_dim=3, use_view_dirs=False, cond_gate=-1))
    cfg = FieldConfig.from_dict({**fast_config(5).to_dict(), "cond_gate": 4})
    assert FieldConfig.from_dict(cfg.to_dict()) == cfg
    stored = cfg.to_dict()
    del stored["cond_gate"]  # a config stored before the key: no gate
    assert FieldConfig.from_dict(stored).cond_gate == 0
    assert RadianceField(cfg).trunk[0].in_features == RadianceField(fast_config(5)).trunk[0].in_features + 4


def test_posed_box_bounds_match_the_moved_box() -> None:
    """Bounds of a box moved by a rigid pose: the entry and exit points lie on the box's faces in
    the box frame, and rays that miss get empty intervals."""
    from adnerf.pose import HeadPose, euler_rotation
    from adnerf.samplers import PosedAABBBounds

    R = euler_rotation(0.4, -0.3, 0.2, like=torch.zeros(3, 3, dtype=torch.float64))
    pose = HeadPose(R, torch.tensor([0.1, -0.2, 4.0], dtype=torch.float64))
    lo = torch.tensor([-0.8, -1.0, -0.6], dtype=torch.float64)
    hi = -lo
    origins = torch.zeros(500, 3, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(500, 3, dtype=torch.float64) * torch.tensor([0.3, 0.3, 0.0]) + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    from adnerf.rays import RayBundle

    near, far = PosedAABBBounds(lo, hi, pose.R, pose.t)(RayBundle(origins, dirs))
    hit = far > near
    assert hit.any() and (~hit).any()
    for t in (near[hit], far[hit]):
        p = pose.to_canonical(origins[hit] + t[:, None] * dirs[hit])
        on_face = torch.minimum((p - lo).abs(), (p - hi).abs()).amin(dim=-1)
        assert on_face.max() < 1e-9
        assert ((p >= lo - 1e-9) & (p <= hi + 1e-9)).all()
    # Missed rays: a midpoint test over many t never enters the box.
    ts = torch.linspace(0, 10, 400, dtype=torch.float64)
    pts = pose.to_canonical(origins[~hit][:, None] + ts[:, None] * dirs[~hit][:, None])
    assert not ((pts > lo) & (pts < hi)).all(dim=-1).any()


def _planes_field(k: int = 2, seed: int = 3) -> RadianceField:
    """A small tri-plane field with ``k`` residual plane sets over the box [-0.5, 0.5]^3 (random
    residuals, so that they act)."""
    torch.manual_seed(seed)
    cfg = FieldConfig(
        encoding="triplane", depth=2, width=16, skips=(), cond_dim=4, use_view_dirs=False, density_activation="softplus",
        grid_levels=2, grid_channels=3, grid_base_resolution=4, grid_max_resolution=8,
        cond_planes=k, cond_planes_min=(-0.5, -0.5, -0.5), cond_planes_max=(0.5, 0.5, 0.5), cond_planes_resolution=5,
    )  # fmt: skip
    field = RadianceField(cfg).double()
    assert field.cond_residual is not None
    with torch.no_grad():
        field.cond_residual.normal_()
    return field


def test_residual_planes_start_at_zero_and_add_their_blend_to_the_finest_features_inside_the_box() -> None:
    """A new field with residual planes is the field without them; a constant residual ``v_k``
    in set ``k`` adds exactly ``sum_k (W c)_k v_k`` to the finest level's features of a point
    inside the box (analytic, since bilinear interpolation of a constant is the constant), leaves
    the coarser levels alone, and adds nothing to points outside the box along one axis, whose
    other two coordinates some plane still covers. A swapped blend (sets mixed up), a residual
    on the wrong level, or no box weight breaks it."""
    field = _planes_field()
    cfg = field.config
    plain = RadianceField(FieldConfig.from_dict({**cfg.to_dict(), "cond_planes": 0})).double()
    plain.load_state_dict({k: v for k, v in field.state_dict().items() if k in plain.state_dict()})
    x = torch.rand(9, 3, dtype=torch.float64) * 2 - 1
    c = torch.randn(4, dtype=torch.float64)
    with torch.no_grad():
        field.cond_residual.zero_()
    torch.testing.assert_close(field(x, None, c).density, plain(x, None, c).density, rtol=0, atol=0)
    values = torch.tensor([0.7, -1.3], dtype=torch.float64)
    with torch.no_grad():
        field.cond_residual.copy_(values[:, None, None, None, None].expand_as(field.cond_residual))
    # Inside: more than a cell (0.25) from every face. Outside along one axis only: the other two
    # planes' coordinates lie inside, so without the box weight they would read the residual.
    inside = torch.tensor([[0.0, 0.1, -0.2], [0.2, -0.2, 0.24]], dtype=torch.float64)
    outside = torch.tensor([[0.9, 0.0, 0.0], [0.0, -0.8, 0.1], [0.1, 0.2, 0.6]], dtype=torch.float64)
    width = 3 * cfg.grid_channels
    assert field.plane_code is not None
    expected = float((field.plane_code(c) @ values).detach())
    with torch.no_grad():
        got = field._residual(inside, c)
        assert got is not None and field._residual(outside, c) is None
        idx, residual = got
        plain, added = field.position_encoding(inside), field.position_encoding(inside, finest=got)
    assert idx.tolist() == [0, 1]
    torch.testing.assert_close(residual, torch.full((width, 2), expected, dtype=torch.float64), rtol=0, atol=1e-12)
    assert float((added - plain)[:, :-width].abs().max()) == 0.0  # the coarser levels as they were
    torch.testing.assert_close((added - plain)[:, -width:], residual.t(), rtol=0, atol=1e-12)


def test_residual_planes_blend_alike_for_one_condition_each_rays_and_each_points() -> None:
    """The fast path (one condition: the planes blended once, then sampled) against the slow one
    (every set sampled, blended at each point), through per-ray rows and per-point conditions;
    and two rays under different codes differ only inside the box."""
    field = _planes_field()
    x = torch.rand(6, 5, 3, dtype=torch.float64) * 1.6 - 0.8
    c = torch.randn(4, dtype=torch.float64)
    with torch.no_grad():
        shared = field(x, None, c)
        per_point = field(x, None, c.expand(6, 5, 4))
        per_ray = field(x, None, SampleRows(c.expand(6, 4).clone(), torch.arange(6)[:, None].expand(6, 5)))
    for other in (per_point, per_ray):
        torch.testing.assert_close(other.rgb, shared.rgb, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(other.density, shared.density, rtol=1e-12, atol=1e-12)
    # Rays of two frames (each frame's planes blended once, sampled at its points) against the
    # same conditions given per point (every set sampled and blended at each point).
    codes = torch.randn(2, 4, dtype=torch.float64)
    of_ray = torch.tensor([1, 0, 0, 1, 1, 0])
    with torch.no_grad():
        by_frame = field(x, None, SampleRows(codes[of_ray], torch.arange(6)[:, None].expand(6, 5)))
        by_point = field(x, None, codes[of_ray][:, None, :].expand(6, 5, 4))
    torch.testing.assert_close(by_frame.density, by_point.density, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(by_frame.rgb, by_point.rgb, rtol=1e-12, atol=1e-12)
    # Two codes through the plain condition columns zeroed: the code acts through the planes alone.
    with torch.no_grad():
        field.trunk[0].weight[:, -4:] = 0.0
        pts = torch.tensor([[0.1, 0.0, 0.2], [0.9, 0.1, -0.1]], dtype=torch.float64)
        a, b = field(pts, None, torch.randn(4, dtype=torch.float64)), field(pts, None, torch.randn(4, dtype=torch.float64))
    assert float((a.density - b.density).abs()[0]) > 1e-6 and float((a.density - b.density).abs()[1]) == 0.0


def test_residual_planes_pass_gradcheck_and_round_trip() -> None:
    """Gradients through both ways of blending: two frames' codes copied to their rays (as
    FrameCondition.of_rays does; fewer conditions than sets, each blended once), and distinct
    rows per ray (every set sampled at every point), with respect to the points, the codes and
    the residual planes."""
    field = _planes_field(k=3, seed=4)
    x = (torch.rand(5, 3, dtype=torch.float64) * 0.8 - 0.4).requires_grad_()
    ray = torch.tensor([0, 1, 1, 2, 3])
    residual = field.cond_residual.detach().clone().requires_grad_()
    codes = torch.randn(2, 4, dtype=torch.float64, requires_grad=True)
    of_ray = torch.tensor([0, 1, 1, 0])  # four rays of two frames
    assert torch.autograd.gradcheck(lambda x, codes, r: _run_with_residual(field, x, codes[of_ray], ray, r), (x, codes, residual))
    rows = torch.randn(4, 4, dtype=torch.float64, requires_grad=True)  # four distinct conditions >= 3 sets
    assert torch.autograd.gradcheck(lambda x, rows, r: _run_with_residual(field, x, rows, ray, r), (x, rows, residual))
    cfg = field.config
    assert FieldConfig.from_dict(cfg.to_dict()) == cfg
    stored = cfg.to_dict()
    for key in ("cond_planes", "cond_planes_min", "cond_planes_max", "cond_planes_resolution"):
        del stored[key]  # a config stored before the keys: no residual planes
    assert RadianceField(FieldConfig.from_dict(stored)).cond_residual is None
    for bad in ({"cond_planes": -1}, {"cond_dim": 0}, {"encoding": "pe"}, {"cond_planes_max": (0.5, -0.5, 0.5)}, {"cond_planes_resolution": 1}):
        with pytest.raises(ValueError, match="residual plane"):
            RadianceField(FieldConfig.from_dict({**cfg.to_dict(), **bad}))


def _run_with_residual(field: RadianceField, x: torch.Tensor, rows: torch.Tensor, ray: torch.Tensor, residual: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The field's output with its residual planes replaced by ``residual`` (a differentiable input)."""
    saved = field.cond_residual
    del field.cond_residual
    field.cond_residual = residual  # type: ignore[assignment]
    try:
        out = field(x, None, SampleRows(rows, ray))
    finally:
        del field.cond_residual
        field.cond_residual = saved
    return out.rgb, out.density


def test_distinct_rows_group_equal_rows_and_never_two_different_ones() -> None:
    """Rows copied from two codes group into two; two different rows that share the grouping's
    projection (weights 1 and 2 here: [2, 0] and [0, 1] both project to 2) stay apart."""
    from adnerf.fields import _distinct_rows

    rows = torch.tensor([[1.0, 2.0], [3.0, 4.0], [1.0, 2.0]], dtype=torch.float64)
    distinct, of_row = _distinct_rows(rows)
    assert distinct.tolist() == [[1.0, 2.0], [3.0, 4.0]] and of_row.tolist() == [0, 1, 0]
    clash = torch.tensor([[2.0, 0.0], [0.0, 1.0], [2.0, 0.0]], dtype=torch.float64)
    distinct, of_row = _distinct_rows(clash)
    torch.testing.assert_close(distinct[of_row], clash, rtol=0, atol=0)
