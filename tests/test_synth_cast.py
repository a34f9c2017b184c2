"""The synthetic scene's ray cast: three meshes cast in their own frames give what one cast of
the whole scene placed in the camera frame gives."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from adnerf.synth import HeadModel, TorsoModel, _cast, pixel_ray_directions, pose_track, torso_pose


def one_mesh_cast(head: HeadModel, torso: TorsoModel, pose: np.ndarray, opening: float, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reference: the head (jaw opened) and torso moved into the camera frame as one mesh, one cast.

    Returns ``(ray, depth, is_head, head_rest)`` of the rays that hit, in pixel order."""
    dirs = pixel_ray_directions(size)
    head_v = head.vertices(opening) @ pose[:3, :3].T + pose[:3, 3]
    tpose = torso_pose(pose)
    torso_v = np.asarray(torso.mesh.vertices) @ tpose[:3, :3].T + tpose[:3, 3]
    n_head = len(head.faces)
    mesh = trimesh.Trimesh(np.concatenate([head_v, torso_v]), np.concatenate([head.faces, np.asarray(torso.mesh.faces) + len(head_v)]), process=False)
    tri, ray, loc = trimesh.ray.ray_triangle.RayMeshIntersector(mesh).intersects_id(np.zeros_like(dirs), dirs, multiple_hits=False, return_locations=True)
    order = np.argsort(ray)
    tri, ray, loc = tri[order], ray[order], loc[order]
    is_head = tri < n_head
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri[is_head]], loc[is_head])
    rest = np.einsum("nk,nkj->nj", bary, head.rest[head.faces[tri[is_head]]])
    return ray, np.linalg.norm(loc, axis=1), is_head, rest


@pytest.mark.parametrize("frame, opening", [(0, 0.0), (7, 1.0), (13, 0.55)])
def test_cast_in_each_mesh_frame_equals_one_cast_of_the_placed_scene(frame: int, opening: float) -> None:
    size = 40
    head, torso = HeadModel(size), TorsoModel(size)
    pose = pose_track(14, 25.0, 3, max_yaw=25.0)[frame]
    hits = _cast(head, torso, pose, opening, size, None)
    ray, depth, is_head, rest = one_mesh_cast(head, torso, pose, opening, size)
    assert is_head.any() and (~is_head).any() and len(ray) < size * size  # head, torso and background
    np.testing.assert_array_equal(hits.ray, ray)
    np.testing.assert_array_equal(hits.is_head, is_head)
    np.testing.assert_allclose(hits.depth, depth, atol=1e-5)
    np.testing.assert_allclose(hits.head_rest, rest, atol=1e-5)  # each head hit's point on the rest surface, in pixel order

