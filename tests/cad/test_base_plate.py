"""The base plate: one valid solid on the MLA housing's flange, clear of the MLA housing, the
LED units and the light (excitation cones, imaging path), its sockets and rails fitting the
LED housings, its dome's volume from its sections, printable walls."""

from __future__ import annotations

import math

import cadquery as cq
import numpy as np
import pytest
import trimesh
from collimator_standin import collimator_envelope
from scipy.spatial import ConvexHull

from cm2optics.cad.base_plate import base_plate_fits, build_base_plate
from cm2optics.cad.led_housing import Box, build_led_housing, led_housing_layout, led_unit_parts
from cm2optics.cad.mesh_checks import min_wall_thickness_mm
from cm2optics.cad.placement import location_from_pose
from cm2optics.design import DesignError, load_preset
from cm2optics.optics import first_order
from cm2optics.optics.layout import led_poses, mla_housing_envelope

SHARED = 1e-6  # mm³: shared faces and edges, not overlap


@pytest.fixture(scope="module")
def plate(design) -> cq.Solid:
    return build_base_plate(design).val()


def placed(design, part: cq.Solid) -> list[cq.Solid]:
    """``part`` (LED frame) at every LED pose."""
    return [part.moved(location_from_pose(pose)) for pose in led_poses(design)]


def unit_parts(design) -> dict[str, cq.Solid]:
    """One unit's solids in the LED frame: housing, LED, filter, collimator stand-in."""
    parts = {"housing": build_led_housing(design).val()} | {k: v.val() for k, v in led_unit_parts(design).items()}
    if design.collimator is not None:
        parts["collimator"] = collimator_envelope(design)
    return parts


def envelope_solid(design) -> cq.Solid:
    """The MLA housing's envelope: a board-sized flange and the chamfered tower."""
    env = mla_housing_envelope(design)
    half_f, half_t = env.flange_side_mm / 2, env.tower_side_mm / 2
    flange = Box(-half_f, half_f, -half_f, half_f, env.flange_bottom_z_mm, env.flange_top_z_mm).solid()
    tower = Box(-half_t, half_t, -half_t, half_t, env.flange_top_z_mm, env.tower_top_z_mm).solid()
    return flange.union(tower.edges(">Z").chamfer(env.tower_chamfer_mm)).val()


def hull_solid(points: np.ndarray) -> cq.Solid:
    """The convex hull of ``points`` (mm) as a polyhedral solid."""
    hull = ConvexHull(points)
    faces = []
    for simplex, plane in zip(hull.simplices, hull.equations, strict=True):
        a, b, c = points[simplex]
        if np.dot(np.cross(b - a, c - a), plane[:3]) < 0:
            b, c = c, b
        faces.append(cq.Face.makeFromWires(cq.Wire.makePolygon([cq.Vector(*p) for p in (a, b, c)], close=True)))
    solid = cq.Solid.makeSolid(cq.Shell.makeShell(faces))
    assert solid.isValid() and solid.Volume() == pytest.approx(hull.volume, rel=1e-6)
    return solid


def field_circle(design, n: int = 96) -> np.ndarray:
    """Points around the illuminated field on the focal plane, on a polygon that encloses it."""
    r = design.volume.field_mm / 2 / math.cos(math.pi / n)
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.column_stack([r * np.cos(t), r * np.sin(t), np.full(n, first_order.object_plane_z_mm(design))])


def excitation_cones(design) -> list[cq.Solid]:
    """Light from each unit's clear aperture (the lip's opening) to the whole field."""
    ap = led_housing_layout(design).aperture
    corners = np.array([(x, y, led_housing_layout(design).front_z_mm) for x in (ap.x0, ap.x1) for y in (ap.y0, ap.y1)])
    return [hull_solid(np.vstack([pose.apply(corners), field_circle(design)])) for pose in led_poses(design)]


def imaging_path(design) -> cq.Solid:
    """From the field on the focal plane down to the emission filter's top face (the tower's top)."""
    f, top = design.emission_filter, mla_housing_envelope(design).tower_top_z_mm
    square = np.array([(sx * f.width_mm / 2, sy * f.length_mm / 2, top) for sx in (-1, 1) for sy in (-1, 1)])
    return hull_solid(np.vstack([square, field_circle(design)]))


def test_one_valid_solid_on_the_flange(design, plate):
    assert plate.isValid() and len(build_base_plate(design).solids().vals()) == 1
    bb = plate.BoundingBox()
    assert bb.zmin == pytest.approx(mla_housing_envelope(design).flange_top_z_mm, abs=1e-6)


def _socket_and_rail_vertices(design, layout, side: float, t: float, z0: float) -> np.ndarray:
    """The vertices of one unit's socket block (its back edge along x at y = −side chamfered by
    ``t``) and of its rail's steps, LED frame (mm): the plate's convex outermost points."""
    z1 = layout.back_z_mm + design.base_plate.socket_depth_mm
    section = [(-side + t, z0), (side, z0), (side, z1), (-side, z1), (-side, z0 + t)]
    points = [(x, y, z) for x in (-side, side) for y, z in section]
    for step in layout.rails:
        z_floor = layout.back_z_mm - design.mechanics.clearance_mm - t / 2
        points += [(x, y, z) for x in (step.x0, side) for y in (step.y0, step.y1) for z in (z_floor, step.z1)]
    return np.array(points)


def test_bounding_box_from_the_sockets_and_rails(design, plate):
    """Its extent is set by the sockets' blocks (their chamfered back corners, whatever the units'
    azimuth) and the rails' front ends."""
    c, t = design.mechanics.clearance_mm, design.mechanics.wall_mm
    layout = led_housing_layout(design)
    side = layout.half_mm + c + t
    z0 = layout.back_z_mm - c - t
    pose = led_poses(design)[0]
    vertices = _socket_and_rail_vertices(design, layout, side, t, z0)
    back_corners = np.concatenate([p.apply(vertices) for p in led_poses(design)])
    rail = layout.rails[1]
    rail_tops = pose.apply(np.array([(side, y, rail.z1) for y in (rail.y0, rail.y1)]))
    socket_tops = pose.apply(
        np.array([(side, y, layout.back_z_mm + design.base_plate.socket_depth_mm) for y in (-side, side)])
    )
    bb = plate.BoundingBox()
    low, high = back_corners[:, :2].min(axis=0), back_corners[:, :2].max(axis=0)
    assert (bb.xmin, bb.xmax, bb.ymin, bb.ymax) == pytest.approx((low[0], high[0], low[1], high[1]), abs=1e-6)
    assert bb.zmax == pytest.approx(max(rail_tops[:, 2].max(), socket_tops[:, 2].max()), abs=1e-6)
    # On the camera board (the authors' plate: ≈ 21 × 21 × 8 mm; cm2-v2's units sit farther out).
    assert bb.xlen < design.sensor_board.size_mm and bb.ylen < design.sensor_board.size_mm and bb.zlen < 11


def test_dome_volume_from_its_sections(design, plate):
    """Below the sockets the plate is the dome alone: a square ring whose inner side slopes at
    the units' tilt and whose outer side is vertical, then slopes."""
    c, t = design.mechanics.clearance_mm, design.base_plate.thickness_mm
    wall = design.mechanics.wall_mm
    cos_t, sin_t = math.cos(math.radians(design.led_array.tilt_deg)), math.sin(math.radians(design.led_array.tilt_deg))
    layout = led_housing_layout(design)
    pose = led_poses(design)[0]
    reach = -pose.origin_mm @ pose.matrix[:3, 1]  # radial·cos + z·sin of the plane y_local = 0
    socket = layout.half_mm + c

    def apothem(z, k):
        return (reach - k - z * sin_t) / cos_t

    z0 = mla_housing_envelope(design).flange_top_z_mm
    side = socket + wall
    lowest = pose.apply(np.array([(0, side, layout.back_z_mm - c - wall)]))[0, 2]  # the sockets' lowest edge
    z1 = lowest - 0.05
    assert z1 - z0 > 0.5
    foot = apothem(z0, socket + 1.5 * t) + t / (cos_t + sin_t)
    z = np.linspace(z0, z1, 20001)
    area = 4 * np.minimum(apothem(z, socket + 0.5 * t), foot) ** 2 - 4 * apothem(z, socket + 1.5 * t) ** 2
    expected = float(np.sum((area[1:] + area[:-1]) / 2 * np.diff(z)))
    band = Box(-50, 50, -50, 50, z0 - 1, z1).solid().val()
    assert plate.intersect(band).Volume() == pytest.approx(expected, rel=1e-6)


def test_stl_is_watertight_and_walls_printable(design, plate, tmp_path):
    path = tmp_path / "base_plate.stl"
    cq.exporters.export(cq.Workplane().add(plate), str(path), tolerance=0.002, angularTolerance=0.05)
    mesh = trimesh.load(path)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(plate.Volume(), rel=2e-3)
    w, t, c = design.mechanics.min_wall_mm, design.base_plate.thickness_mm, design.mechanics.clearance_mm
    wall = design.mechanics.wall_mm
    tilt = math.radians(design.led_array.tilt_deg)
    layout = led_housing_layout(design)
    lower, upper = layout.rails
    walls = {
        "dome": t,
        "dome's rims (vertical land = horizontal face)": t / (math.cos(tilt) + math.sin(tilt)),
        "sockets' walls and floor": wall,
        "sockets' chamfered back corner": wall / math.sqrt(2),
        "rails across": lower.y1 - lower.y0,
        "rails' thinnest step, with the socket wall": layout.half_mm + c + wall - upper.x0,
        "lead hole to rail": lower.x0 - layout.lead_slot.x1,
    }
    assert min(walls.values()) >= w, walls
    assert min_wall_thickness_mm(mesh, samples=4000) >= w - 1e-3


def test_clear_of_the_mla_housing_and_the_led_units(design, plate):
    assert plate.intersect(envelope_solid(design)).Volume() < SHARED
    for name, part in unit_parts(design).items():
        for i, solid in enumerate(placed(design, part), start=1):
            assert plate.intersect(solid).Volume() < SHARED, f"{name} {i}"


def test_light_paths_are_clear(design, plate):
    housings = placed(design, build_led_housing(design).val())
    cones = excitation_cones(design)
    for i, cone in enumerate(cones, start=1):
        assert plate.intersect(cone).Volume() < SHARED, f"excitation cone {i}"
        for j, housing in enumerate(housings, start=1):
            assert housing.intersect(cone).Volume() < SHARED, f"excitation cone {i} and housing {j}"
    image = imaging_path(design)
    assert plate.intersect(image).Volume() < SHARED
    for j, housing in enumerate(housings, start=1):
        assert housing.intersect(image).Volume() < SHARED, f"imaging path and housing {j}"


def test_surrounds_the_tower_and_holds_each_housing_at_the_clearance(design, plate):
    """Grown by the clearance less 0.02 mm the tower and each housing's back stay clear of the
    plate; grown by the clearance plus 0.02 mm they touch it on every side."""
    c, d = design.mechanics.clearance_mm, 0.02
    env = mla_housing_envelope(design)
    half = env.tower_side_mm / 2
    for grow, touches in ((c - d, False), (c + d, True)):
        tower = (
            Box(-half - grow, half + grow, -half - grow, half + grow, env.flange_top_z_mm, env.tower_top_z_mm)
            .solid()
            .val()
        )
        assert (plate.intersect(tower).Volume() > 1e-4) is touches
    layout = led_housing_layout(design)
    h, depth = layout.half_mm, design.base_plate.socket_depth_mm
    z0 = layout.back_z_mm
    window = layout.windows[0].y1
    for grow, touches in ((c - d, False), (c + d, True)):
        sides = {
            "-x": Box(-h - grow, -h, -h, h, z0, z0 + depth),
            "+y": Box(-h, h, h, h + grow, z0, z0 + depth),
            "-y": Box(-h, h, -h - grow, -h, z0, z0 + depth),
            "+x beside the rail": Box(h, h + grow, window + d, h, z0, z0 + depth),
            "floor": Box(-h, -layout.lead_slot.x1 - d, -h, h, z0 - grow, z0),
        }
        for side, box in sides.items():
            for i, solid in enumerate(placed(design, box.solid().val()), start=1):
                assert (plate.intersect(solid).Volume() > 1e-6) is touches, f"socket {i} {side}"


def test_rails_slide_in_from_the_back_and_locate_the_parts(design, plate):
    """Swept back along the unit's axis, the rail steps stay clear of the housing and its parts
    (the housing can slide onto them); and each part, pushed 0.05 mm beyond its clearance
    towards +x, meets the rail."""
    c = design.mechanics.clearance_mm
    layout = led_housing_layout(design)
    lower, upper = layout.rails
    far = layout.back_z_mm - 10
    swept = [Box(r.x0, r.x1, r.y0, r.y1, far, r.z1).solid() for r in layout.rails]
    if layout.bore_radius_mm is not None:
        z0 = layout.bore_z_mm[0]
        swept[0] = swept[0].cut(cq.Workplane().circle(layout.bore_radius_mm).extrude(20).translate((0, 0, z0)))
    parts = unit_parts(design)
    for name, part in parts.items():
        for step in swept:
            assert step.val().intersect(part).Volume() < SHARED, name
    shift = cq.Vector(c + 0.05, 0, 0)
    for name in ("led", "excitation_filter", "collimator"):
        if name in parts:
            for i, solid in enumerate(placed(design, parts[name].translate(shift)), start=1):
                assert plate.intersect(solid).Volume() > 1e-6, f"{name} {i}"


def test_fits_are_slip_fits(design):
    fits = base_plate_fits(design)
    assert len(fits) == 2 * design.led_array.count + 1
    assert all(0.05 <= f.clearance_mm <= 0.2 for f in fits), fits


def test_dome_needs_three_units():
    with pytest.raises(DesignError, match="led_array.count"):
        build_base_plate(load_preset("cm2-v2").with_changes({"led_array.count": 2}))
