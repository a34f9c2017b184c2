"""Bundle adjustment: analytic Jacobians, exact recovery, gauge, and the similarity alignment."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adnerf.pose import euler_rotation
from adnerf.preprocess.bundle import (
    bundle_adjust,
    ellipsoid_points,
    point_groups,
    reprojection_residuals,
    residual_jacobians,
    schur_blocks,
)
from adnerf.preprocess.check import align_poses
from adnerf.preprocess.headpose import (
    chain_segments,
    mean_rotation,
    triangulate_canonical,
)

K = (300.0, 310.0, 64.0, 60.0)


def _scene(n: int = 12, p: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(p, 3, generator=g, dtype=torch.float64) * torch.tensor([0.8, 1.0, 0.5], dtype=torch.float64)
    ang = torch.linspace(-1.0, 1.0, n, dtype=torch.float64)
    R = euler_rotation(0.3 * ang, 0.15 * torch.sin(3 * ang), 0.1 * ang**2, like=X)
    t = torch.stack([0.3 * ang, -0.2 * ang, 6.0 + 0.5 * ang], -1)
    return R, t, X


def _observe(R: torch.Tensor, t: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    cam = torch.einsum("nij,pj->npi", R, X) + t[:, None]
    return torch.stack([K[0] * cam[..., 0] / cam[..., 2] + K[2], K[1] * cam[..., 1] / cam[..., 2] + K[3]], -1)


def test_schur_blocks_by_point_groups_equal_the_dense_product() -> None:
    # The fast assembly of W Hpp^-1 W^T (groups of points seen in nearby frames) against the
    # dense frames-by-points product: tracks seen in runs of consecutive frames, a few points seen
    # in every frame (landmarks), and frames in any order of the observations.
    g = torch.Generator().manual_seed(3)
    nf, p = 40, 90
    spans = [(int(a), int(a) + int(k)) for a, k in zip(torch.randint(0, nf - 8, (p - 3,), generator=g), torch.randint(2, 8, (p - 3,), generator=g))]
    spans += [(0, nf)] * 3
    obs = [(f, q) for q, (a, b) in enumerate(spans) for f in range(a, min(b, nf))]
    obs = [obs[i] for i in torch.randperm(len(obs), generator=g)]
    col = torch.tensor([f for f, _ in obs])
    point = torch.tensor([q for _, q in obs])
    w = torch.randn(len(obs), 6, 3, generator=g, dtype=torch.float64)
    a = torch.randn(p, 3, 3, generator=g, dtype=torch.float64)
    inv = torch.linalg.inv(a @ a.transpose(1, 2) + torch.eye(3, dtype=torch.float64))
    wh = w @ inv[point]
    W = torch.zeros(nf, 6, p, 3, dtype=torch.float64)
    W[col, :, point] = w
    Wm = W.reshape(6 * nf, 3 * p)
    dense = torch.einsum("apk,pkl->apl", W.reshape(6 * nf, p, 3), inv).reshape(6 * nf, 3 * p) @ Wm.T
    groups = point_groups(col, point, p, max_group=16)
    assert sorted(torch.cat(groups).tolist()) == list(range(p))  # each point in one group
    assert any(len(gr) == 3 and set(gr.tolist()) == {p - 3, p - 2, p - 1} for gr in groups)  # the long ones apart
    torch.testing.assert_close(schur_blocks(wh, w, col, point, groups, nf), dense, rtol=1e-12, atol=1e-10)
    # One group of everything is the dense product too (the grouping changes the cost, not the sum).
    torch.testing.assert_close(schur_blocks(wh, w, col, point, [torch.arange(p)], nf), dense, rtol=1e-12, atol=1e-10)


def test_analytic_jacobians_match_autograd() -> None:
    R, t, X = _scene(3, 5)
    frame = torch.tensor([0, 1, 2, 2, 1])
    point = torch.tensor([0, 1, 2, 3, 4])
    uv = torch.zeros(5, 2, dtype=torch.float64)
    jp, jx = residual_jacobians(R, t, X, frame, point, K)
    for m in range(5):
        f, q = int(frame[m]), int(point[m])

        def res_pose(xi: torch.Tensor) -> torch.Tensor:
            from kornia.geometry.conversions import axis_angle_to_rotation_matrix

            E = axis_angle_to_rotation_matrix(xi[None, 3:])[0]
            Rn, tn = R.clone(), t.clone()
            Rn[f], tn[f] = E @ R[f], E @ t[f] + xi[:3]
            return reprojection_residuals(Rn, tn, X, frame[m : m + 1], point[m : m + 1], uv[m : m + 1], K)[0]

        def res_point(x: torch.Tensor) -> torch.Tensor:
            Xn = X.clone()
            Xn[q] = x
            return reprojection_residuals(R, t, Xn, frame[m : m + 1], point[m : m + 1], uv[m : m + 1], K)[0]

        auto_pose = torch.autograd.functional.jacobian(res_pose, torch.zeros(6, dtype=torch.float64))
        auto_point = torch.autograd.functional.jacobian(res_point, X[q].clone())
        torch.testing.assert_close(jp[m], auto_pose, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(jx[m], auto_point, rtol=1e-9, atol=1e-9)


def test_recovers_poses_from_exact_projections_with_partial_visibility() -> None:
    R, t, X = _scene()
    uv = _observe(R, t, X)
    g = torch.Generator().manual_seed(1)
    hidden = torch.rand(uv.shape[:2], generator=g) < 0.3
    hidden[0] = False
    uv[hidden] = float("nan")
    noise = lambda *s: 0.03 * torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    R0 = torch.stack([euler_rotation(*(0.05 * torch.randn(3, generator=g)).tolist(), like=X) for _ in R]) @ R
    R0[0] = R[0]
    t0 = t + noise(*t.shape)
    t0[0] = t[0]
    out = bundle_adjust(R0, t0, X + 3 * noise(*X.shape), uv, K, fixed_frame=0, iterations=50)
    assert out.rms_before > 1.0
    assert out.rms < 1e-6
    torch.testing.assert_close(out.R, R, atol=1e-7, rtol=0)
    # Exact up to the one gauge freedom left (the scene scaled about the camera): after the best
    # similarity the translations agree too.
    est, true = (torch.eye(4, dtype=torch.float64).repeat(len(R), 1, 1) for _ in range(2))
    est[:, :3, :3], est[:, :3, 3] = out.R, out.t
    true[:, :3, :3], true[:, :3, 3] = R, t
    rot, trans, _ = align_poses(est.numpy(), true.numpy())
    assert rot.max() < 1e-5 and trans.max() < 1e-6


def test_shape_prior_fixes_the_scale() -> None:
    R, t, _ = _scene()
    g = torch.Generator().manual_seed(2)
    radii = torch.tensor([0.8, 1.0, 0.9], dtype=torch.float64)
    d = torch.randn(40, 3, generator=g, dtype=torch.float64)
    X = radii * d / d.norm(dim=-1, keepdim=True)  # points on the prior's ellipsoid
    uv = _observe(R, t, X)
    t0 = t * 1.05
    t0[0] = t[0]
    out = bundle_adjust(R.clone(), t0, X * 1.1, uv, K, fixed_frame=0, shape_radii=radii, shape_sigma=0.05, iterations=50)
    torch.testing.assert_close(out.t, t, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.points, X, atol=1e-6, rtol=0)


def test_huber_loss_limits_gross_outliers() -> None:
    R, t, X = _scene()
    uv = _observe(R, t, X)
    uv[3, :4] += 25.0  # four wild observations in frame 3
    robust = bundle_adjust(R.clone(), t.clone(), X.clone(), uv, K, fixed_frame=0, huber=1.0, iterations=50)
    plain = bundle_adjust(R.clone(), t.clone(), X.clone(), uv, K, fixed_frame=0, huber=1e9, iterations=50)
    err = lambda out: float((out.R[3] - R[3]).abs().max())  # noqa: E731
    assert err(robust) < 0.2 * err(plain)
    assert robust.inlier_fraction == pytest.approx(1 - 4 / uv[..., 0].numel())


def test_point_weights_equal_repeated_observations_and_zero_leaves_a_point_out() -> None:
    """A point of weight 3 costs what three copies of its observations cost, so both adjustments
    reach the same poses; a point of weight 0 is as if it were not there."""
    R, t, X = _scene(8, 12)
    g = torch.Generator().manual_seed(4)
    uv = _observe(R, t, X) + 0.4 * torch.randn(8, 12, 2, generator=g, dtype=torch.float64)  # residuals stay: the weights matter
    uv[:, 0] += torch.tensor([1.5, -0.8], dtype=torch.float64)  # point 0 disagrees with the rest
    R0 = torch.stack([euler_rotation(*(0.03 * torch.randn(3, generator=g)).tolist(), like=X) for _ in R]) @ R
    R0[0] = R[0]
    kw = {"fixed_frame": 0, "huber": 1e9, "iterations": 60, "tolerance": 1e-14}
    w = torch.ones(12, dtype=torch.float64)
    w[0] = 3.0
    weighted = bundle_adjust(R0.clone(), t.clone(), X.clone(), uv, K, point_weights=w, **kw)
    copies = bundle_adjust(R0.clone(), t.clone(), torch.cat([X[:1], X[:1], X]), torch.cat([uv[:, :1], uv[:, :1], uv], 1), K, **kw)
    torch.testing.assert_close(weighted.R, copies.R, atol=1e-8, rtol=0)
    torch.testing.assert_close(weighted.t, copies.t, atol=1e-8, rtol=0)
    plain = bundle_adjust(R0.clone(), t.clone(), X.clone(), uv, K, **kw)
    assert float((weighted.R - plain.R).abs().max()) > 1e-4  # the weight moved the poses
    w[0] = 0.0
    zero = bundle_adjust(R0.clone(), t.clone(), X.clone(), uv, K, point_weights=w, **kw)
    without = bundle_adjust(R0.clone(), t.clone(), X[1:].clone(), uv[:, 1:], K, **kw)
    torch.testing.assert_close(zero.R, without.R, atol=1e-8, rtol=0)
    assert zero.rms == pytest.approx(without.rms, rel=1e-6)  # the reported error leaves it out too
    with pytest.raises(ValueError, match="non-negative"):
        bundle_adjust(R0, t, X, uv, K, point_weights=-w)


def test_unconstrained_frames_and_bad_shapes_are_refused() -> None:
    R, t, X = _scene(4, 6)
    uv = _observe(R, t, X)
    uv[2] = float("nan")
    with pytest.raises(ValueError, match="fewer than 3"):
        bundle_adjust(R, t, X, uv, K)
    with pytest.raises(ValueError, match="shapes disagree"):
        bundle_adjust(R[:3], t, X, _observe(R, t, X), K)


def test_ellipsoid_points_lie_on_the_ellipsoid_and_reproject() -> None:
    R, t, _ = _scene(1, 1)
    radii = torch.tensor([0.8, 1.0, 0.9], dtype=torch.float64)
    uv = torch.tensor([[64.0, 60.0], [80.0, 50.0], [500.0, 60.0]], dtype=torch.float64)
    # The first two rays hit the head (it sits in front of the camera at depth ~5.5); the last misses.
    X = ellipsoid_points(uv, R.expand(3, 3, 3), t.expand(3, 3), radii, K)
    on = ((X / radii) ** 2).sum(-1)
    torch.testing.assert_close(on[:2], torch.ones(2, dtype=torch.float64))
    back = reprojection_residuals(R.expand(3, 3, 3), t.expand(3, 3), X, torch.zeros(3, dtype=torch.long), torch.arange(3), uv, K)
    torch.testing.assert_close(back, torch.zeros_like(back), atol=1e-9, rtol=0)
    assert torch.isfinite(X).all()


def test_align_poses_undoes_a_similarity() -> None:
    R, t, _ = _scene(20)
    true = np.tile(np.eye(4), (20, 1, 1))
    true[:, :3, :3], true[:, :3, 3] = R.numpy(), t.numpy()
    G = euler_rotation(0.4, -0.2, 0.7, like=R).numpy()
    g, s = np.array([0.1, -0.3, 0.2]), 2.5
    est = true.copy()
    # R_true = R_est G and s t_true = R_est g + t_est.
    est[:, :3, :3] = true[:, :3, :3] @ G.T
    est[:, :3, 3] = s * true[:, :3, 3] - np.einsum("nij,j->ni", est[:, :3, :3], g)
    rot, trans, sim = align_poses(est, true)
    assert rot.max() < 1e-5 and trans.max() < 1e-9
    assert sim["scale"] == pytest.approx(s)
    est[5, :3, :3] = euler_rotation(0.0, 0.0, np.radians(2.0), like=R).numpy() @ est[5, :3, :3]
    rot, _, _ = align_poses(est, true)
    assert rot[5] == pytest.approx(2.0, abs=0.1)


def _poses(R: torch.Tensor, t: torch.Tensor) -> np.ndarray:
    out = np.tile(np.eye(4), (len(R), 1, 1))
    out[:, :3, :3], out[:, :3, 3] = R.numpy(), t.numpy()
    return out


def test_triangulate_canonical_recovers_a_point_seen_from_turning_poses() -> None:
    R, t, _ = _scene(n=20)
    p = torch.tensor([[0.1, 0.45, -0.8]], dtype=torch.float64)
    uv = _observe(R, t, p)[:, 0].numpy()
    uv[3] = np.nan  # a frame without a landmark is skipped
    est = triangulate_canonical(uv, _poses(R, t), K, prior=np.array([0.0, 0.0, 0.0]), prior_weight=1e-12)
    np.testing.assert_allclose(est, p[0].numpy(), atol=1e-8)


def test_triangulate_canonical_takes_depth_from_the_prior_when_the_head_does_not_turn() -> None:
    """With one pose for every frame, the rays coincide: the answer is the point of that ray
    nearest the prior (a weak prior moves nothing the rays decide)."""
    R, t, _ = _scene(n=1)
    poses = np.repeat(_poses(R, t), 10, axis=0)
    uv = np.repeat(np.array([[70.0, 80.0]]), 10, axis=0)
    prior = np.array([0.2, -0.1, 0.3])
    est = triangulate_canonical(uv, poses, K, prior, prior_weight=1e-9)
    # The ray in canonical space: origin -R^T t, direction R^T d.
    Rm, tm = poses[0, :3, :3], poses[0, :3, 3]
    d = np.array([(70.0 - K[2]) / K[0], (80.0 - K[3]) / K[1], 1.0])
    d = Rm.T @ d / np.linalg.norm(d)
    o = -Rm.T @ tm
    nearest = o + d * ((prior - o) @ d)
    np.testing.assert_allclose(est, nearest, atol=1e-6)
    assert np.all(np.isfinite(est))
    np.testing.assert_array_equal(triangulate_canonical(np.full((4, 2), np.nan), poses[:4], K, prior), prior)
    with pytest.raises(ValueError, match="prior_weight"):
        triangulate_canonical(uv, poses, K, prior, prior_weight=0.0)


def _similarity_gauge(poses: np.ndarray, G: np.ndarray, g: np.ndarray, s: float) -> np.ndarray:
    """The same camera motion described in another canonical frame and scale (inverse of the
    re-expression chain_segments applies)."""
    out = poses.copy()
    out[:, :3, :3] = poses[:, :3, :3] @ G.T
    out[:, :3, 3] = s * poses[:, :3, 3] - np.einsum("nij,j->ni", out[:, :3, :3], g)
    return out


def test_chain_segments_joins_segments_solved_in_different_gauges() -> None:
    R, t, _ = _scene(n=50)
    true = _poses(R, t)
    rng = np.random.default_rng(4)
    spans = [(0, 20), (15, 35), (30, 50)]
    segments = []
    for k, (a, b) in enumerate(spans):
        G = euler_rotation(*torch.tensor(rng.normal(scale=0.3, size=3)), like=R).numpy() if k else np.eye(3)
        g = rng.normal(scale=0.2, size=3) if k else np.zeros(3)
        segments.append((a, _similarity_gauge(true[a:b], G, g, float(rng.uniform(0.7, 1.4)) if k else 1.0)))
    out, joints = chain_segments(segments, 50)
    # The same motion in the first segment's frame, up to the final mean-rotation gauge: compare
    # with the truth after the best similarity, which must be exact.
    rot, trans, sim = align_poses(out, true)
    assert rot.max() < 1e-5 and trans.max() < 1e-9 and abs(sim["scale"] - 1.0) < 1e-9  # degrees: arccos resolves ~1e-6 near 0
    np.testing.assert_allclose(joints, 0.0, atol=1e-6)
    np.testing.assert_allclose(mean_rotation(out[:, :3, :3]), np.eye(3), atol=1e-12)
    alone, none = chain_segments([(0, true)], 50)
    np.testing.assert_array_equal(alone, true)
    assert none == []
    with pytest.raises(ValueError, match="does not overlap"):
        chain_segments([(0, true[:20]), (20, true[20:])], 50)
    with pytest.raises(ValueError, match="cover frames"):
        chain_segments([(0, true[:20]), (10, true[10:30])], 50)
