"""Pinhole cameras and the rays through their pixels.

Convention: OpenCV camera axes (x right, y down, z forward). Intrinsics ``K`` map camera
coordinates to continuous pixel coordinates ``(u, v)`` where the pixel in column ``j`` and row
``i`` covers ``[j, j + 1) x [i, i + 1)``, so its centre is ``(j + 0.5, i + 0.5)``. (kornia's own
convention puts pixel centres at integer coordinates; the two differ only in what ``cx, cy``
mean: a centred image has ``cx = W / 2`` here and ``(W - 1) / 2`` in kornia. Projection and
unprojection through ``K`` are the same formulas in both, and the functions below use kornia's.)

``cam_to_world`` is a ``(4, 4)`` rigid transform taking camera coordinates to world coordinates;
kornia's :class:`~kornia.geometry.camera.PinholeCamera` stores its inverse (world-to-camera) as
``extrinsics``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.camera import PinholeCamera, project_points, unproject_points
from torch import Tensor

from .pose import HeadPose
from .rays import RayBundle

__all__ = ["Camera", "intrinsics_matrix", "pixel_centers", "pixel_rays", "rays_through_pixels"]


def intrinsics_matrix(
    fx: float, fy: float, cx: float, cy: float, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """Build ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` of shape ``(3, 3)``.

    Example:
        >>> intrinsics_matrix(500.0, 500.0, 320.0, 240.0)
        tensor([[500.,   0., 320.],
                [  0., 500., 240.],
                [  0.,   0.,   1.]], dtype=torch.float64)
    """
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def _check_K(K: Tensor) -> None:
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"intrinsics K must have shape (..., 3, 3); got {tuple(K.shape)}")


def _check_pose(cam_to_world: Tensor) -> None:
    if cam_to_world.shape[-2:] != (4, 4):
        raise ValueError(f"cam_to_world must have shape (..., 4, 4); got {tuple(cam_to_world.shape)}")


def pixel_centers(height: int, width: int, *, dtype: torch.dtype, device: torch.device | str | None = None) -> Tensor:
    """Continuous coordinates ``(u, v)`` of every pixel centre, shape ``(height, width, 2)``."""
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive; got height={height}, width={width}")
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device) + 0.5,
        torch.arange(width, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def rays_through_pixels(K: Tensor, pixels: Tensor, cam_to_world: Tensor | None = None) -> RayBundle:
    """Rays through arbitrary continuous pixel coordinates.

    Args:
        K: Intrinsics, shape ``(3, 3)`` (or ``(..., 3, 3)`` broadcastable against ``pixels``).
        pixels: Continuous pixel coordinates ``(u, v)``, shape ``(..., 2)``; pixel centres are at
            ``+0.5`` (see module docstring).
        cam_to_world: Optional rigid camera-to-world transform, shape ``(4, 4)`` or broadcastable
            ``(..., 4, 4)``; ``None`` means rays in camera coordinates.

    Returns:
        A :class:`RayBundle` with origins and unit directions of shape ``(..., 3)``, in the dtype
        and on the device of ``pixels``.

    Example:
        >>> K = intrinsics_matrix(100.0, 100.0, 50.0, 50.0)
        >>> rays = rays_through_pixels(K, torch.tensor([[50.0, 50.0], [150.0, 50.0]], dtype=torch.float64))
        >>> rays.directions  # through the principal point: the optical axis; 100 px right: 45 degrees
        tensor([[0.0000, 0.0000, 1.0000],
                [0.7071, 0.0000, 0.7071]], dtype=torch.float64)
    """
    _check_K(K)
    if pixels.shape[-1] != 2:
        raise ValueError(f"pixels must have shape (..., 2); got {tuple(pixels.shape)}")
    K = K.to(pixels)
    batch = pixels.shape[:-1]
    flat = pixels.reshape(-1, 2)
    # kornia's unprojection to the z = 1 plane, then normalise to unit length.
    Kb = K.expand(*batch, 3, 3).reshape(-1, 3, 3)
    on_plane = unproject_points(flat, torch.ones_like(flat[:, :1]), Kb)
    directions = on_plane / torch.linalg.vector_norm(on_plane, dim=-1, keepdim=True)
    directions = directions.reshape(*batch, 3)
    origins = torch.zeros_like(directions)
    if cam_to_world is None:
        return RayBundle(origins, directions)
    _check_pose(cam_to_world)
    c2w = cam_to_world.to(pixels)
    rotation, translation = c2w[..., :3, :3], c2w[..., :3, 3]
    directions = torch.einsum("...ij,...j->...i", rotation, directions)
    origins = translation.expand_as(directions)
    return RayBundle(origins, directions)


def pixel_rays(K: Tensor, height: int, width: int, cam_to_world: Tensor | None = None) -> RayBundle:
    """Rays through every pixel centre of an image.

    Args:
        K: Intrinsics, shape ``(3, 3)``; its dtype and device are those of the result.
        height: Image height in pixels.
        width: Image width in pixels.
        cam_to_world: Optional camera-to-world transform, shape ``(4, 4)``; ``None`` is identity.

    Returns:
        A :class:`RayBundle` whose ``origins`` and ``directions`` have shape ``(height, width, 3)``;
        directions have unit length. Pixel ``[i, j]`` is row ``i``, column ``j``.

    Example:
        >>> rays = pixel_rays(intrinsics_matrix(2.0, 2.0, 2.0, 2.0), 4, 4)
        >>> rays.directions.shape
        torch.Size([4, 4, 3])
        >>> d = rays.directions[1, 1]  # the pixel centre (1.5, 1.5): half a pixel up-left of (cx, cy)
        >>> d / d[2]
        tensor([-0.2500, -0.2500,  1.0000], dtype=torch.float64)
        >>> float(d.norm())
        1.0
    """
    _check_K(K)
    if K.dim() != 2:
        raise ValueError(f"pixel_rays takes a single (3, 3) K; got {tuple(K.shape)}")
    if not torch.is_floating_point(K):
        K = K.double()
    pixels = pixel_centers(height, width, dtype=K.dtype, device=K.device)
    return rays_through_pixels(K, pixels, cam_to_world)


@dataclass
class Camera:
    """A pinhole camera with an image size and a pose.

    Attributes:
        K: Intrinsics, shape ``(3, 3)``.
        height: Image height in pixels.
        width: Image width in pixels.
        cam_to_world: Camera-to-world transform, shape ``(4, 4)``; identity when the world is the
            camera frame (the AD-NeRF setting: static camera, moving head).
    """

    K: Tensor
    height: int
    width: int
    cam_to_world: Tensor | None = None

    def __post_init__(self) -> None:
        _check_K(self.K)
        if self.cam_to_world is not None:
            _check_pose(self.cam_to_world)

    @property
    def world_to_cam(self) -> Tensor:
        """World-to-camera transform, shape ``(4, 4)``; the rigid inverse of ``cam_to_world``."""
        if self.cam_to_world is None:
            return torch.eye(4, dtype=self.K.dtype, device=self.K.device)
        return HeadPose.from_matrix(self.cam_to_world).inverse().matrix()

    def rays(self) -> RayBundle:
        """Rays through every pixel centre, shape ``(height, width, 3)``."""
        return pixel_rays(self.K, self.height, self.width, self.cam_to_world)

    def rays_at(self, pixels: Tensor) -> RayBundle:
        """Rays through continuous pixel coordinates ``(..., 2)``."""
        return rays_through_pixels(self.K, pixels, self.cam_to_world)

    def to_kornia(self) -> PinholeCamera:
        """The equivalent kornia :class:`PinholeCamera` (batch of one, world-to-camera extrinsics)."""
        K4 = torch.eye(4, dtype=self.K.dtype, device=self.K.device)
        K4[:3, :3] = self.K
        h = torch.tensor([self.height], dtype=self.K.dtype, device=self.K.device)
        w = torch.tensor([self.width], dtype=self.K.dtype, device=self.K.device)
        return PinholeCamera(K4[None], self.world_to_cam.to(self.K)[None], h, w)

    def project(self, points: Tensor) -> Tensor:
        """Project world points ``(..., 3)`` to continuous pixel coordinates ``(..., 2)``.

        Example:
            >>> cam = Camera(intrinsics_matrix(100.0, 100.0, 50.0, 50.0), 100, 100)
            >>> cam.project(torch.tensor([[0.0, 0.0, 2.0], [1.0, -0.5, 2.0]], dtype=torch.float64))
            tensor([[ 50.,  50.],
                    [100.,  25.]], dtype=torch.float64)
        """
        cam = self.world_to_cam.to(points)
        p = torch.einsum("ij,...j->...i", cam[:3, :3], points) + cam[:3, 3]
        flat = p.reshape(-1, 3)
        uv = project_points(flat, self.K.to(points).expand(flat.shape[0], 3, 3))
        return uv.reshape(*points.shape[:-1], 2)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (pixel-centre convention kept)."""
        K = self.K.clone()
        K[:2] = K[:2] * factor
        return Camera(K, round(self.height * factor), round(self.width * factor), self.cam_to_world)
