"""Cameras: every sample on a pixel's ray reprojects to that pixel's centre (through kornia)."""

from __future__ import annotations

import pytest
import torch
from kornia.geometry.camera import project_points
from kornia.geometry.liegroup import Se3, So3

from adnerf.cameras import Camera, intrinsics_matrix, pixel_rays, rays_through_pixels

H, W = 7, 9


def _K(dtype: torch.dtype) -> torch.Tensor:
    # Non-square pixels and an off-centre principal point catch swapped axes.
    return intrinsics_matrix(31.0, 27.0, 4.1, 3.3, dtype=dtype)


def _centres(dtype: torch.dtype) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype) + 0.5, torch.arange(W, dtype=dtype) + 0.5, indexing="ij")
    return torch.stack([u, v], dim=-1)


def test_samples_reproject_to_pixel_centres(dtype: torch.dtype, tol: dict) -> None:
    rays = pixel_rays(_K(dtype), H, W)
    assert rays.origins.shape == (H, W, 3) and rays.directions.shape == (H, W, 3)
    t = torch.tensor([0.1, 1.0, 7.5, 300.0], dtype=dtype).expand(H, W, 4)
    points = rays.at(t)  # (H, W, 4, 3)
    uv = project_points(points.reshape(-1, 3), _K(dtype).expand(H * W * 4, 3, 3)).reshape(H, W, 4, 2)
    expected = _centres(dtype)[:, :, None, :].expand_as(uv)
    torch.testing.assert_close(uv, expected, rtol=tol["rtol"], atol=1e-4 if dtype == torch.float32 else 1e-10)


def test_directions_are_unit_and_t_is_euclidean(dtype: torch.dtype, tol: dict) -> None:
    rays = pixel_rays(_K(dtype), H, W)
    torch.testing.assert_close(torch.linalg.vector_norm(rays.directions, dim=-1), torch.ones(H, W, dtype=dtype), **tol)
    t = torch.full((H, W, 1), 2.5, dtype=dtype)
    p = rays.at(t)[..., 0, :]
    # camera-space z of a sample equals t times the ray's z component ...
    torch.testing.assert_close(p[..., 2], 2.5 * rays.directions[..., 2], **tol)
    # ... and its distance from the origin is t.
    torch.testing.assert_close(torch.linalg.vector_norm(p, dim=-1), torch.full((H, W), 2.5, dtype=dtype), **tol)


def test_pixel_grid_orientation() -> None:
    rays = pixel_rays(_K(torch.float64), H, W)
    d = rays.directions
    # x grows to the right (columns), y grows downwards (rows), everything looks along +z.
    assert (d[:, 1:, 0] > d[:, :-1, 0]).all()
    assert (d[1:, :, 1] > d[:-1, :, 1]).all()
    assert (d[..., 2] > 0).all()
    # The ray through the principal point is the optical axis.
    axis = rays_through_pixels(_K(torch.float64), torch.tensor([4.1, 3.3], dtype=torch.float64))
    torch.testing.assert_close(axis.directions, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def _random_c2w(dtype: torch.dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    pose = Se3(So3.exp(torch.randn(3, generator=g, dtype=torch.float64)), torch.randn(3, generator=g, dtype=torch.float64) * 2)
    return pose.matrix().to(dtype)


def test_cam_to_world_rays_are_world_transform_of_camera_rays(dtype: torch.dtype, tol: dict) -> None:
    c2w = _random_c2w(dtype)
    cam = pixel_rays(_K(dtype), H, W)
    world = pixel_rays(_K(dtype), H, W, c2w)
    torch.testing.assert_close(world.origins, c2w[:3, 3].expand(H, W, 3), **tol)
    torch.testing.assert_close(world.directions, cam.directions @ c2w[:3, :3].T, **tol)
    # Independent path: kornia's PinholeCamera (world-to-camera extrinsics) projects world
    # samples back to the pixel centres.
    camera = Camera(_K(dtype), H, W, c2w)
    pts = world.at(torch.full((H, W, 2), 3.0, dtype=dtype).cumsum(-1))
    uv = camera.to_kornia().project(pts.reshape(1, -1, 3)).reshape(H, W, 2, 2)
    torch.testing.assert_close(uv, _centres(dtype)[:, :, None].expand_as(uv), rtol=1e-4, atol=2e-4 if dtype == torch.float32 else 1e-9)
    torch.testing.assert_close(camera.project(pts), uv, rtol=1e-4, atol=2e-4 if dtype == torch.float32 else 1e-9)


def test_scaled_camera_keeps_pixel_centre_convention() -> None:
    K = intrinsics_matrix(50.0, 50.0, 16.0, 16.0)
    cam = Camera(K, 32, 32)
    small = cam.scaled(0.5)
    assert (small.height, small.width) == (16, 16)
    # The centre of the image is the same ray at both sizes.
    a = cam.rays_at(torch.tensor([16.0, 16.0], dtype=torch.float64)).directions
    b = small.rays_at(torch.tensor([8.0, 8.0], dtype=torch.float64)).directions
    torch.testing.assert_close(a, b)


@pytest.mark.parametrize("shape", [(3, 4), (4,), (2, 3, 3)])
def test_bad_intrinsics_are_rejected(shape: tuple) -> None:
    with pytest.raises(ValueError, match="K"):
        pixel_rays(torch.zeros(shape, dtype=torch.float64), 4, 4)


def test_bad_image_size_is_rejected() -> None:
    with pytest.raises(ValueError, match="size"):
        pixel_rays(torch.eye(3, dtype=torch.float64), 0, 4)
