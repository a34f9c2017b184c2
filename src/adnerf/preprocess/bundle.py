"""Rigid head pose per frame by bundle adjustment of point tracks, in PyTorch.

Unknowns: a pose ``(R_i, t_i)`` per frame (head-canonical -> camera, the project convention
``x_cam = R x_can + t``) and a canonical 3D point ``X_j`` per track. The residual of an
observation is the reprojection error in pixels,

    r_ij = project(K, R_i X_j + t_i) - uv_ij       (kornia ``project_points``),

minimised with a Huber loss by Levenberg-Marquardt: iteratively reweighted Gauss-Newton steps on
the se(3) increments of the poses and the point increments, with analytic Jacobians and the
points eliminated by the Schur complement, so the linear system has only ``6 (N - 1)`` unknowns.

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
from typing import Callable

import torch
from kornia.geometry.camera.perspective import project_points
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

__all__ = ["BundleResult", "bundle_adjust", "reprojection_residuals", "residual_jacobians", "ellipsoid_points"]


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


def _retract(R: torch.Tensor, t: torch.Tensor, delta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply pose increments ``(N, 6) = (v, w)``: ``R <- Exp(w) R``, ``t <- Exp(w) t + v``."""
    E = axis_angle_to_rotation_matrix(delta[:, 3:])
    return E @ R, torch.einsum("nij,nj->ni", E, t) + delta[:, :3]


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
    frame, point = seen.nonzero(as_tuple=True)
    obs = uv[frame, point]
    ow = torch.ones(len(frame), dtype=uv.dtype, device=uv.device) if point_weights is None else point_weights.to(uv)[point]  # (M,) observation weights
    free = torch.ones(n, dtype=torch.bool, device=uv.device)
    free[fixed_frame] = False
    col = torch.cumsum(free.long(), 0) - 1  # frame -> block column among free frames
    nf = int(free.sum())

    def prior(X_: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape prior residuals ``(P,)`` and their Jacobians ``(P, 3)``."""
        if shape_radii is None:
            return torch.zeros(p, dtype=X_.dtype, device=X_.device), torch.zeros(p, 3, dtype=X_.dtype, device=X_.device)
        q = X_ / shape_radii
        norm = q.norm(dim=-1)
        jac = (q / shape_radii) / norm.clamp_min(1e-12)[:, None] / shape_sigma
        return (norm - 1.0) / shape_sigma, jac

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
    lam = 1e-3
    it = 0
    rel = 0.0
    for it in range(1, iterations + 1):
        e = r.norm(dim=-1)
        w = ow * torch.where(e <= huber, torch.ones_like(e), huber / e.clamp_min(huber))  # IRLS weights of the Huber loss
        jc, jp = residual_jacobians(R, t, points, frame, point, intrinsics)
        wjc, wjp = w[:, None, None] * jc, w[:, None, None] * jp
        # Normal equations, block by block.
        Hcc = torch.zeros(n, 6, 6, dtype=R.dtype, device=R.device).index_add_(0, frame, wjc.transpose(1, 2) @ jc)
        Hpp = torch.zeros(p, 3, 3, dtype=R.dtype, device=R.device).index_add_(0, point, wjp.transpose(1, 2) @ jp)
        gc = torch.zeros(n, 6, dtype=R.dtype, device=R.device).index_add_(0, frame, torch.einsum("mki,mk->mi", wjc, r))
        gp = torch.zeros(p, 3, dtype=R.dtype, device=R.device).index_add_(0, point, torch.einsum("mki,mk->mi", wjp, r))
        pr, pj = prior(points)
        Hpp = Hpp + pj[:, :, None] * pj[:, None, :]
        gp = gp + pj * pr[:, None]
        # W = Hcp (6F x 3P, dense over the free frames); the Schur complement is S = Hcc - W Hpp^-1 W^T.
        W = torch.zeros(nf, 6, p, 3, dtype=R.dtype, device=R.device)
        keep = free[frame]
        W[col[frame[keep]], :, point[keep]] = (wjc.transpose(1, 2) @ jp)[keep]
        Wm = W.reshape(6 * nf, 3 * p)
        Hcc_f = Hcc[free]
        improved = False
        while lam < 1e10:
            Hpp_d = Hpp + lam * torch.diag_embed(torch.diagonal(Hpp, dim1=-2, dim2=-1).clamp_min(1e-9))
            Hpp_inv = torch.linalg.inv(Hpp_d)
            WH = torch.einsum("apk,pkl->apl", W.reshape(6 * nf, p, 3), Hpp_inv).reshape(6 * nf, 3 * p)
            Hcc_d = Hcc_f + lam * torch.diag_embed(torch.diagonal(Hcc_f, dim1=-2, dim2=-1).clamp_min(1e-9))
            S = torch.block_diag(*Hcc_d) - WH @ Wm.T
            rhs = -gc[free].reshape(-1) + WH @ gp.reshape(-1)
            try:
                dc = torch.linalg.solve(S, rhs)
            except RuntimeError:
                lam *= 10.0
                continue
            dp = torch.einsum("pkl,pl->pk", Hpp_inv, -gp - (Wm.T @ dc).reshape(p, 3))
            delta = torch.zeros(n, 6, dtype=R.dtype, device=R.device)
            delta[free] = dc.reshape(nf, 6)
            R_new, t_new = _retract(R, t, delta)
            X_new = points + dp
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
