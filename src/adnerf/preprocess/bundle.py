"""Rigid head pose per frame by bundle adjustment of point tracks, in PyTorch.

Unknowns: a pose ``(R_i, t_i)`` per frame (head-canonical -> camera, the project convention
``x_cam = R x_can + t``) and a canonical 3D point ``X_j`` per track. The residual of an
observation is the reprojection error in pixels,

    r_ij = project(K, R_i X_j + t_i) - uv_ij       (kornia ``project_points``),

minimised with a Huber loss by Levenberg-Marquardt: iteratively reweighted Gauss-Newton steps on
the se(3) increments of the poses and the point increments, with analytic Jacobians and the
points eliminated by the Schur complement, so the linear system has only ``6 (N - 1)`` unknowns.
The complement is assembled group by group of points seen in nearby frames (a chained flow
track is seen in a few dozen consecutive frames of a segment), each group's product formed only
over its frames: its cost grows with the tracks' lengths, not with frames times points.

Gauge: the reference frame's pose is held fixed, which fixes the canonical frame (6 degrees of
freedom). One more freedom remains: the whole scene scaled about the camera centre (points
``s X + (s - 1) R_ref^T t_ref``, translations ``s t_i - (s - 1) R_i R_ref^T t_ref`` reproject
identically). The shape prior fixes it; without the prior the damping keeps the scale near its
initial value. Callers choose the reference pose (its depth sets the scene units).

Pose update (a retraction of SE(3), exact to first order): ``R <- Exp(w) R``, ``t <- Exp(w) t + v``
for the increment ``(v, w)``; the derivative of ``p = R X + t`` is ``[I, -[p]x]`` for ``(v, w)``
and ``R`` for ``X``.

Initialisation (:func:`initial_poses`): perspective-n-point (OpenCV ``solvePnP``) frame by frame
against points seeded on an ellipsoid fitted to the head.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Callable

import torch
from kornia.geometry.camera.perspective import project_points
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

__all__ = ["BundleResult", "bundle_adjust", "reprojection_residuals", "residual_jacobians", "ellipsoid_points", "point_groups", "schur_blocks"]


@dataclass
class BundleResult:
    """Output of :func:`bundle_adjust`.

    Attributes:
        R: ``(N, 3, 3)`` rotations.
        t: ``(N, 3)`` translations.
        points: ``(P, 3)`` canonical points.
        rms_before: Root-mean-square reprojection error (pixels) of the initial guess.
        rms: RMS reprojection error after the adjustment, over all observations.
        median: Median reprojection error (pixels) after the adjustment.
        iterations: LM iterations run.
        inlier_fraction: Observations within the Huber threshold.
    """

    R: torch.Tensor
    t: torch.Tensor
    points: torch.Tensor
    rms_before: float
    rms: float
    median: float
    iterations: int
    inlier_fraction: float


def _K(intrinsics: tuple[float, float, float, float], like: torch.Tensor) -> torch.Tensor:
    fx, fy, cx, cy = intrinsics
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=like.dtype, device=like.device)


def reprojection_residuals(R: torch.Tensor, t: torch.Tensor, points: torch.Tensor, frame: torch.Tensor, point: torch.Tensor, uv: torch.Tensor, intrinsics: tuple[float, float, float, float]) -> torch.Tensor:
    """Reprojection residuals ``(M, 2)`` in pixels of ``M`` observations.

    Args:
        R: ``(N, 3, 3)``; t: ``(N, 3)``; points: ``(P, 3)`` canonical.
        frame, point: ``(M,)`` long indices of each observation's frame and point.
        uv: ``(M, 2)`` observed pixel positions (centre convention: ``K`` maps to continuous
            coordinates whose pixel centres are at ``+0.5``).
        intrinsics: ``(fx, fy, cx, cy)``.
    """
    cam = torch.einsum("mij,mj->mi", R[frame], points[point]) + t[frame]
    return project_points(cam, _K(intrinsics, cam)) - uv


def residual_jacobians(R: torch.Tensor, t: torch.Tensor, points: torch.Tensor, frame: torch.Tensor, point: torch.Tensor, intrinsics: tuple[float, float, float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Analytic Jacobians of the residuals: ``(M, 2, 6)`` w.r.t. ``(v, w)`` and ``(M, 2, 3)`` w.r.t. ``X``."""
    fx, fy, _, _ = intrinsics
    Rm = R[frame]
    p = torch.einsum("mij,mj->mi", Rm, points[point]) + t[frame]
    x, y, z = p.unbind(-1)
    zero = torch.zeros_like(z)
    dproj = torch.stack([torch.stack([fx / z, zero, -fx * x / z**2], -1), torch.stack([zero, fy / z, -fy * y / z**2], -1)], -2)
    skew = torch.stack([torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2)
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand_as(skew)
    j_pose = dproj @ torch.cat([eye, -skew], -1)
    j_point = dproj @ Rm
    return j_pose, j_point


def point_groups(col: torch.Tensor, point: torch.Tensor, n_points: int, max_group: int = 256) -> list[torch.Tensor]:
    """Points grouped for :func:`schur_blocks`: each group's observations span few frames.

    Points are taken in the order of their first frame and added to a group while the group's
    frames (first to last) stay within twice the median span of a point (a chained flow track is
    seen in consecutive frames); points seen over more than that (landmarks, seen in every frame)
    form groups of their own.

    Args:
        col: ``(M,)`` each observation's frame (among the free frames).
        point: ``(M,)`` each observation's point.
        n_points: Number of points.
        max_group: Most points in a group.

    Returns:
        Groups of point indices; every point with an observation is in exactly one.
    """
    big = torch.iinfo(torch.long).max
    first = torch.full((n_points,), big, dtype=torch.long, device=col.device).scatter_reduce(0, point, col, "amin")
    last = torch.full((n_points,), -1, dtype=torch.long, device=col.device).scatter_reduce(0, point, col, "amax")
    seen = last >= 0
    span = last - first + 1
    limit = 2 * int(span[seen].median()) if bool(seen.any()) else 0
    long = torch.nonzero(seen & (span > limit))[:, 0].tolist()
    short = torch.nonzero(seen & (span <= limit))[:, 0]
    groups: list[list[int]] = []
    lo = -1
    for q in short[torch.argsort(first[short], stable=True)].tolist():
        if not groups or len(groups[-1]) >= max_group or int(last[q]) - lo + 1 > limit:
            groups.append([])
            lo = int(first[q])
        groups[-1].append(q)
    groups += [long[i : i + max_group] for i in range(0, len(long), max_group)]
    return [torch.tensor(g, dtype=torch.long, device=col.device) for g in groups if g]


def schur_blocks(wh: torch.Tensor, w: torch.Tensor, col: torch.Tensor, point: torch.Tensor, groups: list[torch.Tensor], nf: int) -> torch.Tensor:
    """``W Hpp^-1 W^T`` of the Schur complement as a dense ``(6 nf, 6 nf)`` matrix.

    ``W`` (``6 nf x 3 P``) has a ``6 x 3`` block per observation; for each group of points
    (:func:`point_groups`) only the rows of the frames the group is seen in are formed, and their
    product is added to that square of the result: dense matrix products, at a cost that grows
    with the points' spans rather than with frames times points.

    Args:
        wh: ``(M, 6, 3)`` each observation's ``W_o Hpp^-1`` (its block times the inverse of its
            point's block).
        w: ``(M, 6, 3)`` each observation's block ``W_o``.
        col: ``(M,)`` each observation's frame among the free frames.
        point: ``(M,)`` each observation's point.
        groups: :func:`point_groups` of the observations.
        nf: Free frames.
    """
    out = torch.zeros(6 * nf, 6 * nf, dtype=w.dtype, device=w.device)
    slot = torch.full((int(point.max()) + 1 if len(point) else 0,), -1, dtype=torch.long, device=w.device)
    for g in groups:
        slot[g] = torch.arange(len(g), device=w.device)
        rows = torch.nonzero(slot[point] >= 0)[:, 0]  # the group's observations
        c, q = col[rows], slot[point[rows]]
        lo, hi = int(c.min()), int(c.max()) + 1
        dense_w = torch.zeros(hi - lo, 6, len(g), 3, dtype=w.dtype, device=w.device)
        dense_wh = torch.zeros_like(dense_w)
        dense_w[c - lo, :, q] = w[rows]
        dense_wh[c - lo, :, q] = wh[rows]
        k = 6 * (hi - lo)
        out[6 * lo : 6 * hi, 6 * lo : 6 * hi] += dense_wh.reshape(k, -1) @ dense_w.reshape(k, -1).T
        slot[g] = -1
    return out


def _retract(R: torch.Tensor, t: torch.Tensor, delta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply pose increments ``(N, 6) = (v, w)``: ``R <- Exp(w) R``, ``t <- Exp(w) t + v``."""
    E = axis_angle_to_rotation_matrix(delta[:, 3:])
    return E @ R, torch.einsum("nij,nj->ni", E, t) + delta[:, :3]


def _checked_observations(R: torch.Tensor, t: torch.Tensor, points: torch.Tensor, uv: torch.Tensor, fixed_frame: int, point_weights: torch.Tensor | None) -> torch.Tensor:
    """``(N, P)`` bool: which point each frame observes, once the inputs are checked (see
    :func:`bundle_adjust`'s Raises)."""
    n, p = uv.shape[:2]
    if R.shape != (n, 3, 3) or t.shape != (n, 3) or points.shape != (p, 3):
        raise ValueError(f"shapes disagree: R {tuple(R.shape)}, t {tuple(t.shape)}, points {tuple(points.shape)}, uv {tuple(uv.shape)}")
    seen = torch.isfinite(uv[..., 0])
    if not seen.any(0).all():
        raise ValueError("every point needs at least one observation")
    lonely = [i for i in range(n) if i != fixed_frame and int(seen[i].sum()) < 3]
    if lonely:
        raise ValueError(f"frames {lonely[:10]} have fewer than 3 observed points; their pose is not constrained")
    if point_weights is not None and (point_weights.shape != (p,) or not bool((point_weights >= 0).all())):
        raise ValueError(f"point_weights must be ({p},) and non-negative; got shape {tuple(point_weights.shape)}")
    return seen


def _shape_prior(X: torch.Tensor, radii: torch.Tensor | None, sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ellipsoid shape prior's residuals ``(P,)`` and their Jacobians ``(P, 3)`` (zeros
    without ``radii``)."""
    p = X.shape[0]
    if radii is None:
        return torch.zeros(p, dtype=X.dtype, device=X.device), torch.zeros(p, 3, dtype=X.dtype, device=X.device)
    q = X / radii
    norm = q.norm(dim=-1)
    jac = (q / radii) / norm.clamp_min(1e-12)[:, None] / sigma
    return (norm - 1.0) / sigma, jac


def _normal_equations(
    R: torch.Tensor, t: torch.Tensor, points: torch.Tensor, r: torch.Tensor, w: torch.Tensor, frame: torch.Tensor, point: torch.Tensor,
    keep: torch.Tensor, n: int, p: int, intrinsics: tuple[float, float, float, float], prior: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
) -> tuple[torch.Tensor, ...]:  # fmt: skip
    """The weighted normal equations block by block: ``Hcc (N, 6, 6)``, ``Hpp (P, 3, 3)`` (with
    the shape prior), gradients ``gc (N, 6)``, ``gp (P, 3)``, and ``W = Hcp`` as a 6 x 3 block per
    observation of a free frame (``keep``)."""
    jc, jp = residual_jacobians(R, t, points, frame, point, intrinsics)
    wjc, wjp = w[:, None, None] * jc, w[:, None, None] * jp
    Hcc = torch.zeros(n, 6, 6, dtype=R.dtype, device=R.device).index_add_(0, frame, wjc.transpose(1, 2) @ jc)
    Hpp = torch.zeros(p, 3, 3, dtype=R.dtype, device=R.device).index_add_(0, point, wjp.transpose(1, 2) @ jp)
    gc = torch.zeros(n, 6, dtype=R.dtype, device=R.device).index_add_(0, frame, torch.einsum("mki,mk->mi", wjc, r))
    gp = torch.zeros(p, 3, dtype=R.dtype, device=R.device).index_add_(0, point, torch.einsum("mki,mk->mi", wjp, r))
    pr, pj = prior(points)
    Hpp = Hpp + pj[:, :, None] * pj[:, None, :]
    gp = gp + pj * pr[:, None]
    return Hcc, Hpp, gc, gp, (wjc.transpose(1, 2) @ jp)[keep]


def _damped_step(
    Hcc_f: torch.Tensor, Hpp: torch.Tensor, gc_f: torch.Tensor, gp: torch.Tensor, w_obs: torch.Tensor, lam: float,
    kept_col: torch.Tensor, kept_point: torch.Tensor, groups: list,
) -> tuple[torch.Tensor, torch.Tensor] | None:  # fmt: skip
    """The Levenberg-Marquardt step ``(dc (6 nf,), dp (P, 3))`` at damping ``lam`` by the Schur
    complement ``S = Hcc - W Hpp^-1 W^T`` (its ``(i, j)`` block sums ``W_o Hpp^-1 W_o'^T`` over
    the pairs of observations of one point in frames ``i`` and ``j``); ``None`` when ``S`` is
    not positive definite in floating point. ``S`` is symmetric positive definite in exact
    arithmetic, so it is solved by Cholesky, at half the cost of LU."""
    nf = Hcc_f.shape[0]
    Hpp_d = Hpp + lam * torch.diag_embed(torch.diagonal(Hpp, dim1=-2, dim2=-1).clamp_min(1e-9))
    Hpp_inv = torch.linalg.inv(Hpp_d)
    wh = w_obs @ Hpp_inv[kept_point]
    Hcc_d = Hcc_f + lam * torch.diag_embed(torch.diagonal(Hcc_f, dim1=-2, dim2=-1).clamp_min(1e-9))
    S = torch.block_diag(*Hcc_d) - schur_blocks(wh, w_obs, kept_col, kept_point, groups, nf)
    whg = torch.zeros(nf, 6, dtype=Hpp.dtype, device=Hpp.device).index_add_(0, kept_col, torch.einsum("okl,ol->ok", wh, gp[kept_point]))
    rhs = -gc_f.reshape(-1) + whg.reshape(-1)
    L, info = torch.linalg.cholesky_ex(S)
    if int(info) != 0:
        return None
    dc = torch.cholesky_solve(rhs[:, None], L)[:, 0]
    wdc = torch.zeros(Hpp.shape[0], 3, dtype=Hpp.dtype, device=Hpp.device).index_add_(0, kept_point, torch.einsum("okl,ok->ol", w_obs, dc.reshape(nf, 6)[kept_col]))
    return dc, torch.einsum("pkl,pl->pk", Hpp_inv, -gp - wdc)


def _free_layout(frame: torch.Tensor, point: torch.Tensor, n: int, p: int, fixed_frame: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, list]:
    """Where the free frames' observations go in the Schur complement: ``free (N,)`` bool,
    ``keep (M,)`` (the observations of free frames: the rows of ``W``), their block columns and
    points, and the points grouped by the frames they are seen in (:func:`point_groups`)."""
    free = torch.ones(n, dtype=torch.bool, device=frame.device)
    free[fixed_frame] = False
    col = torch.cumsum(free.long(), 0) - 1  # frame -> block column among free frames
    keep = free[frame]
    kept_col, kept_point = col[frame[keep]], point[keep]
    return free, keep, kept_col, kept_point, point_groups(kept_col, kept_point, p)


def _moved(R: torch.Tensor, t: torch.Tensor, points: torch.Tensor, step: tuple[torch.Tensor, torch.Tensor], free: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Poses and points moved by a step ``(dc, dp)`` (:func:`_damped_step`; the fixed frame stays)."""
    dc, dp = step
    delta = torch.zeros(R.shape[0], 6, dtype=R.dtype, device=R.device)
    delta[free] = dc.reshape(-1, 6)
    R_new, t_new = _retract(R, t, delta)
    return R_new, t_new, points + dp


def bundle_adjust(
    R: torch.Tensor,
    t: torch.Tensor,
    points: torch.Tensor,
    uv: torch.Tensor,
    intrinsics: tuple[float, float, float, float],
    *,
    fixed_frame: int = 0,
    huber: float = 1.0,
    shape_radii: torch.Tensor | None = None,
    shape_sigma: float = 0.05,
    point_weights: torch.Tensor | None = None,
    iterations: int = 30,
    tolerance: float = 1e-7,
    progress: Callable[[int, float], None] | None = None,
) -> BundleResult:
    """Levenberg-Marquardt bundle adjustment of poses and points with a Huber loss.

    Args:
        R: ``(N, 3, 3)`` initial rotations (float64 recommended).
        t: ``(N, 3)`` initial translations.
        points: ``(P, 3)`` initial canonical points.
        uv: ``(N, P, 2)`` observations, NaN where a point is not seen in a frame.
        intrinsics: ``(fx, fy, cx, cy)`` in pixels.
        fixed_frame: The frame whose pose is held (the gauge).
        huber: Huber threshold in pixels.
        shape_radii: ``(3,)`` semi-axes of a canonical ellipsoid centred at the origin that the
            points are drawn towards: a prior residual ``(|X / radii| - 1) / shape_sigma`` per
            point (it resolves the depth-relief / rotation ambiguity of a head seen from the
            front). ``None``: no prior.
        shape_sigma: Radial deviation (a fraction of the radius) that costs as much as one pixel.
        point_weights: ``(P,)`` non-negative weight of each point's observations in the cost
            (their Huber losses are multiplied by it); ``None``: all 1. The reported RMS, median
            and inlier fraction count the observations of points of positive weight, unweighted.
        iterations: Maximum LM iterations.
        tolerance: Stop when the relative decrease of the cost is below this.
        progress: Called as ``progress(iteration, rms)``.

    Returns:
        A :class:`BundleResult`.

    Raises:
        ValueError: Shapes disagree, or a frame other than the fixed one or a point has no
            observation (nothing would constrain it).
    """
    n, p = uv.shape[:2]
    seen = _checked_observations(R, t, points, uv, fixed_frame, point_weights)
    frame, point = seen.nonzero(as_tuple=True)
    obs = uv[frame, point]
    ow = torch.ones(len(frame), dtype=uv.dtype, device=uv.device) if point_weights is None else point_weights.to(uv)[point]  # (M,) observation weights
    free, keep, kept_col, kept_point, groups = _free_layout(frame, point, n, p, fixed_frame)

    prior = partial(_shape_prior, radii=shape_radii, sigma=shape_sigma)

    def cost_of(R_: torch.Tensor, t_: torch.Tensor, X_: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r = reprojection_residuals(R_, t_, X_, frame, point, obs, intrinsics)
        e = r.norm(dim=-1)
        rho = torch.where(e <= huber, 0.5 * e**2, huber * (e - 0.5 * huber))
        return (ow * rho).sum() + 0.5 * prior(X_)[0].pow(2).sum(), r

    counted = ow > 0  # observations the reported errors describe

    def rms_of(r_: torch.Tensor) -> float:
        return float(r_[counted].pow(2).sum(-1).mean().sqrt())

    cost, r = cost_of(R, t, points)
    rms_before = rms_of(r)
    lam, it, rel = 1e-3, 0, 0.0
    for it in range(1, iterations + 1):
        e = r.norm(dim=-1)
        w = ow * torch.where(e <= huber, torch.ones_like(e), huber / e.clamp_min(huber))  # IRLS weights of the Huber loss
        Hcc, Hpp, gc, gp, w_obs = _normal_equations(R, t, points, r, w, frame, point, keep, n, p, intrinsics, prior)
        improved = False
        while lam < 1e10:
            step = _damped_step(Hcc[free], Hpp, gc[free], gp, w_obs, lam, kept_col, kept_point, groups)
            if step is None:  # rounding made the damped complement indefinite: damp more
                lam *= 10.0
                continue
            R_new, t_new, X_new = _moved(R, t, points, step, free)
            depth = torch.einsum("mij,mj->mi", R_new[frame], X_new[point])[:, 2] + t_new[frame, 2]
            if bool((depth > 0).all()):
                new_cost, new_r = cost_of(R_new, t_new, X_new)
                if new_cost < cost:
                    rel = float((cost - new_cost) / cost.clamp_min(1e-300))
                    R, t, points, cost, r = R_new, t_new, X_new, new_cost, new_r
                    lam = max(lam / 10.0, 1e-9)
                    improved = True
                    break
            lam *= 10.0
        if progress is not None:
            progress(it, rms_of(r))
        if not improved or rel < tolerance:
            break
    e = r.norm(dim=-1)[counted]
    return BundleResult(
        R=R,
        t=t,
        points=points,
        rms_before=rms_before,
        rms=rms_of(r),
        median=float(e.median()),
        iterations=it,
        inlier_fraction=float((e <= huber).double().mean()),
    )


def ellipsoid_points(uv: torch.Tensor, R: torch.Tensor, t: torch.Tensor, radii: torch.Tensor, intrinsics: tuple[float, float, float, float]) -> torch.Tensor:
    """Canonical points where pixel rays first meet the ellipsoid ``sum((x / radii)^2) = 1``.

    Rays that miss it take the point of the ray closest (in the ellipsoid's metric) to its centre,
    i.e. the silhouette, so every pixel gets a finite point.

    Args:
        uv: ``(M, 2)`` pixels (centre convention).
        R: ``(M, 3, 3)``, t: ``(M, 3)`` the pose of each pixel's frame.
        radii: ``(3,)`` semi-axes in canonical units.
        intrinsics: ``(fx, fy, cx, cy)``.

    Returns:
        ``(M, 3)`` canonical points.
    """
    fx, fy, cx, cy = intrinsics
    d = torch.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, torch.ones_like(uv[:, 0])], -1)
    o_c = -torch.einsum("mji,mj->mi", R, t) / radii  # camera centre in canonical, ellipsoid scaled to a sphere
    d_c = torch.einsum("mji,mj->mi", R, d) / radii
    a = (d_c * d_c).sum(-1)
    b = 2 * (o_c * d_c).sum(-1)
    c = (o_c * o_c).sum(-1) - 1.0
    disc = b * b - 4 * a * c
    s_hit = (-b - disc.clamp_min(0).sqrt()) / (2 * a)
    s_close = -b / (2 * a)
    s = torch.where(disc >= 0, s_hit, s_close)
    return (o_c + s[:, None] * d_c) * radii
