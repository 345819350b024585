"""The freeform TIR collimator as a solid, and its comparison with a reference part.

Local frame: the LED frame (origin at the centre of the LED's emitting surface, +z the
direction the light leaves in). The section computed by :mod:`cm2optics.optics.collimator` is
revolved about z — the lens and the TIR surface as splines through the computed points with
their end tangents — and fused with the square exit flange.

The lens is revolved from ``r = ε`` and closed by a flat disc of radius ε at its vertex, with
ε chosen so that the flat departs from the hyperbola by ``VERTEX_FLAT_SAG_MM`` (≈ 6 µm radius
for the default design): a curved face revolved from the axis has a pole there, which
OpenCascade tessellates into a degenerate triangle and the exported STL is then not closed.

A freeform lens (``collimator.lens_freeform_um``, :mod:`cm2optics.optics.freeform`) is one smooth
B-spline face: the displaced lens ``z_lens(r) + S(x, y)`` is sampled on a square grid a little
wider than the cavity, approximated by a B-spline surface, extruded downwards into a prism and
cut, inside the cavity's cylinder, from the revolved body with its cavity filled. The cavity
wall stays the cylinder ``r = a`` (the sag of :func:`~cm2optics.optics.freeform.displace_lens`
moves its points along it); the STL, the STEP file and the tracer all carry this solid.

A non-revolved TIR wall (``collimator.tir_cos2``, ``tir_cos4``) is one smooth lofted face through
closed periodic splines at heights of the wall, extruded up into the flange; the cavity (the
revolved lens, or the freeform one) is cut from it.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

import cadquery as cq
import numpy as np
import trimesh
from scipy.interpolate import CubicSpline

from cm2optics.design import Collimator, SystemDesign
from cm2optics.optics.collimator import (
    CollimatorProfile,
    collimator_profile,
    profile_from_parameters,
    tir_wall_scale,
)
from cm2optics.optics.freeform import lens_sag_mm

SPLINE_POINTS = 41
"""Points of the computed curves that each CAD spline passes through."""

VERTEX_FLAT_SAG_MM = 1e-4
"""Largest departure of the lens's vertex flat from the hyperbola, mm (0.1 µm: below any
tessellation or printing tolerance)."""

FREEFORM_GRID_POINTS = 41
"""Points per side of the square grid of the displaced lens that its B-spline face fits."""

FREEFORM_GRID_MARGIN = 1.05
"""Half-width of that grid over the cavity radius: the face overhangs the cavity's cylinder."""

FREEFORM_FIT_TOLERANCE_MM = 1e-5
"""Tolerance of the B-spline fit to the grid points, mm (10 nm)."""

ANAMORPHIC_AZIMUTHS = 96
"""Points per closed section of a non-revolved TIR wall (its periodic spline passes through them)."""


def _spline_points(points: np.ndarray) -> list[tuple[float, float]]:
    """``SPLINE_POINTS`` of a sampled curve (its ends included) as (r, z) tuples."""
    pick = np.unique(np.round(np.linspace(0, len(points) - 1, SPLINE_POINTS)).astype(int))
    return [(float(r), float(z)) for r, z in points[pick]]


def _unit(vector) -> tuple[float, float]:
    vector = np.asarray(vector, dtype=float)
    return tuple(float(v) for v in vector / np.linalg.norm(vector))


def _end_tangents(points: np.ndarray) -> list[tuple[float, float]]:
    """Unit tangents of a densely sampled curve at its two ends (end chords)."""
    return [_unit(points[1] - points[0]), _unit(points[-1] - points[-2])]


def _section(profile: CollimatorProfile, filled: bool = False) -> cq.Workplane:
    """The closed half-section (r ≥ 0) in the XZ plane, ready to revolve about z; ``filled``:
    without the cavity (its floor the entry plane)."""
    tir = np.column_stack([profile.tir_r_mm, profile.tir_z_mm])
    a, g = profile.cavity_radius_mm, profile.entry_z_mm
    r_end, z_end = tir[-1]
    # On "XZ", local (x, y) is global (x, z).
    sketch = cq.Workplane("XZ").moveTo(0.0, profile.exit_z_mm)
    if filled:
        sketch = sketch.lineTo(0.0, g)
    else:
        # Vertex flat of radius ε: sag ε² / (2 R_vertex) = VERTEX_FLAT_SAG_MM.
        flat = np.sqrt(2.0 * profile.lens_vertex_radius_mm * VERTEX_FLAT_SAG_MM)
        keep = profile.lens_r_mm > 2.0 * flat
        lens = np.vstack(
            [[flat, profile.lens_height_mm(flat)], np.column_stack([profile.lens_r_mm[keep], profile.lens_z_mm[keep]])]
        )
        lens_tangents = [_unit((1.0, profile.lens_slope(r))) for r in (lens[0, 0], lens[-1, 0])]
        sketch = (
            sketch.lineTo(0.0, lens[0, 1])
            .lineTo(*lens[0])
            .spline(_spline_points(lens)[1:], tangents=lens_tangents, includeCurrent=True)
            .lineTo(a, g)
        )
    sketch = sketch.lineTo(profile.outer_radius_entry_mm, g)
    if np.hypot(tir[0, 0] - profile.outer_radius_entry_mm, tir[0, 1] - g) > 1e-9:
        sketch = sketch.lineTo(*tir[0])  # the wall's tangent below the mouth ray (none when led_gap_mm = 0)
    sketch = sketch.spline(_spline_points(tir)[1:], tangents=_end_tangents(tir), includeCurrent=True)
    if profile.flange_bottom_z_mm - z_end > 1e-6:
        sketch = sketch.lineTo(r_end, profile.flange_bottom_z_mm)
    return sketch.lineTo(r_end, profile.exit_z_mm).close()


def build_collimator(design: SystemDesign) -> cq.Workplane:
    """One solid in the LED frame: the revolved optical body fused with the square flange,
    its lens one smooth freeform face when the design's lens has a Zernike sag."""
    collimator_profile(design)  # checks the walls against this design's printer
    return _built_collimator(design.collimator, design.led.peak_nm)


@functools.lru_cache(maxsize=8)
def _built_collimator(collimator: Collimator, peak_nm: float) -> cq.Workplane:
    """The solid of ``collimator`` designed at ``peak_nm`` (nm), built once per process: the
    export, the tracer and the reports all ask for it (callers only place or tessellate it,
    never change it)."""
    profile = profile_from_parameters(collimator, peak_nm)
    if collimator.tir_is_freeform:
        body = _anamorphic_body(profile, collimator.tir_cos2, collimator.tir_cos4)
        cavity = (
            _freeform_cavity(profile, collimator.lens_freeform_um)
            if collimator.is_freeform
            else _revolved_cavity(profile)
        )
        return _one_solid(body.cut(cavity).clean())
    if not collimator.is_freeform:
        return _revolved_collimator(profile)
    body = _revolved_collimator(profile, filled=True).val()
    return _one_solid(body.cut(_freeform_cavity(profile, collimator.lens_freeform_um)).clean())


def _anamorphic_body(profile: CollimatorProfile, cos2: float, cos4: float) -> cq.Shape:
    """The optical body without its cavity, its TIR wall not revolved: a smooth loft through
    ``SPLINE_POINTS`` closed periodic splines (``ANAMORPHIC_AZIMUTHS`` points each) at heights of
    the wall, each ``r(φ) = r_e + (r(z) − r_e) · (1 + cos2 cos 2φ + cos4 cos 4φ)`` (mm), the top
    section extruded up into the square flange, fused with it."""
    tir = np.column_stack([profile.tir_r_mm, profile.tir_z_mm])
    pick = np.unique(np.round(np.linspace(0, len(tir) - 1, SPLINE_POINTS)).astype(int))
    phi = 2.0 * np.pi * np.arange(ANAMORPHIC_AZIMUTHS) / ANAMORPHIC_AZIMUTHS
    scale = tir_wall_scale(cos2, cos4, phi)
    entry = profile.outer_radius_entry_mm
    wires = []
    for r, z in tir[pick]:
        radius = entry + (r - entry) * scale
        points = [
            cq.Vector(float(q * np.cos(p)), float(q * np.sin(p)), float(z)) for q, p in zip(radius, phi, strict=True)
        ]
        wires.append(cq.Wire.assembleEdges([cq.Edge.makeSpline(points, periodic=True)]))
    wall = cq.Solid.makeLoft(wires, ruled=False)
    rise = (profile.flange_bottom_z_mm + profile.exit_z_mm) / 2 - float(tir[-1, 1])
    step = cq.Solid.extrudeLinear(cq.Face.makeFromWires(wires[-1]), cq.Vector(0.0, 0.0, rise))
    side = profile.footprint_mm
    flange = cq.Solid.makeBox(
        side,
        side,
        profile.exit_z_mm - profile.flange_bottom_z_mm,
        cq.Vector(-side / 2, -side / 2, profile.flange_bottom_z_mm),
    )
    return _one_solid(wall.fuse(step, flange).clean()).val()


def _revolved_cavity(profile: CollimatorProfile) -> cq.Solid:
    """The cavity of the revolved lens as a solid: the lens (vertex flat, spline) over the cylinder
    ``r = a``, from 0.5 mm below the entry plane (LED frame, mm)."""
    a, g = profile.cavity_radius_mm, profile.entry_z_mm
    flat = np.sqrt(2.0 * profile.lens_vertex_radius_mm * VERTEX_FLAT_SAG_MM)
    keep = profile.lens_r_mm > 2.0 * flat
    lens = np.vstack(
        [[flat, profile.lens_height_mm(flat)], np.column_stack([profile.lens_r_mm[keep], profile.lens_z_mm[keep]])]
    )[::-1]
    tangents = [_unit((-1.0, -profile.lens_slope(r))) for r in (lens[0, 0], lens[-1, 0])]
    sketch = (
        cq.Workplane("XZ")
        .moveTo(0.0, g - 0.5)
        .lineTo(a, g - 0.5)
        .lineTo(*lens[0])
        .spline(_spline_points(lens)[1:], tangents=tangents, includeCurrent=True)
        .lineTo(0.0, lens[-1, 1])
        .close()
    )
    return sketch.revolve(360.0, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)).val()


def _revolved_collimator(profile: CollimatorProfile, filled: bool = False) -> cq.Workplane:
    """The revolved optical body fused with the square flange (LED frame); ``filled``: without
    its cavity."""
    body = _section(profile, filled).revolve(360.0, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    side = profile.footprint_mm
    flange = (
        cq.Workplane("XY")
        .workplane(offset=profile.flange_bottom_z_mm)
        .rect(side, side)
        .extrude(profile.exit_z_mm - profile.flange_bottom_z_mm)
    )
    return _one_solid(body.union(flange, clean=True).val())


def _one_solid(shape: cq.Shape) -> cq.Workplane:
    """``shape`` as a workplane holding its single solid; raises when it is not one solid."""
    solids = shape.Solids()
    if len(solids) != 1 or not solids[0].isValid():
        raise RuntimeError(f"the collimator must be one valid solid, got {len(solids)} solid(s)")
    return cq.Workplane("XY").add(solids[0])


def _freeform_lens_height(profile: CollimatorProfile, coefficients_um: tuple[float, ...]):
    """``z(x, y) = z_lens(r) + S(x, y)`` (mm) of the lens of ``profile`` with the Zernike sag
    of ``coefficients_um`` (µm): ``z_lens`` a cubic spline through the profile's lens points
    (mirrored about the axis), both continued smoothly past the cavity's rim."""
    r = np.concatenate([-profile.lens_r_mm[:0:-1], profile.lens_r_mm])
    z = np.concatenate([profile.lens_z_mm[:0:-1], profile.lens_z_mm])
    lens = CubicSpline(r, z, extrapolate=True)

    def height(x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        sag = lens_sag_mm(coefficients_um, x_mm, y_mm, profile.cavity_radius_mm, clip=False)
        return lens(np.hypot(x_mm, y_mm)) + sag

    return height


def _freeform_cavity(profile: CollimatorProfile, coefficients_um: tuple[float, ...]) -> cq.Solid:
    """The cavity under the freeform lens: the cylinder ``r = a`` from below the entry plane,
    capped by the B-spline face through the displaced lens (fit to ``FREEFORM_FIT_TOLERANCE_MM``
    on a ``FREEFORM_GRID_POINTS``² grid)."""
    a, g = profile.cavity_radius_mm, profile.entry_z_mm
    half = FREEFORM_GRID_MARGIN * a
    x, y = np.meshgrid(*2 * [np.linspace(-half, half, FREEFORM_GRID_POINTS)], indexing="ij")
    z = _freeform_lens_height(profile, coefficients_um)(x, y)
    if z.min() <= g or z.max() >= profile.exit_z_mm:
        raise RuntimeError("the freeform lens leaves the collimator's body: smaller Zernike terms are needed")
    grid = [[cq.Vector(*map(float, p)) for p in zip(*row, strict=True)] for row in zip(x, y, z, strict=True)]
    face = cq.Face.makeSplineApprox(grid, tol=FREEFORM_FIT_TOLERANCE_MM, minDeg=3, maxDeg=5)
    depth = z.max() - g + 1.0  # the prism's floor lies below the cylinder's
    prism = cq.Solid.extrudeLinear(face, cq.Vector(0.0, 0.0, -depth))
    cylinder = cq.Solid.makeCylinder(a, z.max() - g + 1.0, cq.Vector(0.0, 0.0, g - 0.5))
    return cylinder.intersect(prism)


def _mesh_summary(mesh: trimesh.Trimesh, light_axis: np.ndarray) -> dict[str, object]:
    """Extents, volume (mm³), exit face, cavity and outer-surface radii (over sections at
    5–95 % of the height) and the lens vertex's depth below the cavity mouth (mm) of a
    collimator mesh whose light leaves along ``light_axis`` (a unit vector along ±z)."""
    lower, upper = mesh.bounds
    height = float(upper[2] - lower[2])
    centre = (lower[:2] + upper[:2]) / 2
    # Exit face: triangles facing the light direction in the extreme plane along it.
    along = mesh.triangles_center @ light_axis
    exit_faces = (mesh.face_normals @ light_axis > 0.999) & (along > along.max() - 1e-3)
    exit_vertices = mesh.triangles[exit_faces].reshape(-1, 3)
    exit_side = exit_vertices[:, :2].max(axis=0) - exit_vertices[:, :2].min(axis=0)
    # Radii of the round axis-centred loops of sections across the height; the outer surface
    # only where no other axis-centred loop (a square plate) encloses the section.
    entry_z = upper[2] if light_axis[2] < 0 else lower[2]
    outer, cavity = [], None
    for fraction in np.linspace(0.05, 0.95, 19):
        z = entry_z + light_axis[2] * fraction * height
        section = mesh.section(plane_origin=[centre[0], centre[1], z], plane_normal=[0, 0, 1])
        if section is None:
            continue
        round_radii, plate = [], False
        for loop in section.discrete:
            offset = loop[:, :2] - centre
            rho = np.hypot(offset[:, 0], offset[:, 1])
            turns = np.sum(np.diff(np.unwrap(np.arctan2(offset[:, 1], offset[:, 0])))) / (2 * np.pi)
            if abs(turns) < 0.5:
                continue  # does not go round the axis (a post, a rib)
            if rho.max() - rho.min() < 0.05 * rho.max():
                round_radii.append(float(rho.mean()))
            else:
                plate = True
        if cavity is None and len(round_radii) + plate > 1:
            cavity = min(round_radii)
        if round_radii and not plate:
            outer.append(max(round_radii))
    # Lens vertex: first face met going along the axis from the cavity mouth.
    start = np.array([centre[0], centre[1], entry_z]) - 1e-3 * light_axis
    hits, _, _ = mesh.ray.intersects_location([start], [light_axis])
    depth = float(np.min((hits - start) @ light_axis) - 1e-3) if len(hits) else None
    return {
        "extent_mm": [round(float(v), 4) for v in upper - lower],
        "volume_mm3": round(float(mesh.volume), 4),
        "height_mm": round(height, 4),
        "exit_face_side_mm": [round(float(v), 4) for v in exit_side],
        "exit_face_area_mm2": round(float(mesh.area_faces[exit_faces].sum()), 4),
        "cavity_radius_mm": None if cavity is None else round(cavity, 4),
        "lens_vertex_depth_mm": None if depth is None else round(depth, 4),
        "outer_radius_range_mm": [round(min(outer), 4), round(max(outer), 4)] if outer else None,
        "watertight": bool(mesh.is_watertight),
    }


def compare_with_reference(
    design: SystemDesign, stl_path: str | Path, reference_light_axis: str = "-z"
) -> dict[str, object]:
    """This design's collimator and a reference part (an STL in mm), measured the same way
    from their meshes and reported side by side: ``{quantity: {"ours": …, "reference": …}}``.

    stl_path: the reference part's STL, mm.
    reference_light_axis: the direction light leaves the reference part in, "+z" or "-z"
        (the CM² authors' part: "-z", its LED at the cavity mouth at z = +1 mm).
    """
    if reference_light_axis not in ("+z", "-z"):
        raise ValueError(f"reference_light_axis = {reference_light_axis!r}: must be '+z' or '-z'")
    path = Path(stl_path)
    if not path.is_file():
        raise FileNotFoundError(f"reference STL not found: {path}")
    reference = trimesh.load_mesh(path)
    with tempfile.TemporaryDirectory() as folder:
        ours_path = Path(folder) / "collimator.stl"
        cq.exporters.export(build_collimator(design), str(ours_path), tolerance=0.002, angularTolerance=0.05)
        ours = trimesh.load_mesh(ours_path)
    ours_summary = _mesh_summary(ours, np.array([0.0, 0.0, 1.0]))
    reference_summary = _mesh_summary(reference, np.array([0.0, 0.0, 1.0 if reference_light_axis == "+z" else -1.0]))
    return {key: {"ours": ours_summary[key], "reference": reference_summary[key]} for key in ours_summary}
