"""Canonical warping: inverse pairs, isometry, kornia Se3 agreement, extreme rotations."""

from __future__ import annotations

import math

import pytest
import torch
from kornia.geometry.liegroup import Se3, So3

from adnerf.pose import (
    HeadPose,
    directions_to_canonical,
    euler_angles,
    euler_rotation,
    from_canonical,
    perturb_pose,
    rotation_angle,
    to_canonical,
)

AXIS = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64) / math.sqrt(0.98)


def _pose(angle: float, translation_scale: float = 1.0, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    R = So3.exp(AXIS * angle).matrix()
    t = torch.tensor([0.2, -0.1, 0.7], dtype=torch.float64) * translation_scale
    return R.to(dtype), t.to(dtype)


def _points(dtype: torch.dtype, n: int = 64, scale: float = 1.0) -> torch.Tensor:
    return (torch.randn(n, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * scale).to(dtype)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 0.7, math.pi - 1e-6, math.pi])
def test_round_trip_and_isometry(angle: float, dtype: torch.dtype, tol: dict) -> None:
    R, t = _pose(angle, dtype=dtype)
    x = _points(dtype)
    can = to_canonical(x, R, t)
    torch.testing.assert_close(from_canonical(can, R, t), x, rtol=tol["rtol"] * 10, atol=tol["atol"] * 10)
    # Distances are preserved.
    d_cam = torch.linalg.vector_norm(x[:, None] - x[None], dim=-1)
    d_can = torch.linalg.vector_norm(can[:, None] - can[None], dim=-1)
    torch.testing.assert_close(d_can, d_cam, rtol=tol["rtol"] * 10, atol=1e-5 if dtype == torch.float32 else 1e-12)
    # Directions rotate but do not translate: the warp of a difference is the rotated difference.
    diff = x[1:] - x[:-1]
    torch.testing.assert_close(directions_to_canonical(diff, R), can[1:] - can[:-1], rtol=1e-4 if dtype == torch.float32 else 1e-10, atol=1e-5 if dtype == torch.float32 else 1e-12)


def test_identity_pose_is_exact(dtype: torch.dtype) -> None:
    x = _points(dtype)
    pose = HeadPose.identity(dtype=dtype)
    assert torch.equal(pose.to_canonical(x), x)
    assert torch.equal(pose.from_canonical(x), x)
    assert torch.equal(directions_to_canonical(x, pose.R), x)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1.3, math.pi - 1e-6])
def test_agrees_with_kornia_se3(angle: float) -> None:
    R, t = _pose(angle)
    x = _points(torch.float64)
    se3 = Se3(So3.from_matrix(R[None].expand(x.shape[0], 3, 3)), t.expand(x.shape[0], 3))
    torch.testing.assert_close(from_canonical(x, R, t), se3 * x, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(to_canonical(x, R, t), se3.inverse() * x, rtol=1e-12, atol=1e-12)
    pose = HeadPose(R, t)
    torch.testing.assert_close(HeadPose.from_se3(pose.se3()).matrix(), pose.matrix(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("scale", [1e-12, 1.0, 1e6])
def test_far_and_near_translations(scale: float, dtype: torch.dtype) -> None:
    R, t = _pose(0.4, translation_scale=scale, dtype=dtype)
    x = _points(dtype, scale=max(scale, 1.0)) + t
    back = from_canonical(to_canonical(x, R, t), R, t)
    eps = torch.finfo(dtype).eps
    # Error relative to the magnitudes involved: a few ulps of |x| + |t|.
    bound = 16 * eps * (x.abs().amax() + t.abs().amax())
    assert (back - x).abs().max() <= bound
    assert torch.isfinite(back).all()


def test_batched_poses_broadcast_over_samples() -> None:
    R = torch.stack([_pose(a)[0] for a in (0.1, 0.5, 2.0)])  # (3, 3, 3)
    t = torch.stack([_pose(a, s)[1] for a, s in ((0.1, 1.0), (0.5, 2.0), (2.0, -1.0))])  # (3, 3)
    x = torch.randn(3, 10, 3, dtype=torch.float64)
    batched = to_canonical(x, R[:, None], t[:, None])
    for i in range(3):
        torch.testing.assert_close(batched[i], to_canonical(x[i], R[i], t[i]))


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-4, 1.0, math.pi - 1e-6, math.pi])
def test_rotation_angle_is_accurate_at_the_extremes(angle: float) -> None:
    R = So3.exp(AXIS * angle).matrix()
    assert abs(rotation_angle(R).item() - angle) <= 4e-15 + 1e-9 * (angle > math.pi - 1e-3)


def test_perturbation_rotates_about_the_head_centre() -> None:
    R, t = _pose(0.3)
    centre = torch.tensor([0.0, 0.05, -0.02], dtype=torch.float64)
    yaw, pitch, roll = math.radians(15), math.radians(-5), math.radians(3)
    R2, t2 = perturb_pose(R, t, yaw=yaw, pitch=pitch, roll=roll, center=centre)
    # The head centre stays where it was in camera space.
    torch.testing.assert_close(from_canonical(centre, R2, t2), from_canonical(centre, R, t))
    # The change is exactly the requested rotation, applied in camera axes.
    D = R2 @ R.T
    torch.testing.assert_close(D, euler_rotation(yaw, pitch, roll, like=R))
    # Pure yaw turns about the camera's vertical axis by the requested angle.
    R3, _ = perturb_pose(R, t, yaw=yaw)
    D3 = R3 @ R.T
    assert abs(rotation_angle(D3).item() - yaw) < 1e-12
    torch.testing.assert_close(D3[:, 1], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


def test_zero_perturbation_is_exact() -> None:
    R, t = _pose(1.1)
    R2, t2 = perturb_pose(R, t)
    assert torch.equal(R2, R) and torch.equal(t2, t)


def test_headpose_algebra() -> None:
    R, t = _pose(0.9)
    pose = HeadPose(R, t)
    ident = pose.compose(pose.inverse())
    torch.testing.assert_close(ident.matrix(), torch.eye(4, dtype=torch.float64), rtol=0, atol=1e-15)
    torch.testing.assert_close(HeadPose.from_matrix(pose.matrix()).matrix(), pose.matrix())
    assert pose.code().shape == (9,)
    with pytest.raises(ValueError):
        HeadPose(R, t[:2])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_euler_angles_invert_euler_rotation(dtype: torch.dtype) -> None:
    """Angles drawn over the whole domain (pitch within +-pi/2) come back from their rotation: a
    swapped axis order or a sign error in any of the three would fail."""
    g = torch.Generator().manual_seed(3)
    a = (torch.rand(2000, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([2 * math.pi, math.pi, 2 * math.pi], dtype=torch.float64)
    a = a.to(dtype)
    R = euler_rotation(a[:, 0], a[:, 1], a[:, 2], like=a)
    back = euler_angles(R)
    assert back.dtype == dtype
    tol = 1e-12 if dtype == torch.float64 else 5e-4  # yaw and roll lose digits as the pitch nears +-pi/2
    wrapped = torch.remainder(back - a + math.pi, 2 * math.pi) - math.pi  # yaw and roll are defined modulo 2 pi
    assert wrapped.abs().max() < tol


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_euler_angles_at_gimbal_lock_rebuild_the_rotation(sign: float) -> None:
    """At pitch +-90 degrees only yaw -+ roll is defined: the angles reported (roll 0) rebuild the
    same rotation, with no NaN."""
    like = torch.zeros((), dtype=torch.float64)
    R = euler_rotation(0.3, sign * math.pi / 2, 0.2, like=like)
    back = euler_angles(R)
    assert torch.isfinite(back).all() and back[2] == 0.0
    torch.testing.assert_close(euler_rotation(*back, like=like), R, atol=1e-12, rtol=0)
