"""The illumination scene as triangle meshes with optical roles, in the device frame (mm).

Pure NumPy/trimesh: the Mitsuba tracer (:mod:`cm2optics.illumination.scene`) and the NumPy
reference tracer (:mod:`cm2optics.illumination.reference_numpy`) both read these parts.

One LED unit, in its LED frame (:mod:`cm2optics.optics.layout`; ``z`` along the unit's axis), with
``g = led_array.excitation_gap_mm``, ``t`` the filter's thickness, ``c = mechanics.clearance_mm``:

==================  =========================================================================
LED                 the emitter at ``z = 0`` (:mod:`cm2optics.illumination.source`)
LED board           absorbing plane at ``z = −0.01`` across the housing's bore (the LED
                    package's own reflectance is ignored: a conservative choice)
collimator          a closed mesh (CAD part or STL), dielectric, smooth vertex normals within
                    each face of the CAD solid (an STL: creased above :data:`CREASE_DEG`)
excitation filter   a ``width × length × t`` plate at ``g ≤ z ≤ g + t``: the face towards the
                    LED carries the coating, the other is bare glass, the edges absorb; where
                    it rests on the collimator's exit face (``g`` = exit height) it is lifted
                    by a 10-µm air film (:data:`CONTACT_GAP_MM`)
portal              without a filter only: a plane at ``z = g + t + c/2`` across the bore (or
                    20 × 20 mm without housing), not a surface but a tally: rays crossing it
                    outwards have left the unit. With the filter, rays leaving the filter's
                    back face into the air are the ones that "passed the filter".
housing             absorbing square tube: the bore (filter + c on each side) from the LED
                    board to a front lip ``led_housing.lip_mm`` wide and
                    ``mechanics.min_wall_mm`` thick at ``z = g + t + c``, whose opening is the
                    clear aperture; outer walls ``led_housing.outer_mm``. Without a
                    collimator (V1) the tube below the filter seat narrows to the aperture,
                    as in the CAD housing.
==================  =========================================================================

Around the units: the MLA housing (an absorbing tower of the envelope of
:func:`cm2optics.optics.layout.mla_housing_envelope`, its top standing for the emission filter that
light must not enter, on a flange plane) and the sample plane ``z = object_plane_z_mm``
(a perfect absorber that records where each ray lands).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import numpy as np
import trimesh

from cm2optics.design import SystemDesign
from cm2optics.design.materials import Material, refractive_index
from cm2optics.optics import first_order
from cm2optics.optics.layout import led_poses, mla_housing_envelope

__all__ = [
    "Absorber",
    "CollimatorMesh",
    "IlluminationScene",
    "Medium",
    "Part",
    "Role",
    "build_scene",
    "collimator_from_design",
    "collimator_from_solid",
    "collimator_from_stl",
    "corner_normals",
]

#: Crease angle of the smooth normals of a mesh without B-rep faces (an STL): neighbouring
#: triangles meeting at a sharper angle keep a crease between them, degrees.
CREASE_DEG = 30.0
#: Half-side of the square sample plane, mm; rays landing beyond it "left the scene".
SAMPLE_HALF_MM = 25.0
#: The LED board's plane behind the emitting surface (LED frame), mm.
BOARD_Z_MM = -0.01
#: Air film between a collimator's exit face and a filter resting on it, mm: two flat faces in
#: contact are not optically bonded, and the film keeps the two surfaces apart for the tracer.
CONTACT_GAP_MM = 0.01
#: CAD tessellation of the design's collimator: chord tolerance, mm.
CAD_TOLERANCE_MM = 0.0005


class Role(IntEnum):
    """What a surface does to a ray."""

    DIELECTRIC = 1  # interface of a closed dielectric solid with air: Fresnel + Snell + TIR
    COATED = 2  # filter face with the coating: transmits T(λ, θ), reflects 1 − T
    GLASS = 3  # filter's bare face: Snell + TIR, no Fresnel loss (T includes it)
    ABSORBER = 4  # stops the ray, counted by its Absorber group
    SAMPLE = 5  # the sample plane: stops the ray, records where it landed
    PORTAL = 6  # invisible tally plane at each unit's exit


class Medium(IntEnum):
    """Which refractive index n(λ) a dielectric surface borders."""

    COLLIMATOR = 0
    FILTER = 1


class Absorber(IntEnum):
    """Ledger groups of absorbed power."""

    HOUSING = 0
    LED_BOARD = 1
    FILTER_EDGE = 2
    IMAGING_TOWER = 3


@dataclass(frozen=True, eq=False)
class Part:
    """One surface mesh of the scene in the device frame.

    name: unique name (also the Mitsuba shape id).
    vertices_mm: (V, 3) vertex positions, mm.
    faces: (F, 3) vertex indices; for closed dielectric solids counter-clockwise seen from
        outside (outward normals).
    role, medium, absorber: the optical role and, where it applies, the index or ledger group.
    unit: LED unit the part belongs to (−1: shared).
    corner_normals: (F, 3, 3) smooth normals at each face corner (outward), or None (flat).
    """

    name: str
    vertices_mm: np.ndarray
    faces: np.ndarray
    role: Role
    medium: Medium = Medium.COLLIMATOR
    absorber: Absorber = Absorber.HOUSING
    unit: int = -1
    corner_normals: np.ndarray | None = None

    @property
    def code(self) -> int:
        """Role, medium and absorber group packed as the kernel reads them."""
        return int(self.role) | (int(self.medium) << 4) | (int(self.absorber) << 8)


@dataclass(frozen=True, eq=False)
class CollimatorMesh:
    """A collimator as a closed mesh in the LED frame (mm, LED at the origin, light along +z).

    label: short name for tables (``cm2-v2 (CAD)``, an STL's file name).
    mesh: the watertight solid with outward normals.
    material: its material (sets n(λ)).
    face_ids: (F,) the smooth surface (B-rep face of the CAD solid) each triangle lies on: the
        smooth normals crease exactly along the solid's edges; None (an STL): creased by angle.
    """

    label: str
    mesh: trimesh.Trimesh
    material: Material
    face_ids: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class IlluminationScene:
    """Everything the tracers need: the parts, the units' poses and the optics' materials.

    design: the system design.
    label: short name of the configuration.
    parts: the surfaces (device frame).
    poses: (count, 4, 4) LED frame → device frame of each unit.
    collimator: the collimator (None: a bare LED, V1).
    has_filter: whether the excitation filter is in place.
    has_housing: whether the housings and the imaging tower absorb.
    filter_material: substrate of the excitation filter.
    portal_z_mm: height of the tally plane in the LED frame, mm.
    notes: remarks on how the scene departs from the design (e.g. an air film added).
    index_override: optional ``{Medium: n(wavelength_nm)}`` replacing the materials' indices
        (tests use a constant n = 1.5).
    led_flux: per unit its radiant flux relative to the LED's (empty: all 1; a design's
        ``illumination_as_built.led_flux``, :mod:`cm2optics.illumination.as_built`).
    """

    design: SystemDesign
    label: str
    parts: tuple[Part, ...]
    poses: np.ndarray
    collimator: CollimatorMesh | None
    has_filter: bool
    has_housing: bool
    filter_material: Material
    portal_z_mm: float
    notes: tuple[str, ...] = field(default=())
    index_override: dict[Medium, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)
    led_flux: tuple[float, ...] = ()

    def refractive_indices(self, wavelength_nm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-ray refractive indices (collimator material, filter substrate) at ``wavelength_nm`` (nm)."""
        wl = np.asarray(wavelength_nm, dtype=float)
        if Medium.COLLIMATOR in self.index_override:
            n_coll = np.broadcast_to(self.index_override[Medium.COLLIMATOR](wl), wl.shape).astype(float)
        elif self.collimator is not None:
            n_coll = np.asarray(refractive_index(self.collimator.material, wl), dtype=float)
        else:
            n_coll = np.ones_like(wl)
        if Medium.FILTER in self.index_override:
            n_filt = np.broadcast_to(self.index_override[Medium.FILTER](wl), wl.shape).astype(float)
        else:
            n_filt = np.asarray(refractive_index(self.filter_material, wl), dtype=float)
        return n_coll, n_filt

    @property
    def units(self) -> int:
        return len(self.poses)

    @property
    def sample_z_mm(self) -> float:
        return float(first_order.object_plane_z_mm(self.design))

    @property
    def field_radius_mm(self) -> float:
        return float(self.design.volume.field_mm / 2)

    @property
    def unit_flux(self) -> np.ndarray:
        """(count,) each unit's radiant flux relative to the LED's."""
        return np.asarray(self.led_flux, dtype=float) if self.led_flux else np.ones(self.units)

    @property
    def unit_axes(self) -> np.ndarray:
        """(count, 3) unit axes in the device frame."""
        return self.poses[:, :3, 2].copy()


# ----------------------------------------------------------------------------- smooth normals


def corner_normals(
    vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray | None = None, crease_deg: float = CREASE_DEG
) -> np.ndarray:
    """Smooth normals at each face corner: the area-weighted mean of the normals of the faces
    around that vertex on the same smooth surface: with ``face_ids`` ((F,), e.g. the B-rep face
    of each triangle) those with the same id, without them those meeting the face at less
    than ``crease_deg`` (degrees). Returns (F, 3, 3) unit vectors along the faces' winding normals."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 × area
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    unit = np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)
    cos_crease = math.cos(math.radians(crease_deg))
    corner_v = faces.ravel()
    corner_f = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(corner_v, kind="stable")
    sorted_v = corner_v[order]
    starts = np.flatnonzero(np.r_[True, sorted_v[1:] != sorted_v[:-1]])
    counts = np.diff(np.r_[starts, len(sorted_v)])
    result = np.zeros((len(corner_v), 3))
    for valence in np.unique(counts):
        group = starts[counts == valence]
        idx = group[:, None] + np.arange(valence)[None, :]  # (n, k) positions in sorted order
        corners = order[idx]  # corner ids
        fids = corner_f[corners]  # (n, k) faces around each vertex
        if face_ids is None:
            n = unit[fids]  # (n, k, 3)
            agree = np.einsum("nid,njd->nij", n, n) >= cos_crease  # (n, k, k)
        else:
            surface = face_ids[fids]
            agree = surface[:, :, None] == surface[:, None, :]
        summed = np.einsum("nij,njd->nid", agree.astype(float), cross[fids])
        result[corners.ravel()] = summed.reshape(-1, 3)
    result /= np.maximum(np.linalg.norm(result, axis=1, keepdims=True), 1e-300)
    bad = ~np.isfinite(result).all(axis=1) | (np.einsum("ij,ij->i", result, unit[corner_f]) <= 0.0)
    result[bad] = unit[corner_f][bad]
    return result.reshape(len(faces), 3, 3)


# ----------------------------------------------------------------------------- collimators


def _rotation_to_z(axis: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector ``axis`` to +z (180° about x for −z)."""
    a = axis / np.linalg.norm(axis)
    z = np.array([0.0, 0.0, 1.0])
    c = float(a @ z)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(a, z)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def _check_solid(mesh: trimesh.Trimesh, what: str) -> trimesh.Trimesh:
    if len(mesh.faces) == 0:
        raise ValueError(f"{what}: the mesh is empty (no triangles)")
    if not mesh.is_watertight:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise ValueError(
            f"{what}: the mesh is not watertight ({open_edges} open edges): a collimator must be a closed solid"
        )
    if not mesh.is_winding_consistent:
        raise ValueError(f"{what}: the mesh's triangles are not consistently wound (inside and outside undefined)")
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def collimator_from_stl(
    path: str | Path, led_position_mm: np.ndarray, led_axis: np.ndarray, material: Material, label: str | None = None
) -> CollimatorMesh:
    """Load a collimator STL (mm) and place it in the LED frame.

    led_position_mm: where the centre of the LED's emitting surface sits, in the STL's frame, mm.
    led_axis: the direction the LED emits in, in the STL's frame (any length ≠ 0).
    material: the part's material (sets n(λ)).
    The part is moved so that the LED is at the origin and rotated by the smallest rotation
    that takes ``led_axis`` to +z. Raises ValueError for an empty or open mesh.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"collimator STL not found: {path}")
    axis = np.asarray(led_axis, dtype=float)
    if not (np.all(np.isfinite(axis)) and np.linalg.norm(axis) > 0):
        raise ValueError(f"--led-axis = {led_axis}: must be a non-zero direction")
    try:
        mesh = trimesh.load_mesh(path, force="mesh")
    except Exception as error:  # noqa: BLE001 - any parser failure is a bad file
        raise ValueError(f"{path}: not a readable mesh ({error})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{path}: the mesh is empty (no triangles)")
    mesh = _check_solid(mesh, str(path))
    rotation = _rotation_to_z(axis)
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = -rotation @ np.asarray(led_position_mm, dtype=float)
    mesh = mesh.copy()
    mesh.apply_transform(matrix)
    return CollimatorMesh(label or path.name, mesh, Material(material))


def collimator_from_solid(
    solid: object, label: str, material: Material, tolerance_mm: float = CAD_TOLERANCE_MM
) -> CollimatorMesh:
    """A CadQuery solid (LED frame, mm) tessellated with chord tolerance ``tolerance_mm`` (mm),
    each triangle tagged with its B-rep face (:attr:`CollimatorMesh.face_ids`)."""
    from cm2optics.cad.tessellate import tessellate_faces

    vertices, faces, face_ids = tessellate_faces(solid, tolerance_mm)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.merge_vertices()  # the faces' copies of their shared edges' nodes; keeps the face order
    merged = np.asarray(mesh.faces)
    # Triangles collapsed onto a pole (e.g. a cone's apex, meshed once per seam node).
    keep = (merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2]) & (merged[:, 2] != merged[:, 0])
    mesh = _check_solid(trimesh.Trimesh(mesh.vertices, merged[keep], process=False), label)
    return CollimatorMesh(label, mesh, Material(material), face_ids[keep])


def collimator_from_design(design: SystemDesign, tolerance_mm: float = CAD_TOLERANCE_MM) -> CollimatorMesh:
    """The design's collimator: the CAD solid (:func:`cm2optics.cad.collimator.build_collimator`)
    tessellated with chord tolerance ``tolerance_mm`` (mm), its faces kept for the normals."""
    from cm2optics.cad.collimator import build_collimator

    if design.collimator is None:
        raise ValueError(f"design {design.name!r} has no collimator")
    solid = build_collimator(design)
    return collimator_from_solid(solid.val(), f"{design.name} (CAD)", design.collimator.material, tolerance_mm)


# ----------------------------------------------------------------------------- simple quads


def _quads(quads: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Quads (4 corners each, in order) → vertices and two triangles per quad."""
    vertices = np.concatenate(quads).reshape(-1, 3)
    base = 4 * np.arange(len(quads))[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return vertices, faces


def _rect(x0: float, x1: float, y0: float, y1: float, z: float) -> np.ndarray:
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])


def _frame(ix: float, iy: float, ox: float, oy: float, z: float) -> list[np.ndarray]:
    """A square annulus at height z between half-widths (ix, iy) and (ox, oy)."""
    return [
        _rect(-ox, ox, iy, oy, z),
        _rect(-ox, ox, -oy, -iy, z),
        _rect(ix, ox, -iy, iy, z),
        _rect(-ox, -ix, -iy, iy, z),
    ]


def _walls(hx: float, hy: float, z0: float, z1: float) -> list[np.ndarray]:
    """The four side walls of a square tube of half-widths (hx, hy) from z0 to z1."""
    return [
        np.array([[-hx, -hy, z0], [hx, -hy, z0], [hx, -hy, z1], [-hx, -hy, z1]]),
        np.array([[-hx, hy, z0], [hx, hy, z0], [hx, hy, z1], [-hx, hy, z1]]),
        np.array([[hx, -hy, z0], [hx, hy, z0], [hx, hy, z1], [hx, -hy, z1]]),
        np.array([[-hx, -hy, z0], [-hx, hy, z0], [-hx, hy, z1], [-hx, -hy, z1]]),
    ]


def _box(hx: float, hy: float, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed box with outward normals (faces wound counter-clockwise from outside)."""
    box = trimesh.creation.box(extents=[2 * hx, 2 * hy, z1 - z0])
    box.apply_translation([0.0, 0.0, (z0 + z1) / 2])
    return np.asarray(box.vertices), np.asarray(box.faces)


def _place(matrix: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    return vertices @ matrix[:3, :3].T + matrix[:3, 3]


# ----------------------------------------------------------------------------- the scene


@dataclass(frozen=True)
class _UnitLayout:
    """Dimensions of one unit in its LED frame (mm)."""

    filter_z0: float
    filter_z1: float
    bore_x: float
    bore_y: float
    tube_x: float
    tube_y: float
    seat_z: float
    lip_z0: float
    lip_z1: float
    aperture_x: float
    aperture_y: float
    outer: float
    back_z: float


def _unit_layout(design: SystemDesign, collimator: CollimatorMesh | None) -> _UnitLayout:
    f, c = design.excitation_filter, design.mechanics.clearance_mm
    z0 = design.led_array.excitation_gap_mm
    if collimator is not None:
        top = float(collimator.mesh.bounds[1, 2])
        if z0 - CONTACT_GAP_MM < top <= z0 + 1e-3:  # resting on the exit face
            z0 = top + CONTACT_GAP_MM
    z1 = z0 + f.thickness_mm
    ax, ay = f.width_mm / 2 - design.led_housing.lip_mm, f.length_mm / 2 - design.led_housing.lip_mm
    bx, by = f.width_mm / 2 + c, f.length_mm / 2 + c
    tube_x, tube_y = (bx, by) if collimator is not None else (ax, ay)
    lip0 = z1 + c
    return _UnitLayout(
        filter_z0=z0,
        filter_z1=z1,
        bore_x=bx,
        bore_y=by,
        tube_x=tube_x,
        tube_y=tube_y,
        seat_z=z0 - c,
        lip_z0=lip0,
        lip_z1=lip0 + design.mechanics.min_wall_mm,
        aperture_x=ax,
        aperture_y=ay,
        outer=design.led_housing.outer_mm / 2,
        back_z=-(design.led.package_height_mm + design.led_housing.back_mm),
    )


def _check_fit(collimator: CollimatorMesh, lay: _UnitLayout, design: SystemDesign, has_filter: bool) -> None:
    mesh = collimator.mesh
    (xmin, ymin, zmin), (xmax, ymax, zmax) = mesh.bounds
    what = f"collimator {collimator.label}"
    half = design.led.emitter_mm / 2
    grid = np.linspace(-half, half, 7)
    points = np.array([[x, y, 1e-3] for x in grid for y in grid])
    inside = mesh.contains(points)
    if inside.any():
        raise ValueError(
            f"the LED sits inside {what}: {int(inside.sum())} of {len(points)} points of its emitting surface "
            "lie within the solid (check --led-position/--led-axis)"
        )
    if zmin < -1e-3:
        raise ValueError(
            f"{what} extends behind the LED's emitting surface (to z = {zmin:.3f} mm in the LED frame): "
            "check --led-position/--led-axis"
        )
    if has_filter and zmax > lay.filter_z0 - CONTACT_GAP_MM + 1e-9:
        raise ValueError(
            f"{what} reaches z = {zmax:.3f} mm along the LED axis, into the excitation filter at "
            f"led_array.excitation_gap_mm = {design.led_array.excitation_gap_mm} mm"
        )
    if max(-xmin, xmax) > lay.bore_x or max(-ymin, ymax) > lay.bore_y:
        raise ValueError(
            f"{what} ({xmax - xmin:.2f} × {ymax - ymin:.2f} mm) does not fit the LED housing's bore "
            f"({2 * lay.bore_x:.2f} × {2 * lay.bore_y:.2f} mm: the excitation filter plus clearance)"
        )


def _filter_parts(design: SystemDesign, lay: _UnitLayout, matrix: np.ndarray, unit: int) -> list[Part]:
    """The excitation filter of one unit (pose ``matrix``, mm) as a closed plate with outward
    normals: coated face towards the LED (−z), bare back face (+z), absorbing edges."""
    f = design.excitation_filter
    v, fc = _box(f.width_mm / 2, f.length_mm / 2, lay.filter_z0, lay.filter_z1)
    nz = np.cross(v[fc[:, 1]] - v[fc[:, 0]], v[fc[:, 2]] - v[fc[:, 0]])[:, 2]
    scale = np.abs(nz).max()
    return [
        Part(f"{name}_{unit}", _place(matrix, v), fc[pick], role, Medium.FILTER, absorber, unit=unit)
        for name, pick, role, absorber in (
            ("filter_coated", nz < -0.5 * scale, Role.COATED, Absorber.HOUSING),
            ("filter_back", nz > 0.5 * scale, Role.GLASS, Absorber.HOUSING),
            ("filter_edge", np.abs(nz) <= 0.5 * scale, Role.ABSORBER, Absorber.FILTER_EDGE),
        )
    ]


def _housing_part(lay: _UnitLayout, matrix: np.ndarray, unit: int) -> Part:
    """One unit's absorbing LED housing (tube, seat, bore, lip, back; mm) at its pose."""
    quads = _walls(lay.tube_x, lay.tube_y, BOARD_Z_MM, lay.seat_z)
    quads += _walls(lay.bore_x, lay.bore_y, lay.seat_z, lay.lip_z0)
    if (lay.tube_x, lay.tube_y) != (lay.bore_x, lay.bore_y):
        quads += _frame(lay.tube_x, lay.tube_y, lay.bore_x, lay.bore_y, lay.seat_z)
    quads += _frame(lay.aperture_x, lay.aperture_y, lay.bore_x, lay.bore_y, lay.lip_z0)
    quads += _walls(lay.aperture_x, lay.aperture_y, lay.lip_z0, lay.lip_z1)
    quads += _frame(lay.aperture_x, lay.aperture_y, lay.outer, lay.outer, lay.lip_z1)
    quads += _walls(lay.outer, lay.outer, lay.back_z, lay.lip_z1)
    quads += [_rect(-lay.outer, lay.outer, -lay.outer, lay.outer, lay.back_z)]
    v, fc = _quads(quads)
    return Part(f"housing_{unit}", _place(matrix, v), fc, Role.ABSORBER, absorber=Absorber.HOUSING, unit=unit)


def _imaging_tower_parts(design: SystemDesign) -> list[Part]:
    """The MLA housing's tower and flange in the device frame, as absorbers."""
    env = mla_housing_envelope(design)
    half = env.tower_side_mm / 2
    v, fc = _box(half, half, env.flange_top_z_mm, env.tower_top_z_mm)
    tower = Part("imaging_tower", v, fc, Role.ABSORBER, absorber=Absorber.IMAGING_TOWER)
    flange = env.flange_side_mm / 2
    v, fc = _quads(_frame(half, half, flange, flange, env.flange_top_z_mm))
    return [tower, Part("imaging_flange", v, fc, Role.ABSORBER, absorber=Absorber.IMAGING_TOWER)]


def build_scene(
    design: SystemDesign,
    collimator: CollimatorMesh | None,
    *,
    excitation_filter: bool = True,
    housing: bool = True,
    smooth_normals: bool = True,
    label: str | None = None,
) -> IlluminationScene:
    """The four (``led_array.count``) units at their poses, the imaging tower and the sample plane.

    collimator: the collimator of every unit (None: a bare LED, the V1 design).
    excitation_filter: put the excitation filter in each unit.
    housing: surround each unit by its absorbing housing and add the imaging tower
        (False: a bare optical trace; the LED board stays).
    smooth_normals: shade the collimator with smooth vertex normals (creased along its B-rep
        faces' edges, or above :data:`CREASE_DEG` for an STL) rather than its flat facets.
    Raises ValueError when the collimator does not fit (see :func:`_check_fit`).
    """
    lay = _unit_layout(design, collimator)
    if collimator is not None:
        _check_fit(collimator, lay, design, excitation_filter)
    poses = np.array([pose.matrix for pose in led_poses(design)])
    parts: list[Part] = []
    if collimator is not None:
        cm_vertices = np.asarray(collimator.mesh.vertices, dtype=float)
        cm_faces = np.asarray(collimator.mesh.faces, dtype=np.int64)
        cm_normals = corner_normals(cm_vertices, cm_faces, collimator.face_ids) if smooth_normals else None
    portal_z = lay.filter_z1 + design.mechanics.clearance_mm / 2
    for unit, matrix in enumerate(poses):
        rot = matrix[:3, :3]
        if collimator is not None:
            parts.append(
                Part(
                    f"collimator_{unit}",
                    _place(matrix, cm_vertices),
                    cm_faces,
                    Role.DIELECTRIC,
                    Medium.COLLIMATOR,
                    unit=unit,
                    corner_normals=None if cm_normals is None else cm_normals @ rot.T,
                )
            )
        if excitation_filter:
            parts += _filter_parts(design, lay, matrix, unit)
        board_half = lay.outer if housing else max(lay.outer, 10.0)
        v, fc = _quads([_rect(-board_half, board_half, -board_half, board_half, BOARD_Z_MM)])
        parts.append(
            Part(f"led_board_{unit}", _place(matrix, v), fc, Role.ABSORBER, absorber=Absorber.LED_BOARD, unit=unit)
        )
        if not excitation_filter:
            portal_x, portal_y = (lay.bore_x, lay.bore_y) if housing else (10.0, 10.0)
            v, fc = _quads([_rect(-portal_x, portal_x, -portal_y, portal_y, portal_z)])
            parts.append(Part(f"portal_{unit}", _place(matrix, v), fc, Role.PORTAL, unit=unit))
        if housing:
            parts.append(_housing_part(lay, matrix, unit))
    if housing:
        parts += _imaging_tower_parts(design)
    z = first_order.object_plane_z_mm(design)
    v, fc = _quads([_rect(-SAMPLE_HALF_MM, SAMPLE_HALF_MM, -SAMPLE_HALF_MM, SAMPLE_HALF_MM, z)])
    parts.append(Part("sample_plane", v, fc, Role.SAMPLE))
    if label is None:
        label = collimator.label if collimator is not None else "bare LED (V1)"
    return IlluminationScene(
        design=design,
        label=label,
        parts=tuple(parts),
        poses=poses,
        collimator=collimator,
        has_filter=excitation_filter,
        has_housing=housing,
        filter_material=design.excitation_filter.material,
        portal_z_mm=portal_z,
    )
