"""AD-NeRF dataset conventions: its rays, cast our way after the import's conversion, are the same rays.

AD-NeRF casts the ray of pixel ``(i, j)`` from the camera-to-head matrix ``M`` of an OpenGL camera:
origin ``t_M``, direction ``R_M [(i - cx) / f, -(j - cy) / f, -1]``, both in its head frame (y up,
face towards +z). After :func:`adnerf_pose_to_ours` our camera's ray through the same pixel, moved
into our canonical head space and flipped by ``F = diag(1, -1, -1)`` into AD-NeRF's head frame,
must be that ray: same origin, same direction.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from kornia.geometry.liegroup import So3

from adnerf.cameras import Camera, intrinsics_matrix
from adnerf.pose import HeadPose, directions_to_canonical
from adnerf.preprocess.adnerf_import import adnerf_pose_to_ours, ours_pose_to_adnerf

SHARED_VAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "adnerf_transforms_val.json"
F = np.diag([1.0, -1.0, -1.0])


def _random_transforms(n: int, seed: int = 0) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    R = So3.exp(torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.6).matrix().numpy()
    M = np.tile(np.eye(4), (n, 1, 1))
    M[:, :3, :3] = R
    # Camera in front of the face (+z of AD-NeRF's head frame), about 0.8 units away.
    M[:, :3, 3] = R @ np.array([0.0, 0.0, 0.8]) + torch.randn(n, 3, generator=g, dtype=torch.float64).numpy() * 0.05
    return M


def test_converted_poses_cast_adnerf_rays() -> None:
    f, cx, cy, H, W = 300.0, 63.0, 47.0, 96, 128
    ours_cam = Camera(intrinsics_matrix(f, f, cx + 0.5, cy + 0.5, dtype=torch.float64), H, W)
    rays = ours_cam.rays()
    j, i = np.mgrid[0:H, 0:W].astype(np.float64)
    for M in _random_transforms(5):
        pose = HeadPose.from_matrix(torch.as_tensor(adnerf_pose_to_ours(M)))
        origin = pose.to_canonical(rays.origins).numpy() @ F.T
        direction = directions_to_canonical(rays.directions, pose.R).numpy() @ F.T
        d_ad = np.stack([(i - cx) / f, -(j - cy) / f, -np.ones_like(i)], -1) @ M[:3, :3].T
        d_ad /= np.linalg.norm(d_ad, axis=-1, keepdims=True)
        np.testing.assert_allclose(origin, np.broadcast_to(M[:3, 3], origin.shape), atol=1e-12)
        np.testing.assert_allclose(direction / np.linalg.norm(direction, axis=-1, keepdims=True), d_ad, atol=1e-12)


def test_conversion_round_trips_and_keeps_rotations_proper() -> None:
    M = _random_transforms(64, seed=1)
    P = adnerf_pose_to_ours(M)
    np.testing.assert_allclose(ours_pose_to_adnerf(P), M, atol=1e-13)
    R = P[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-13)
    # The identity camera-to-head at distance d puts our head d in front of the camera, facing it.
    M0 = np.eye(4)
    M0[2, 3] = 0.7
    np.testing.assert_allclose(adnerf_pose_to_ours(M0), np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.7], [0, 0, 0, 1.0]]), atol=1e-15)


@pytest.mark.skipif(not SHARED_VAL.exists(), reason="needs ../shared/data/adnerf_transforms_val.json (development data, not in a user's clone)")
def test_real_adnerf_split_file_puts_the_head_in_its_face_rect(report) -> None:
    doc = json.loads(SHARED_VAL.read_text())
    P = adnerf_pose_to_ours(np.array([fr["transform_matrix"] for fr in doc["frames"]]))
    f, cx, cy = doc["focal_len"], doc["cx"] + 0.5, doc["cy"] + 0.5
    t = P[:, :3, 3]
    u, v = f * t[:, 0] / t[:, 2] + cx, f * t[:, 1] / t[:, 2] + cy
    rect = np.array([fr["face_rect"] for fr in doc["frames"]], dtype=np.float64)
    centre_u, centre_v = rect[:, 0] + rect[:, 2] / 2, rect[:, 1] + rect[:, 3] / 2
    inside = (u > rect[:, 0]) & (u < rect[:, 0] + rect[:, 2]) & (v > rect[:, 1]) & (v < rect[:, 1] + rect[:, 3])
    assert inside.all()
    # The head origin follows the landmark box up and down (a flipped y would anti-correlate).
    corr_v = float(np.corrcoef(v, centre_v)[0, 1])
    corr_u = float(np.corrcoef(u, centre_u)[0, 1])
    assert corr_v > 0.9 and corr_u > 0.5
    # Every face looks towards the camera: canonical -z maps to camera -z.
    assert (P[:, 2, 2] > 0.8).all()
    report(f"AD-NeRF val split ({len(P)} frames): projected head origin inside face_rect 100%, corr with rect centre u {corr_u:.3f} v {corr_v:.3f}")
