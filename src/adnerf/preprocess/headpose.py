"""Head pose per frame: tracks -> perspective-n-point initialisation -> bundle adjustment -> gauge.

Scene units: the head is ``head_width`` units wide (1.6 by default, as in the synthetic scene),
measured on the reference frame's head silhouette; the canonical origin is the centre of the
ellipsoid fitted to that silhouette and the canonical axes are those of the mean head orientation
(after adjustment, the poses are re-expressed so that their chordal mean rotation is the identity).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np
import torch
from kornia.geometry.camera import project_points as kornia_project

from ..cameras import intrinsics_matrix
from ..formats.dataset import LABEL_HEAD
from ..pose import mean_rotation, rotation_angle
from .bundle import bundle_adjust, ellipsoid_points
from .tracking import Tracks

__all__ = ["HeadTrack", "head_boxes", "estimate_head_poses", "mean_rotation", "smooth_poses", "triangulate_canonical", "align_poses", "chain_segments", "project_points"]


@dataclass
class HeadTrack:
    """Estimated head poses.

    Attributes:
        poses: ``(N, 4, 4)`` float64 head-canonical -> camera.
        points: ``(P, 3)`` canonical track points (NaN for tracks no frame could place).
        radii: ``(3,)`` semi-axes of the head ellipsoid used for initialisation (canonical units).
        reference: The frame whose pose fixed the gauge.
        rms_before, rms, median: Reprojection errors in pixels (initial guess, adjusted RMS,
            adjusted median).
        iterations: LM iterations.
        inlier_fraction: Observations within the Huber threshold.
        landmark_rms: RMS reprojection error in pixels of the landmarks that joined the
            adjustment (NaN when none did); ``rms`` and ``median`` count them as well.
    """

    poses: np.ndarray
    points: np.ndarray
    radii: np.ndarray
    reference: int
    rms_before: float
    rms: float
    median: float
    iterations: int
    inlier_fraction: float
    landmark_rms: float = float("nan")
    adjusted: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    """The adjustment's own ``(R (N, 3, 3), t (N, 3), points (P', 3))`` before smoothing and the gauge
    (tracks, then landmarks): where a later adjustment of the same tracks starts (``initial``)."""


def head_boxes(labels: np.ndarray) -> np.ndarray:
    """Bounding boxes ``(N, 4)`` ``[x0, y0, x1, y1]`` (pixel edges) of the head label; NaN when absent."""
    out = np.full((len(labels), 4), np.nan)
    for i, lab in enumerate(labels):
        head = lab == LABEL_HEAD
        rows, cols = np.flatnonzero(head.any(1)), np.flatnonzero(head.any(0))
        if len(rows):
            out[i] = (cols[0], rows[0], cols[-1] + 1, rows[-1] + 1)
    return out


def _interpolate_poses(R: np.ndarray, t: np.ndarray, good: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses of frames where ``good`` is False, linearly interpolated (rotation vectors relative
    to the mean rotation of the good frames; ends held)."""
    M = mean_rotation(R[good])
    rel = np.stack([cv2.Rodrigues(M.T @ r)[0][:, 0] for r in R])
    idx, miss = np.flatnonzero(good), np.flatnonzero(~good)
    R, t = R.copy(), t.copy()
    for k in range(3):
        rel[miss, k] = np.interp(miss, idx, rel[idx, k])
        t[miss, k] = np.interp(miss, idx, t[idx, k])
    R[miss] = np.stack([M @ cv2.Rodrigues(rel[i])[0] for i in miss])
    return R, t


def smooth_poses(poses: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing over time (``sigma`` in frames) of rotation vectors and translations.

    Rotations are smoothed as rotation vectors relative to their mean rotation (small angles for a
    talking head), so there is no wrap-around; ``sigma <= 0`` returns a copy.
    """
    if sigma <= 0 or len(poses) < 3:
        return poses.copy()
    from scipy.ndimage import gaussian_filter1d

    M = mean_rotation(poses[:, :3, :3])
    rel = np.stack([cv2.Rodrigues(M.T @ r)[0][:, 0] for r in poses[:, :3, :3]])
    rel = gaussian_filter1d(rel, sigma, axis=0, mode="nearest")
    t = gaussian_filter1d(poses[:, :3, 3], sigma, axis=0, mode="nearest")
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, :3] = np.stack([M @ cv2.Rodrigues(v)[0] for v in rel])
    out[:, :3, 3] = t
    return out


def project_points(points: np.ndarray, K: tuple[float, float, float, float]) -> np.ndarray:
    """Pixel positions ``(..., 2)`` (centre convention) of camera-frame points ``(..., 3)``: numpy
    in and out around the one pinhole projection (kornia's, as :meth:`adnerf.cameras.Camera.project`)."""
    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float64))
    flat = pts.reshape(-1, 3)
    uv = kornia_project(flat, intrinsics_matrix(*K, dtype=torch.float64).expand(flat.shape[0], 3, 3))
    return uv.reshape(*pts.shape[:-1], 2).numpy()


def align_poses(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Similarity alignment of estimated to true poses and per-frame errors.

    Args:
        est, true: ``(N, 4, 4)`` head-canonical -> camera poses.

    Returns:
        ``(rotation error (N,) degrees, translation error (N,) in the true scene's units,
        {"scale": s, "G": (3, 3), "g": (3,)})``.
    """
    Re, te = est[:, :3, :3], est[:, :3, 3]
    Rt, tt = true[:, :3, :3], true[:, :3, 3]
    u, _, vt = np.linalg.svd((Re.transpose(0, 2, 1) @ Rt).sum(0))
    G = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    # Linear least squares in (g, s): R_est g - s t_true = -t_est.
    n = len(est)
    A = np.concatenate([Re, -tt[:, :, None]], axis=2).reshape(3 * n, 4)
    sol, *_ = np.linalg.lstsq(A, -te.reshape(-1), rcond=None)
    g, s = sol[:3], sol[3]
    rel = Re @ G @ Rt.transpose(0, 2, 1)
    rot = np.degrees(rotation_angle(torch.from_numpy(np.ascontiguousarray(rel))).numpy())
    aligned = (np.einsum("nij,j->ni", Re, g) + te) / s
    return rot, np.linalg.norm(aligned - tt, axis=1), {"scale": float(s), "G": G, "g": g}


def triangulate_canonical(
    pixels: np.ndarray, poses: np.ndarray, K: tuple[float, float, float, float], prior: np.ndarray, prior_weight: float = 0.01
) -> np.ndarray:
    """The canonical point seen at ``pixels`` under head ``poses``: linear least squares over rays.

    Minimises ``sum_i |(I - d_i d_i^T)(R_i p + t_i)|^2 + w N |p - prior|^2`` over canonical ``p``,
    where ``d_i`` is the unit camera ray through pixel ``i``: the distance (scene units) of the
    point from every ray, plus a weak pull towards ``prior`` that decides what the rays leave
    open (a talking head turns little, so depth along the viewing direction is barely constrained).

    Args:
        pixels: ``(N, 2)`` pixel positions (centre convention); rows with NaN are skipped.
        poses: ``(N, 4, 4)`` head-canonical -> camera.
        K: ``(fx, fy, cx, cy)``.
        prior: ``(3,)`` canonical point favoured where the rays do not decide.
        prior_weight: ``w``; must be positive (it keeps the system well posed).

    Returns:
        ``(3,)`` float64 canonical point; ``prior`` when no row is finite.
    """
    if not prior_weight > 0:
        raise ValueError(f"prior_weight must be positive; got {prior_weight}")
    prior = np.asarray(prior, dtype=np.float64)
    ok = np.isfinite(pixels).all(1)
    if not ok.any():
        return prior.copy()
    fx, fy, cx, cy = K
    d = np.stack([(pixels[ok, 0] - cx) / fx, (pixels[ok, 1] - cy) / fy, np.ones(int(ok.sum()))], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    A = np.eye(3) - d[:, :, None] * d[:, None, :]  # (n, 3, 3) projectors off each ray
    R, t = poses[ok, :3, :3], poses[ok, :3, 3]
    RtA = R.transpose(0, 2, 1) @ A
    w = prior_weight * len(d)
    lhs = (RtA @ R).sum(0) + w * np.eye(3)
    rhs = -np.einsum("nij,nj->i", RtA, t) + w * prior
    return np.linalg.solve(lhs, rhs)


def chain_segments(segments: list[tuple[int, np.ndarray]], n_frames: int) -> tuple[np.ndarray, list[float]]:
    """Poses of overlapping segments, each in its own canonical frame and scale, in one frame.

    Each segment after the first is carried into the canonical frame of the one before by the
    similarity that best aligns their shared frames (:func:`align_poses`: ``R_a ~ R_b G``,
    ``s t_a ~ R_b g + t_b``, so ``R_b <- R_b G`` and ``t_b <- (R_b g + t_b) / s``). A shared frame
    takes the earlier segment's pose in the first half of the overlap and the later one's in the
    second (the ends of a segment are its least constrained frames). Finally the canonical frame
    is turned so that the chordal mean rotation of all frames is the identity (a single segment
    is returned as it is).

    Args:
        segments: ``(start frame, poses (n_i, 4, 4))`` in order; segment ``k + 1`` must start
            inside segment ``k`` and end after it.
        n_frames: Frames in the clip; the segments must cover them.

    Returns:
        ``((n_frames, 4, 4) poses, rotation disagreement (degrees, median over the overlap) of
        each joint after alignment)``.

    Raises:
        ValueError: Segments that do not overlap or do not cover the clip.
    """
    start0, first = segments[0]
    if start0 != 0:
        raise ValueError("the first segment must start at frame 0")
    if len(segments) == 1:
        if len(first) != n_frames:
            raise ValueError(f"the segments cover frames 0-{len(first) - 1} of {n_frames}")
        return first.copy(), []
    out = np.full((n_frames, 4, 4), np.nan)
    out[: len(first)] = first
    end = len(first)
    joints = []
    prev_start, prev = start0, first
    for start, poses in segments[1:]:
        lo, hi = start, min(prev_start + len(prev), start + len(poses))
        if not (prev_start < lo < hi) or start + len(poses) <= prev_start + len(prev):
            raise ValueError(f"segment at frame {start} does not overlap the one before and reach past it")
        ref = out[lo:hi]
        rot, _, sim = align_poses(poses[: hi - lo], ref)
        joints.append(float(np.median(rot)))
        moved = poses.copy()
        moved[:, :3, :3] = poses[:, :3, :3] @ sim["G"]
        moved[:, :3, 3] = (np.einsum("nij,j->ni", poses[:, :3, :3], sim["g"]) + poses[:, :3, 3]) / sim["scale"]
        switch = (lo + hi) // 2
        out[switch : start + len(poses)] = moved[switch - start :]
        end = start + len(poses)
        prev_start, prev = start, moved
    if end < n_frames:
        raise ValueError(f"the segments cover frames 0-{end - 1} of {n_frames}")
    M = mean_rotation(out[:, :3, :3])
    out[:, :3, :3] = out[:, :3, :3] @ M.T
    return out, joints


def _pnp(X: np.ndarray, uv: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    rvec, _ = cv2.Rodrigues(R)
    ok, rvec, tvec = cv2.solvePnP(X, uv, K, None, rvec.copy(), t.reshape(3, 1).copy(), useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or not np.all(np.isfinite(tvec)) or tvec[2, 0] <= 0:
        return None
    return cv2.Rodrigues(rvec)[0], tvec[:, 0]


def _first_guess(
    uv: np.ndarray, obs: np.ndarray, R: np.ndarray, t: np.ndarray, radii: np.ndarray, reference: int,
    intrinsics: tuple[float, float, float, float], initial: HeadTrack | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The adjustment's start: poses ``R (N, 3, 3)``, ``t (N, 3)`` and canonical points ``(P, 3)``.

    From ``initial``'s adjusted poses and points (tracks it could not place seeded under them),
    or else a chain from the reference frame outwards: each frame's pose by perspective-n-point
    from the points already placed, and its new tracks placed on the ellipsoid ``radii``.
    """
    fx, fy, cx, cy = intrinsics
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    n = len(uv)
    points = np.full((uv.shape[1], 3), np.nan)

    def seed(i: int) -> None:
        new = obs[i] & ~np.isfinite(points[:, 0])
        if new.any():
            got = ellipsoid_points(
                torch.from_numpy(uv[i, new]),
                torch.from_numpy(R[i]).expand(int(new.sum()), 3, 3),
                torch.from_numpy(t[i]).expand(int(new.sum()), 3),
                torch.from_numpy(radii),
                intrinsics,
            )
            points[new] = got.numpy()

    order = list(range(reference, n)) + list(range(reference - 1, -1, -1))
    if initial is not None:
        R0, t0, X0 = initial.adjusted  # type: ignore[misc]
        R, t = R0.copy(), t0.copy()
        m = min(len(X0), len(points))
        points[:m] = X0[:m]
        for i in order:
            seed(i)
        return R, t, points
    seed(reference)
    for k, i in enumerate(order[1:], 1):
        prev = order[k - 1]
        known = obs[i] & np.isfinite(points[:, 0])
        R[i], t[i] = R[prev], t[prev]
        if known.sum() >= 6:
            got = _pnp(points[known], uv[i, known], K, R[prev], t[prev])
            if got is not None:
                R[i], t[i] = got
        seed(i)
    return R, t, points


def _landmark_rms(R: np.ndarray, t: np.ndarray, X: np.ndarray, uv: np.ndarray, good: np.ndarray, intrinsics: tuple[float, float, float, float]) -> float:
    """RMS reprojection error (pixels) of the landmarks ``uv (N, L, 2)`` at their adjusted points
    ``X (L, 3)`` in the adjusted frames ``good``; NaN without landmarks."""
    if uv.shape[1] == 0:
        return float("nan")
    cam = np.einsum("nij,pj->npi", R, X) + t[:, None]
    err = np.linalg.norm(project_points(cam, intrinsics) - uv, axis=-1)[good]
    err = err[np.isfinite(err)]  # frames without the landmark, and landmarks never seen
    return float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")


def _reference_head(box: np.ndarray, reference: int, intrinsics: tuple[float, float, float, float], head_width: float) -> tuple[np.ndarray, np.ndarray]:
    """The head in the reference frame from its box ``(x0, y0, x1, y1)``: its position ``(3,)``
    (``head_width`` across the box fixes the depth) and the ellipsoid's radii ``(3,)``.

    Raises:
        ValueError: The reference frame shows no head.
    """
    if not np.all(np.isfinite(box)):
        raise ValueError(f"frame {reference} shows no head; cannot anchor the head pose")
    fx, fy, cx, cy = intrinsics
    x0, y0, x1, y1 = box
    z0 = fx * head_width / (x1 - x0)
    height = (y1 - y0) * z0 / fy
    position = np.array([(0.5 * (x0 + x1) - cx) / fx * z0, (0.5 * (y0 + y1) - cy) / fy * z0, z0])
    return position, np.array([head_width / 2, height / 2, 0.55 * head_width])


def _gauged(R: np.ndarray, t: np.ndarray, smooth_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(N, 4, 4)`` from ``R``, ``t`` smoothed over ``smooth_sigma`` frames, in the gauge
    whose canonical axes are the mean head orientation ``M`` (returned): ``R_i <- R_i M^T`` and
    ``x <- M x`` leave every camera point ``R_i x + t_i`` unchanged and make the chordal mean of
    the ``R_i`` the identity."""
    poses = np.tile(np.eye(4), (len(R), 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = t
    poses = smooth_poses(poses, smooth_sigma)
    M = mean_rotation(poses[:, :3, :3])
    poses[:, :3, :3] = poses[:, :3, :3] @ M.T
    return poses, M


def _with_landmarks(uv: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """The tracks ``(N, P, 2)`` followed by the landmarks ``(N, L, 2)`` as more tracks (a landmark
    with a NaN coordinate not observed in that frame).

    Raises:
        ValueError: Landmarks of another number of frames or not 2-d.
    """
    if landmarks.shape[0] != len(uv) or landmarks.shape[-1] != 2:
        raise ValueError(f"landmarks must be ({len(uv)}, L, 2); got {landmarks.shape}")
    return np.concatenate([uv, np.where(np.isfinite(landmarks).all(-1, keepdims=True), landmarks, np.nan)], axis=1)


def estimate_head_poses(
    tracks: Tracks,
    labels: np.ndarray,
    intrinsics: tuple[float, float, float, float],
    *,
    head_width: float = 1.6,
    reference: int = -1,
    smooth_sigma: float = 0.0,
    shape_sigma: float = 0.05,
    landmarks: np.ndarray | None = None,
    landmark_weight: float = 0.0,
    iterations: int = 30,
    progress: Callable[[int, float], None] | None = None,
    initial: HeadTrack | None = None,
) -> HeadTrack:
    """Head poses from point tracks (see the module docstring for the units and gauge).

    Args:
        tracks: Point tracks on the rigid part of the head.
        labels: ``(N, H, W)`` parsing (head boxes for the initial depth and the ellipsoid).
        intrinsics: ``(fx, fy, cx, cy)`` pixels.
        head_width: Width of the head in scene units.
        reference: Frame that fixes the gauge (must show the head); -1: the first frame with at
            least 6 tracked points.
        smooth_sigma: Temporal smoothing of the result in frames (0: none).
        shape_sigma: Weight of the ellipsoid shape prior (see :func:`bundle_adjust`); 0 disables it.
        landmarks: ``(N, L, 2)`` detected positions (centre convention, NaN where not found) of
            face landmarks that move rigidly with the head (nose, eye corners): each joins the
            adjustment as one more track, a canonical point observed in every frame it was
            found. Unlike the chained flow tracks they do not drift; unlike them, they are few.
        landmark_weight: Weight of one landmark observation against one track observation (0: the
            landmarks are left out).
        iterations: Bundle-adjustment iterations.
        progress: Called per LM iteration as ``progress(iteration, rms)``.
        initial: An earlier estimate from the same tracks, of which these re-observe more (the
            pipeline's re-observation passes): the adjustment starts from its poses and points
            (tracks it could not place are seeded as usual), with its reference frame and
            ellipsoid, instead of from the perspective-n-point chain. It converges in fewer
            iterations to the same poses.

    Returns:
        A :class:`HeadTrack`.

    Raises:
        ValueError: The reference frame shows no head, or a frame has too few tracked points.
    """
    n = len(labels)
    warm = initial is not None and initial.adjusted is not None and len(initial.adjusted[0]) == n
    if warm:
        reference = initial.reference  # type: ignore[union-attr]
    if reference < 0:  # the first frame with enough tracked points
        counts = tracks.observed.sum(1)
        reference = int(np.argmax(counts >= 6)) if (counts >= 6).any() else int(np.argmax(counts))
    t_reference, radii = _reference_head(head_boxes(labels)[reference], reference, intrinsics, head_width)
    if warm:
        radii = initial.radii.copy()  # type: ignore[union-attr]
    R = np.tile(np.eye(3), (n, 1, 1))
    t = np.zeros((n, 3))
    t[reference] = t_reference
    n_tracks = tracks.uv.shape[1]
    uv = tracks.uv if landmarks is None or landmark_weight <= 0 else _with_landmarks(tracks.uv, landmarks)
    obs = np.isfinite(uv[..., 0])
    R, t, points = _first_guess(uv, obs, R, t, radii, reference, intrinsics, initial if warm else None)
    # Frames with fewer than 3 tracked points are left out of the adjustment and interpolated.
    good = obs.sum(1) >= 3
    good[reference] = True
    sub = np.flatnonzero(good)
    seen_points = np.isfinite(points[:, 0]) & obs[sub].any(0)
    weights = np.where(np.arange(uv.shape[1]) < n_tracks, 1.0, landmark_weight)[seen_points]
    result = bundle_adjust(
        torch.from_numpy(R[sub]),
        torch.from_numpy(t[sub]),
        torch.from_numpy(points[seen_points]),
        torch.from_numpy(uv[sub][:, seen_points]),
        intrinsics,
        fixed_frame=int(np.searchsorted(sub, reference)),
        shape_radii=torch.from_numpy(radii) if shape_sigma > 0 else None,
        shape_sigma=shape_sigma,
        point_weights=torch.from_numpy(weights),
        iterations=iterations,
        progress=progress,
    )
    Rb, tb = R.copy(), t.copy()
    Rb[sub], tb[sub] = result.R.numpy(), result.t.numpy()
    if not good.all():
        Rb, tb = _interpolate_poses(Rb, tb, good)
    Xb = result.points.numpy()
    X_all = _scatter(seen_points, Xb)
    landmark_rms = _landmark_rms(Rb, tb, X_all[n_tracks:], uv[:, n_tracks:], good, intrinsics)
    adjusted = (Rb.copy(), tb.copy(), X_all.copy())
    poses, M = _gauged(Rb, tb, smooth_sigma)
    return HeadTrack(
        poses=poses,
        points=X_all[:n_tracks] @ M.T,
        radii=radii,
        reference=reference,
        rms_before=result.rms_before,
        rms=result.rms,
        median=result.median,
        iterations=result.iterations,
        inlier_fraction=result.inlier_fraction,
        landmark_rms=landmark_rms,
        adjusted=adjusted,
    )


def _scatter(mask: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.full((len(mask),) + values.shape[1:], np.nan)
    out[mask] = values
    return out
