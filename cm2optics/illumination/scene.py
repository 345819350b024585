"""The Mitsuba scene of an :class:`~cm2optics.illumination.geometry.IlluminationScene`.

Every part becomes a ``mi.Mesh`` built in memory (no temporary files) and the scene is loaded
from a dict, as Mitsuba's own tests do. Mitsuba is used for what it is best at — finding the
nearest surface along millions of rays (Embree on the CPU, OptiX on CUDA) — and the optics
happen in :mod:`cm2optics.illumination.tracer`. Smooth normals are given per face corner, so
vertices are split per corner; positions stay bit-identical along shared edges, so the
surface stays watertight for the ray tests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cm2optics.illumination.geometry import IlluminationScene, Part
from cm2optics.optics.backend import is_jit, mitsuba

__all__ = ["MitsubaScene", "mitsuba_scene"]


@dataclass(frozen=True, eq=False)
class MitsubaScene:
    """A loaded Mitsuba scene and how to tell its shapes apart inside a kernel.

    scene: the ``mi.Scene``.
    codes_by_id: packed role code (:attr:`Part.code`) of each shape, indexed by the shape's
        registry id as ``dr.reinterpret_array(UInt32, si.shape)`` gives it (JIT variants), or
        a dict ``{shape id string: code}`` (scalar variant).
    """

    scene: Any
    codes_by_id: Any


def _buffer(current: Any, values: np.ndarray) -> Any:
    """Convert ``values`` to the array type of a Mitsuba parameter (JIT or scalar)."""
    return type(current)(values)


def _mesh(mi: Any, part: Part) -> Any:
    smooth = part.corner_normals is not None
    if smooth:
        positions = part.vertices_mm[part.faces].reshape(-1, 3)
        faces = np.arange(positions.shape[0], dtype=np.uint32).reshape(-1, 3)
        normals = part.corner_normals.reshape(-1, 3)
    else:
        positions, faces, normals = part.vertices_mm, part.faces.astype(np.uint32), None
    mesh = mi.Mesh(part.name, len(positions), len(faces), has_vertex_normals=smooth)
    params = mi.traverse(mesh)
    params["vertex_positions"] = _buffer(
        params["vertex_positions"], np.ascontiguousarray(positions, np.float32).ravel()
    )
    params["faces"] = _buffer(params["faces"], np.ascontiguousarray(faces, np.uint32).ravel())
    if smooth:
        params["vertex_normals"] = _buffer(params["vertex_normals"], np.ascontiguousarray(normals, np.float32).ravel())
    params.update()
    return mesh


def mitsuba_scene(scene: IlluminationScene) -> MitsubaScene:
    """Load ``scene`` into Mitsuba (the variant chosen by :mod:`~cm2optics.optics.backend`)."""
    mi = mitsuba()
    spec: dict[str, Any] = {"type": "scene"}
    for part in scene.parts:
        spec[part.name] = _mesh(mi, part)
    loaded = mi.load_dict(spec)
    code = {part.name: part.code for part in scene.parts}
    if is_jit():
        import drjit as dr

        ids = dr.reinterpret_array(mi.UInt32, loaded.shapes_dr()).numpy()
        names = [shape.id() for shape in loaded.shapes()]
        table = np.zeros(int(ids.max()) + 1, dtype=np.uint32)
        table[ids] = [code[name] for name in names]
        return MitsubaScene(loaded, mi.UInt32(table))
    return MitsubaScene(loaded, {shape.id(): code[shape.id()] for shape in loaded.shapes()})
