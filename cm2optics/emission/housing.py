"""The opaque parts around the emission path as a Mitsuba scene: mask and housing bore.

Each opening of :attr:`EmissionOptics.bores` (the mask's opening, the seats, the spacer and the
MLA's corner tabs of the printed MLA housing) becomes a tube of wall quads, one per edge of its
rectangle or octagon, plus a floor and a ceiling: annuli from the opening out to
:data:`OUTER_MM`, so that a ray outside the opening at either end is stopped too. The tracer
(:mod:`.trace`) casts each straight air segment of a ray against this scene with ``scene.ray_test`` (Embree on the CPU, OptiX on CUDA): any hit blocks
the ray. Mitsuba finds surfaces; the optics (refraction, optical path) stays in float64 in
the tracer. The scene is built in memory from a dict, one ``mi.Mesh`` per opening.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from cm2optics.emission.optics import Bore, EmissionOptics
from cm2optics.optics.backend import mitsuba

__all__ = ["OUTER_MM", "bore_mesh", "housing_scene", "segment_test"]

#: Half-width of the annuli that close each opening's floor and ceiling, mm.
OUTER_MM = 20.0


def bore_mesh(bore: Bore, outer_mm: float = OUTER_MM) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (mm) and triangles of one opening: a wall quad per edge of its polygon
    (:meth:`Bore.polygon_mm`), and at each end an annulus from the polygon out to the same polygon
    scaled to reach at least ``outer_mm`` (mm) from the axis."""
    poly = bore.polygon_mm()
    scale = outer_mm / min(bore.half_x_mm, bore.half_y_mm)
    quads = []
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        quads.append([[*a, bore.z0_mm], [*b, bore.z0_mm], [*b, bore.z1_mm], [*a, bore.z1_mm]])
        for z in (bore.z0_mm, bore.z1_mm):
            quads.append([[*a, z], [*b, z], [*(scale * b), z], [*(scale * a), z]])
    vertices = np.asarray(quads, dtype=float).reshape(-1, 3)
    base = 4 * np.arange(len(quads))[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return vertices, faces


def _mesh(mi: Any, name: str, vertices: np.ndarray, faces: np.ndarray) -> Any:
    mesh = mi.Mesh(name, len(vertices), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = type(params["vertex_positions"])(np.ascontiguousarray(vertices, np.float32).ravel())
    params["faces"] = type(params["faces"])(np.ascontiguousarray(faces, np.uint32).ravel())
    params.update()
    return mesh


@lru_cache(maxsize=8)
def housing_scene(optics: EmissionOptics) -> Any:
    """The Mitsuba scene of ``optics``' openings (cached per optics)."""
    mi = mitsuba()
    scene: dict[str, Any] = {"type": "scene"}
    for k, bore in enumerate(optics.bores):
        scene[f"bore_{k}"] = _mesh(mi, bore.name, *bore_mesh(bore))
    return mi.load_dict(scene)


def segment_test(scene: Any):
    """A segment test for :func:`cm2optics.emission.trace._trace` that casts the segment against
    ``scene``: True where nothing lies along it."""
    mi = mitsuba()

    def test(px, py, pz, dx, dy, dz, length, z_low, z_high):
        ray = mi.Ray3f(
            mi.Point3f(mi.Float(px), mi.Float(py), mi.Float(pz)),
            mi.Vector3f(mi.Float(dx), mi.Float(dy), mi.Float(dz)),
        )
        ray.maxt = mi.Float(length) * (1.0 - 1e-6)
        return ~scene.ray_test(ray)

    return test
