"""Rigid head pose and the warp between camera space and the head's canonical space.

Convention: a head pose ``(R, t)`` maps head-canonical coordinates to camera coordinates,

    x_cam = R x_can + t,        x_can = R^T (x_cam - t),        d_can = R^T d_cam.

``R`` is a rotation matrix ``(..., 3, 3)`` and ``t`` a translation ``(..., 3)`` in scene units.
Everything here is differentiable, follows the dtype and device of its inputs, and is exact for
the identity pose. kornia's :class:`~kornia.geometry.liegroup.Se3` is the group type used for
interchange (:meth:`HeadPose.se3`, :meth:`HeadPose.from_se3`) and for rotations about axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.liegroup import Se3, So3
from torch import Tensor

__all__ = [
    "HeadPose",
    "directions_from_canonical",
    "directions_to_canonical",
    "euler_angles",
    "euler_rotation",
    "from_canonical",
    "mean_rotation",
    "perturb_pose",
    "rotation_angle",
    "to_canonical",
]


def _check(points: Tensor, R: Tensor, t: Tensor | None = None) -> None:
    if points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3); got {tuple(points.shape)}")
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3); got {tuple(R.shape)}")
    if t is not None and t.shape[-1] != 3:
        raise ValueError(f"t must have shape (..., 3); got {tuple(t.shape)}")


def to_canonical(points: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Camera-space points to head-canonical space: ``x_can = R^T (x_cam - t)``.

    Args:
        points: Camera-space points, shape ``(..., 3)``.
        R: Head rotation, shape ``(..., 3, 3)`` broadcastable against ``points``.
        t: Head translation, shape ``(..., 3)`` broadcastable against ``points``.

    Returns:
        Canonical points, shape ``(..., 3)`` (the broadcast batch shape).

    Example:
        >>> R = euler_rotation(0.3, 0.1, 0.0, like=torch.zeros((), dtype=torch.float64))
        >>> t = torch.tensor([0.0, 0.1, 2.0], dtype=torch.float64)
        >>> to_canonical(t, R, t)  # the head's position is its canonical origin
        tensor([0., 0., 0.], dtype=torch.float64)
        >>> x = torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64)
        >>> torch.allclose(from_canonical(to_canonical(x, R, t), R, t), x)
        True
    """
    _check(points, R, t)
    return torch.einsum("...ji,...j->...i", R, points - t)


def from_canonical(points: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Head-canonical points to camera space: ``x_cam = R x_can + t``.

    Args:
        points: Canonical points, shape ``(..., 3)``.
        R: Head rotation, shape ``(..., 3, 3)``.
        t: Head translation, shape ``(..., 3)``.

    Returns:
        Camera-space points, shape ``(..., 3)``.

    Example:
        >>> R = euler_rotation(0.5 * torch.pi, 0.0, 0.0, like=torch.zeros((), dtype=torch.float64))
        >>> from_canonical(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), R, torch.zeros(3, dtype=torch.float64)).round(decimals=6)
        tensor([ 0.,  0., -1.], dtype=torch.float64)
    """
    _check(points, R, t)
    return torch.einsum("...ij,...j->...i", R, points) + t


def directions_to_canonical(directions: Tensor, R: Tensor) -> Tensor:
    """Rotate camera-space directions into canonical space: ``d_can = R^T d_cam`` (no translation)."""
    _check(directions, R)
    return torch.einsum("...ji,...j->...i", R, directions)


def directions_from_canonical(directions: Tensor, R: Tensor) -> Tensor:
    """Rotate canonical directions into camera space: ``d_cam = R d_can`` (no translation)."""
    _check(directions, R)
    return torch.einsum("...ij,...j->...i", R, directions)


def rotation_angle(R: Tensor) -> Tensor:
    """Rotation angle in radians of rotation matrices ``(..., 3, 3)``, in ``[0, pi]``.

    Uses ``atan2(|axis * sin|, cos)`` from the skew and trace parts, which stays accurate near 0
    and near pi where ``arccos((tr - 1) / 2)`` loses half the digits.

    Example:
        >>> R = euler_rotation(0.0, 0.0, 3.14159, like=torch.zeros((), dtype=torch.float64))
        >>> round(float(rotation_angle(R)), 5)
        3.14159
    """
    skew = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], dim=-1
    )
    sin = 0.5 * torch.linalg.vector_norm(skew, dim=-1)
    cos = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    return torch.atan2(sin, cos)


def euler_rotation(yaw: Tensor | float, pitch: Tensor | float, roll: Tensor | float, *, like: Tensor) -> Tensor:
    """Rotation ``R_y(yaw) @ R_x(pitch) @ R_z(roll)`` in camera axes (radians), shape ``(..., 3, 3)``.

    In OpenCV camera axes: yaw turns about the vertical (y, pointing down) axis, pitch nods about
    the horizontal (x) axis and roll tilts about the optical (z) axis. Built from kornia
    :class:`~kornia.geometry.liegroup.So3` elementary rotations; dtype and device follow ``like``.
    """
    angles = [torch.as_tensor(a, dtype=like.dtype, device=like.device) for a in (yaw, pitch, roll)]
    yaw_t, pitch_t, roll_t = torch.broadcast_tensors(*angles)
    shape = yaw_t.shape
    flat = [a.reshape(-1) for a in (yaw_t, pitch_t, roll_t)]
    R = (So3.rot_y(flat[0]) * So3.rot_x(flat[1]) * So3.rot_z(flat[2])).matrix()
    return R.reshape(*shape, 3, 3)


def euler_angles(R: Tensor) -> Tensor:
    """The inverse of :func:`euler_rotation`: ``(yaw, pitch, roll)`` in radians, shape ``(..., 3)``,
    of rotations ``R (..., 3, 3) = R_y(yaw) @ R_x(pitch) @ R_z(roll)`` (camera axes).

    Pitch lies in ``[-pi/2, pi/2]``, yaw and roll in ``(-pi, pi]``. At gimbal lock (pitch
    ``+-pi/2``, where only ``yaw -+ roll`` is defined) the roll is reported as 0 and the yaw carries
    the rotation. dtype and device follow ``R``.

    Example:
        >>> import torch
        >>> R = euler_rotation(0.3, -0.2, 0.1, like=torch.zeros((), dtype=torch.float64))
        >>> [round(float(a), 6) for a in euler_angles(R)]
        [0.3, -0.2, 0.1]
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3); got {tuple(R.shape)}")
    # R = [[., ., sy cp], [cp sr, cp cr, -sp], [., ., cy cp]] for R_y(y) R_x(p) R_z(r).
    cos_pitch = torch.hypot(R[..., 1, 0], R[..., 1, 1])
    pitch = torch.atan2(-R[..., 1, 2], cos_pitch)
    locked = cos_pitch <= 1e-12 * torch.ones_like(cos_pitch)
    yaw = torch.where(locked, torch.atan2(-R[..., 2, 0], R[..., 0, 0]), torch.atan2(R[..., 0, 2], R[..., 2, 2]))
    roll = torch.where(locked, torch.zeros_like(pitch), torch.atan2(R[..., 1, 0], R[..., 1, 1]))
    return torch.stack([yaw, pitch, roll], dim=-1)


def mean_rotation(R: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations ``(N, 3, 3)`` (numpy, float64): the rotation nearest to their
    arithmetic mean."""
    u, _, vt = np.linalg.svd(np.asarray(R, dtype=np.float64).mean(0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def perturb_pose(
    R: Tensor,
    t: Tensor,
    *,
    yaw: Tensor | float = 0.0,
    pitch: Tensor | float = 0.0,
    roll: Tensor | float = 0.0,
    center: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Rotate a head pose about the head centre by yaw / pitch / roll offsets in camera axes.

    The new pose is ``x_cam' = D (x_cam - c) + c`` applied after the old one, with
    ``D = euler_rotation(yaw, pitch, roll)`` and ``c`` the head centre in camera space, so
    ``R' = D R`` and ``t' = D (t - c) + c``. Zero offsets return the pose unchanged (exactly).

    Args:
        R: Head rotation, shape ``(..., 3, 3)``.
        t: Head translation, shape ``(..., 3)``.
        yaw: Offset about the camera's vertical axis in radians (scalar or ``(...)``).
        pitch: Offset about the camera's horizontal axis in radians.
        roll: Offset about the optical axis in radians.
        center: Head centre in *canonical* coordinates, shape ``(3,)`` or ``(..., 3)``; default
            the canonical origin, whose camera position is ``t``.

    Returns:
        ``(R', t')`` with the shapes of ``R`` and ``t``.

    Example:
        >>> R, t = torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
        >>> R2, t2 = perturb_pose(R, t, yaw=0.2)
        >>> t2  # turned about its own centre: the head stays where it was
        tensor([0., 0., 3.], dtype=torch.float64)
        >>> round(float(rotation_angle(R2)), 6)
        0.2
    """
    D = euler_rotation(yaw, pitch, roll, like=R)
    c = t if center is None else from_canonical(center.to(t), R, t)
    R_new = D @ R
    t_new = torch.einsum("...ij,...j->...i", D, t - c) + c
    return R_new, t_new


@dataclass
class HeadPose:
    """A batch of rigid head poses, head-canonical to camera.

    Attributes:
        R: Rotations, shape ``(..., 3, 3)``.
        t: Translations, shape ``(..., 3)``.
    """

    R: Tensor
    t: Tensor

    def __post_init__(self) -> None:
        if self.R.shape[-2:] != (3, 3) or self.t.shape[-1:] != (3,) or self.R.shape[:-2] != self.t.shape[:-1]:
            raise ValueError(f"HeadPose needs R (..., 3, 3) and t (..., 3); got {tuple(self.R.shape)} and {tuple(self.t.shape)}")

    @staticmethod
    def identity(*batch: int, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> "HeadPose":
        """Identity poses of batch shape ``batch``."""
        R = torch.eye(3, dtype=dtype, device=device).expand(*batch, 3, 3).clone()
        return HeadPose(R, torch.zeros(*batch, 3, dtype=dtype, device=device))

    @staticmethod
    def from_matrix(matrix: Tensor) -> "HeadPose":
        """From homogeneous transforms ``(..., 4, 4)`` (or ``(..., 3, 4)``)."""
        if matrix.shape[-2:] not in ((4, 4), (3, 4)):
            raise ValueError(f"pose matrix must have shape (..., 4, 4) or (..., 3, 4); got {tuple(matrix.shape)}")
        return HeadPose(matrix[..., :3, :3], matrix[..., :3, 3])

    def matrix(self) -> Tensor:
        """Homogeneous transforms, shape ``(..., 4, 4)``."""
        out = torch.zeros(*self.R.shape[:-2], 4, 4, dtype=self.R.dtype, device=self.R.device)
        out[..., :3, :3] = self.R
        out[..., :3, 3] = self.t
        out[..., 3, 3] = 1.0
        return out

    @staticmethod
    def from_se3(pose: Se3) -> "HeadPose":
        """From a kornia :class:`Se3` (canonical to camera)."""
        m = pose.matrix()
        return HeadPose(m[..., :3, :3], m[..., :3, 3])

    def se3(self) -> Se3:
        """As a kornia :class:`Se3` (canonical to camera)."""
        return Se3(So3.from_matrix(self.R), self.t)

    def inverse(self) -> "HeadPose":
        """Camera-to-canonical pose ``(R^T, -R^T t)``.

        Example:
            >>> p = HeadPose(euler_rotation(0.3, 0.2, 0.1, like=torch.zeros((), dtype=torch.float64)), torch.tensor([0.1, 0.2, 3.0], dtype=torch.float64))
            >>> torch.allclose(p.compose(p.inverse()).matrix(), torch.eye(4, dtype=torch.float64))
            True
        """
        Rt = self.R.transpose(-1, -2)
        return HeadPose(Rt, -torch.einsum("...ij,...j->...i", Rt, self.t))

    def compose(self, other: "HeadPose") -> "HeadPose":
        """``self * other``: apply ``other`` first, then ``self``."""
        return HeadPose(self.R @ other.R, torch.einsum("...ij,...j->...i", self.R, other.t) + self.t)

    def to_canonical(self, points: Tensor) -> Tensor:
        """Camera-space points ``(..., 3)`` to canonical space (see :func:`to_canonical`)."""
        return to_canonical(points, self.R, self.t)

    def from_canonical(self, points: Tensor) -> Tensor:
        """Canonical points ``(..., 3)`` to camera space (see :func:`from_canonical`)."""
        return from_canonical(points, self.R, self.t)

    def perturbed(self, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0, center: Tensor | None = None) -> "HeadPose":
        """The pose rotated about the head centre (angles in radians; see :func:`perturb_pose`)."""
        return HeadPose(*perturb_pose(self.R, self.t, yaw=yaw, pitch=pitch, roll=roll, center=center))

    def code(self) -> Tensor:
        """A continuous pose vector ``(..., 9)``: the first two columns of ``R`` and ``t``.

        The 6-D rotation representation is continuous (unlike Euler angles or quaternions with
        sign flips), which makes it a good conditioning input for the torso field.

        Example:
            >>> HeadPose.identity(5).code().shape
            torch.Size([5, 9])
            >>> HeadPose.identity().code()
            tensor([1., 0., 0., 0., 1., 0., 0., 0., 0.], dtype=torch.float64)
        """
        return torch.cat([self.R[..., :, 0], self.R[..., :, 1], self.t], dim=-1)

    def __getitem__(self, index: object) -> "HeadPose":
        return HeadPose(self.R[index], self.t[index])

    def to(self, *args: object, **kwargs: object) -> "HeadPose":
        """Move / cast both tensors like :meth:`torch.Tensor.to`."""
        return HeadPose(self.R.to(*args, **kwargs), self.t.to(*args, **kwargs))
