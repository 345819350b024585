"""Writing solids to files: STL tessellated finely enough for micrometre lens sags, and STEP."""

from __future__ import annotations

from pathlib import Path

import cadquery as cq
from OCP.BRepTools import BRepTools

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


def export_step(part: cq.Workplane, path: Path) -> None:
    """Write ``part`` as STEP (exact B-rep geometry, no tessellation)."""
    cq.exporters.export(part, str(path), exportType="STEP")
