"""Checks of exported meshes: closed and manifold, true to the solid, thick enough to print.

Pure trimesh/NumPy (no CadQuery), so a user can run them on any STL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass(frozen=True)
class MeshReport:
    """What a mesh is: closed, manifold, its volume (mm³), bounding box (mm), thinnest wall (mm)."""

    watertight: bool
    winding_consistent: bool
    volume_mm3: float
    bbox_mm: tuple[tuple[float, float, float], tuple[float, float, float]]
    min_wall_mm: float
    faces: int


def min_wall_thickness_mm(mesh: trimesh.Trimesh, samples: int = 20000, seed: int = 0) -> float:
    """Thinnest wall of a closed mesh, mm: the shortest inward ray from a surface point to an
    opposing face (normals at least 120° apart, so rays that run into the adjacent face of an
    inner corner don't count). Points: every face centre plus ``samples`` random surface points.
    """
    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mesh, samples, seed=int(rng.integers(2**31)))
    points = np.vstack([mesh.triangles_center, points])
    faces = np.concatenate([np.arange(len(mesh.faces)), faces])
    normals = mesh.face_normals[faces]
    eps = 1e-6 * max(float(mesh.scale), 1.0)
    origins = points - normals * eps
    locations, ray_idx, tri_idx = mesh.ray.intersects_location(origins, -normals, multiple_hits=True)
    if len(ray_idx) == 0:
        return float("nan")
    distance = np.linalg.norm(locations - points[ray_idx], axis=1)
    keep = distance > 10 * eps
    ray_idx, tri_idx, distance = ray_idx[keep], tri_idx[keep], distance[keep]
    # Where each ray leaves the solid: its nearest hit. It bounds a wall if that face opposes.
    order = np.lexsort((distance, ray_idx))
    _, first = np.unique(ray_idx[order], return_index=True)
    first = order[first]
    opposing = np.einsum("ij,ij->i", normals[ray_idx[first]], mesh.face_normals[tri_idx[first]]) < -0.5
    finite = distance[first][opposing]
    return float(finite.min()) if finite.size else float("nan")


def check_mesh(mesh: trimesh.Trimesh, wall_samples: int = 20000) -> MeshReport:
    """Report on a mesh loaded from an STL (vertices merged)."""
    lower, upper = mesh.bounds
    return MeshReport(
        watertight=bool(mesh.is_watertight),
        winding_consistent=bool(mesh.is_winding_consistent),
        volume_mm3=float(mesh.volume),
        bbox_mm=(tuple(float(v) for v in lower), tuple(float(v) for v in upper)),
        min_wall_mm=min_wall_thickness_mm(mesh, wall_samples) if mesh.is_watertight else float("nan"),
        faces=len(mesh.faces),
    )
