"""Where things sit in the device frame: poses of the LED units and of the imaging stack.

Pure NumPy so that CAD, ray tracing and analysis share one placement. Device frame:
origin on the sensor surface, +z towards the sample (see :mod:`cm2optics.design`).

LED frame (one per unit): origin at the centre of the LED's emitting surface, +z along the
unit's axis (the direction the light leaves in), +x tangential (counter-clockwise seen from
the sample side), +y = z × x. The LED package lies at z ≤ 0, the collimator and filter at z > 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.optics import first_order


@dataclass(frozen=True)
class Pose:
    """A rigid placement: ``matrix`` (4×4) maps local homogeneous points to the device frame."""

    matrix: np.ndarray

    @property
    def origin_mm(self) -> np.ndarray:
        return self.matrix[:3, 3].copy()

    @property
    def axis(self) -> np.ndarray:
        """The local +z axis in the device frame (unit vector)."""
        return self.matrix[:3, 2].copy()

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        """Map local points (…, 3) in mm to the device frame."""
        points = np.asarray(points_mm, dtype=float)
        return points @ self.matrix[:3, :3].T + self.matrix[:3, 3]


def led_poses(design: SystemDesign) -> list[Pose]:
    """Pose of every LED unit: its aperture (excitation filter's lower face) ``led_array.offset_mm``
    off the optical axis, its axis tilted by ``led_array.tilt_deg`` and aimed at the point of the
    nominal focal plane ``led_array.aim_mm`` (mm) from the optical axis along the unit's radial
    direction (0: the field's centre), which fixes the unit's height."""
    arr = design.led_array
    tilt = math.radians(arr.tilt_deg)
    reach = arr.offset_mm - arr.aim_mm  # horizontal run of the axis from the aperture to the aim point, mm
    aperture_z = first_order.object_plane_z_mm(design) - (reach / math.tan(tilt) if tilt > 0 else 10.0)
    poses = []
    for i in range(arr.count):
        phi = math.radians(arr.azimuth_deg) + 2.0 * math.pi * i / arr.count
        radial = np.array([math.cos(phi), math.sin(phi), 0.0])
        z_axis = -math.sin(tilt) * radial + np.array([0.0, 0.0, math.cos(tilt)])
        origin = arr.offset_mm * radial + np.array([0.0, 0.0, aperture_z]) - arr.excitation_gap_mm * z_axis
        x_axis = np.array([-math.sin(phi), math.cos(phi), 0.0])
        y_axis = np.cross(z_axis, x_axis)
        matrix = np.eye(4)
        matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = x_axis, y_axis, z_axis, origin
        poses.append(Pose(matrix))
    return poses


@dataclass(frozen=True)
class HousingEnvelope:
    """Outer envelope of the MLA housing in the device frame (mm): a square base flange that
    stands on the sensor board (a skirt around the sensor package and standoffs at the screw
    holes below a plate just above the sensor surface) and a square tower around the optics,
    open at the top. Other parts may rest on the flange's top face."""

    flange_side_mm: float
    flange_bottom_z_mm: float
    flange_top_z_mm: float
    tower_side_mm: float
    tower_top_z_mm: float
    tower_chamfer_mm: float


def mla_housing_envelope(design: SystemDesign) -> HousingEnvelope:
    """Envelope that every other printed part must keep clear of."""
    return HousingEnvelope(
        flange_side_mm=design.sensor_board.size_mm,
        flange_bottom_z_mm=-design.sensor.package_height_mm,
        flange_top_z_mm=design.mechanics.clearance_mm + design.mla_housing.flange_mm,
        tower_side_mm=design.mla_housing.outer_mm,
        tower_top_z_mm=design.emission_filter_z_mm + design.emission_filter.thickness_mm,
        tower_chamfer_mm=design.mla_housing.chamfer_mm,
    )


@dataclass(frozen=True)
class UnitBlock:
    """The outer block of one LED unit's printed housing in its LED frame (mm): a square of
    half-side ``half_mm`` from ``back_z_mm`` (its back face) to ``front_z_mm`` (the front of its
    lip, where light leaves the unit)."""

    half_mm: float
    back_z_mm: float
    front_z_mm: float


def led_unit_block(design: SystemDesign) -> UnitBlock:
    """The LED housing's outer block (:mod:`cm2optics.cad.led_housing` builds its solid in it):
    the back wall ``led_housing.back_mm`` behind the LED's pocket, the lip ``mechanics.min_wall_mm``
    in front of the excitation filter's seat."""
    c, w = design.mechanics.clearance_mm, design.mechanics.min_wall_mm
    back = -design.led.package_height_mm - c - design.led_housing.back_mm
    front = design.led_array.excitation_gap_mm + design.excitation_filter.thickness_mm + c + w
    return UnitBlock(design.led_housing.outer_mm / 2, back, front)


def dome_rim_z_mm(design: SystemDesign) -> tuple[float, float]:
    """Where the base plate's dome (:mod:`cm2optics.cad.base_plate`) meets the tower, mm: the
    height at which the inner face of the dome's face under each unit (parallel to the unit's
    inner side, ``base_plate.thickness_mm`` thick, beyond the socket's clearance) reaches the
    tower's side plus the clearance, and the top of the rim's vertical land above it. The dome
    can be built only when both lie between the flange's top and the tower's top."""
    arr, t, c = design.led_array, design.base_plate.thickness_mm, design.mechanics.clearance_mm
    cos_t, sin_t = math.cos(math.radians(arr.tilt_deg)), math.sin(math.radians(arr.tilt_deg))
    pose = led_poses(design)[0]
    # Plane y_local = k of unit 0's LED frame: radial · cos + z · sin = reach − k (all units alike).
    reach = float(-pose.origin_mm @ pose.matrix[:3, 1])
    k_inner = led_unit_block(design).half_mm + c + 3 * t / 2
    hole = mla_housing_envelope(design).tower_side_mm / 2 + c
    meets_tower = (reach - k_inner - hole * cos_t) / sin_t if sin_t > 1e-9 else -math.inf
    return meets_tower, meets_tower + t / (cos_t + sin_t)


def _box_corners(pose: Pose, half_mm: float, z0_mm: float, z1_mm: float) -> np.ndarray:
    """(8, 3) corners in the device frame of the LED-frame box ``|x|, |y| ≤ half_mm``, ``z0 ≤ z ≤ z1`` (mm)."""
    s = np.array([-1.0, 1.0])
    x, y, z = np.meshgrid(half_mm * s, half_mm * s, np.array([z0_mm, z1_mm]), indexing="ij")
    return pose.apply(np.column_stack([x.ravel(), y.ravel(), z.ravel()]))


def _convex_overlap(a: np.ndarray, a_dirs: np.ndarray, b: np.ndarray, b_dirs: np.ndarray) -> bool:
    """Whether two convex solids overlap, each given by its vertices (n, 3) and the directions
    (k, 3) of its face normals and edges: the separating-axis test over the normals and the
    cross products of the edges (the normals listed among the edges: a box's edges are its normals)."""
    crosses = np.cross(a_dirs[:, None, :], b_dirs[None, :, :]).reshape(-1, 3)
    axes = np.vstack([a_dirs, b_dirs, crosses[np.linalg.norm(crosses, axis=1) > 1e-9]])
    pa, pb = a @ axes.T, b @ axes.T
    separated = (pa.max(axis=0) < pb.min(axis=0) - 1e-9) | (pb.max(axis=0) < pa.min(axis=0) - 1e-9)
    return not bool(separated.any())


def _tower(env: HousingEnvelope) -> tuple[np.ndarray, np.ndarray]:
    """The MLA housing's tower (from the flange's top to its chamfered top) as vertices and the
    directions of its face normals and edges (device frame, mm)."""
    half, top, ch = env.tower_side_mm / 2, env.tower_top_z_mm, env.tower_chamfer_mm
    ring = np.array([[sx, sy] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)])
    layers = [(half, env.flange_top_z_mm), (half, top - ch), (half - ch, top)]
    vertices = np.vstack([np.column_stack([r * ring, np.full(4, z)]) for r, z in layers])
    dirs = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [-1, 0, 1], [0, 1, 1], [0, -1, 1]]
    dirs += [[sx, sy, 1] for sx in (-1, 1) for sy in (-1, 1)]  # where two chamfers meet
    return vertices, np.array(dirs, dtype=float)


def unit_clashes(design: SystemDesign) -> list[str]:
    """A quick test that the placed LED units clear the MLA housing (mm, no CAD kernel): each
    unit's housing block and the base plate's socket around its back (``mechanics.clearance_mm``
    and ``mechanics.wall_mm`` wider, ``base_plate.socket_depth_mm`` deep, taken as a box) against
    the chamfered tower, the flange's top plane and the other units, and the base plate's dome
    meeting the tower below its top (:func:`dome_rim_z_mm`). Returns one line per clash
    (empty: clear). The assembly's interference check (:mod:`cm2optics.cad.assembly`) is the
    exact one; this one is for design searches."""
    block, c, wall = led_unit_block(design), design.mechanics.clearance_mm, design.mechanics.wall_mm
    env = mla_housing_envelope(design)
    tower, tower_dirs = _tower(env)
    units = []
    for pose in led_poses(design):
        housing = _box_corners(pose, block.half_mm, block.back_z_mm, block.front_z_mm)
        socket_z = (block.back_z_mm - c - wall, block.back_z_mm + design.base_plate.socket_depth_mm)
        socket = _box_corners(pose, block.half_mm + c + wall, *socket_z)
        units.append((housing, socket, pose.matrix[:3, :3].T))
    clashes = []
    meets, top = dome_rim_z_mm(design)
    if not env.flange_top_z_mm < meets < top < env.tower_top_z_mm:
        clashes.append(
            f"the base plate's dome would meet the tower at {meets:.3f}–{top:.3f} mm, not between the flange "
            f"({env.flange_top_z_mm:g} mm) and the tower's top ({env.tower_top_z_mm:g} mm)"
        )
    for i, (housing, socket, axes) in enumerate(units, start=1):
        for name, corners in (("housing", housing), ("base-plate socket", socket)):
            if _convex_overlap(corners, axes, tower, tower_dirs):
                clashes.append(f"LED unit {i}'s {name} enters the imaging tower")
            if corners[:, 2].min() < env.flange_top_z_mm:
                clashes.append(
                    f"LED unit {i}'s {name} reaches below the MLA housing's flange ({env.flange_top_z_mm:g} mm)"
                )
        for j in range(i, len(units)):
            if _convex_overlap(housing, axes, units[j][0], units[j][2]):
                clashes.append(f"LED units {i} and {j + 1} overlap")
    return clashes
