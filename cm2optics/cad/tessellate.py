"""Writing solids to files: STL tessellated finely enough for micrometre lens sags, and STEP;
and the same tessellation in memory with the B-rep face each triangle lies on."""

from __future__ import annotations

from pathlib import Path

import cadquery as cq
import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.BRepTools import BRepTools
from OCP.TopAbs import TopAbs_Orientation
from OCP.TopLoc import TopLoc_Location

#: Angular deflection limit, rad: loose, so the linear tolerance sets the density of curved
#: optical surfaces, yet small holes keep ≥ 21 segments.
ANGULAR_TOLERANCE_RAD = 0.3
#: Default linear (chord) tolerance, µm: lens faces then stay ≈ 0.5 µm RMS from their spheres.
DEFAULT_TOLERANCE_UM = 0.5


def export_stl(shape: cq.Shape, path: Path, tolerance_mm: float) -> None:
    """Write ``shape`` as binary STL with chord deviation ≤ ``tolerance_mm`` (mm)."""
    BRepTools.Clean_s(shape.wrapped)  # drop any coarser triangulation cached on the shape
    cq.exporters.export(
        cq.Workplane().add(shape), str(path), tolerance=tolerance_mm, angularTolerance=ANGULAR_TOLERANCE_RAD
    )


def tessellate_faces(shape: cq.Shape, tolerance_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``shape`` tessellated as :func:`export_stl` does (chord deviation ≤ ``tolerance_mm``, mm),
    face by face. Returns (vertices (V, 3) mm, triangles (F, 3) wound outwards, face_ids (F,):
    the index of the B-rep face each triangle lies on). Vertices on an edge shared by two faces
    appear once per face (merge them to close the mesh)."""
    BRepTools.Clean_s(shape.wrapped)
    BRepMesh_IncrementalMesh(shape.wrapped, tolerance_mm, True, ANGULAR_TOLERANCE_RAD, True)
    vertices, triangles, face_ids = [], [], []
    offset = 0
    for index, face in enumerate(shape.Faces()):
        location = TopLoc_Location()
        poly = BRep_Tool.Triangulation_s(face.wrapped, location)
        if poly is None:
            continue
        transform = location.Transformation()
        nodes = (poly.Node(i).Transformed(transform) for i in range(1, poly.NbNodes() + 1))
        vertices.append(np.array([(p.X(), p.Y(), p.Z()) for p in nodes], dtype=float).reshape(-1, 3))
        corners = [(t.Value(1), t.Value(2), t.Value(3)) for t in poly.Triangles()]
        tri = np.array(corners, dtype=np.int64).reshape(-1, 3) - 1 + offset
        if face.wrapped.Orientation() == TopAbs_Orientation.TopAbs_REVERSED:
            tri = tri[:, [0, 2, 1]]
        triangles.append(tri)
        face_ids.append(np.full(len(tri), index, dtype=np.int64))
        offset += poly.NbNodes()
    if not triangles:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(face_ids)


def export_step(part: cq.Workplane, path: Path) -> None:
    """Write ``part`` as STEP (exact B-rep geometry, no tessellation)."""
    cq.exporters.export(part, str(path), exportType="STEP")
