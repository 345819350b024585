"""The microlens array: square-cell spherical lenslets on one substrate.

Local frame: origin at the centre of the flat (sensor-side) face, +z towards the lenslets,
cells laid out as :meth:`MicrolensArray.lenslet_centres_mm` (x along columns, y along rows).

Each cell is a column ``box(cell) ∩ (slab ∪ ball)`` with the ball of radius ``radius_mm``
centred ``radius_mm`` below the cell's vertex. Neighbouring columns share their planar side
faces exactly (the two spheres cut the shared plane in the same arc), so one fuse gives one
closed solid with creases along the cell borders, as on a real 100 %-fill-factor array;
fusing separate lens caps onto a substrate instead leaves slivers and open seams.
"""

from __future__ import annotations

import math

import cadquery as cq
import numpy as np
import trimesh

from cm2optics.design import MicrolensArray, SystemDesign
from cm2optics.optics.lenslets import LensCell, lens_cells


def land_height_mm(mla: MicrolensArray) -> float:
    """Height of the flat land (or of the lowest crease) below which the array is solid, mm."""
    return mla.thickness_mm - mla.corner_sag_mm


def _cell_column(mla: MicrolensArray, cell: LensCell) -> cq.Solid:
    t, r, half = mla.thickness_mm, mla.radius_mm, mla.aperture_mm / 2
    land = land_height_mm(mla)
    footprint = cq.Solid.makeBox(
        cell.x_max - cell.x_min, cell.y_max - cell.y_min, land, cq.Vector(cell.x_min, cell.y_min, 0)
    )
    lens_x0, lens_x1 = max(cell.x_min, cell.vertex_x - half), min(cell.x_max, cell.vertex_x + half)
    lens_y0, lens_y1 = max(cell.y_min, cell.vertex_y - half), min(cell.y_max, cell.vertex_y + half)
    # The ball covers the whole aperture down to just below the land, where its section is wider.
    margin = 0.05 * mla.corner_sag_mm + 1e-3
    cap_box = cq.Solid.makeBox(
        lens_x1 - lens_x0, lens_y1 - lens_y0, t - land + margin, cq.Vector(lens_x0, lens_y0, land - margin)
    )
    # Poles along x, outside the cap: a pole inside it meshes into degenerate, open triangles.
    centre = cq.Vector(cell.vertex_x, cell.vertex_y, t - r)
    ball = cq.Solid.makeSphere(r, centre, cq.Vector(1, 0, 0), angleDegrees1=-90, angleDegrees2=90)
    cap = cap_box.intersect(ball)
    return footprint.fuse(cap).clean()


def build_mla(design: SystemDesign) -> cq.Workplane:
    """The microlens array of ``design`` as one solid in the MLA's local frame."""
    mla = design.mla
    columns = [_cell_column(mla, cell) for cell in lens_cells(mla)]
    solid = columns[0].fuse(*columns[1:], glue=True).clean() if len(columns) > 1 else columns[0]
    return cq.Workplane().add(_single_solid(solid, "MLA"))


def _single_solid(shape: cq.Shape, name: str) -> cq.Solid:
    solids = shape.Solids()
    if len(solids) != 1 or not solids[0].isValid():
        raise RuntimeError(f"the {name} did not build as one valid solid ({len(solids)} solids)")
    return solids[0]


def lens_surface_height_mm(mla: MicrolensArray, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """Height of the array's top surface at local (x, y), mm (NaN outside the array)."""
    x = np.asarray(x_mm, dtype=float)
    y = np.asarray(y_mm, dtype=float)
    z = np.full(np.broadcast(x, y).shape, np.nan)
    land = land_height_mm(mla)
    half = mla.aperture_mm / 2
    for cell in lens_cells(mla):
        inside = (x >= cell.x_min) & (x <= cell.x_max) & (y >= cell.y_min) & (y <= cell.y_max)
        in_lens = inside & (np.abs(x - cell.vertex_x) <= half) & (np.abs(y - cell.vertex_y) <= half)
        rho2 = (x - cell.vertex_x) ** 2 + (y - cell.vertex_y) ** 2
        sphere = mla.thickness_mm - mla.radius_mm + np.sqrt(np.clip(mla.radius_mm**2 - rho2, 0, None))
        z = np.where(inside, land, z)
        z = np.where(in_lens, np.maximum(sphere, land), z)
    return z


def mla_volume_mm3(mla: MicrolensArray, samples_per_mm: int = 2000) -> float:
    """Volume of the array by midpoint quadrature of its surface height, mm³ (≈ 1e-6 relative)."""
    cells = lens_cells(mla)
    x0, x1 = min(c.x_min for c in cells), max(c.x_max for c in cells)
    y0, y1 = min(c.y_min for c in cells), max(c.y_max for c in cells)
    nx, ny = math.ceil((x1 - x0) * samples_per_mm), math.ceil((y1 - y0) * samples_per_mm)
    xs = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    total = 0.0
    for ys in np.array_split(y0 + (np.arange(ny) + 0.5) * (y1 - y0) / ny, max(1, ny // 256)):
        xx, yy = np.meshgrid(xs, ys)
        total += float(np.nansum(lens_surface_height_mm(mla, xx, yy)))
    return total * (x1 - x0) / nx * (y1 - y0) / ny


def sphere_deviation_um(mla: MicrolensArray, points_mm: np.ndarray) -> np.ndarray:
    """Distance (µm) of local points on the lens surfaces from their cell's design sphere."""
    pts = np.asarray(points_mm, dtype=float)
    dev = np.full(len(pts), np.nan)
    for cell in lens_cells(mla):
        inside = (
            (pts[:, 0] >= cell.x_min)
            & (pts[:, 0] <= cell.x_max)
            & (pts[:, 1] >= cell.y_min)
            & (pts[:, 1] <= cell.y_max)
        )
        centre = np.array([cell.vertex_x, cell.vertex_y, mla.thickness_mm - mla.radius_mm])
        dist = np.abs(np.linalg.norm(pts - centre, axis=1) - mla.radius_mm) * 1000.0
        dev = np.where(inside & np.isnan(dev), dist, dev)
    return dev


def lens_rms_deviation_um(
    design: SystemDesign, mesh: trimesh.Trimesh, samples: int = 100_000, seed: int = 0
) -> dict[str, float]:
    """RMS and maximum distance (µm) of a tessellated MLA's lens faces from the design spheres,
    sampled uniformly over their area (mesh in the MLA's local frame)."""
    lens_faces = np.flatnonzero(mesh.face_normals[:, 2] > 0.2)
    lens = mesh.submesh([lens_faces], append=True)
    points, _ = trimesh.sample.sample_surface(lens, samples, seed=seed)
    deviation = sphere_deviation_um(design.mla, points)
    return {
        "lens_rms_deviation_um": float(np.sqrt(np.mean(deviation**2))),
        "lens_max_deviation_um": float(deviation.max()),
    }
