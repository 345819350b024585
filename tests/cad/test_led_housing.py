"""The LED housing: one valid solid, watertight, its volume from its sections, its fits and
walls, its parts seated without clashing and able to slide in through the loading window."""

from __future__ import annotations

import math

import cadquery as cq
import numpy as np
import pytest
import trimesh
from collimator_standin import collimator_envelope, collimator_swept_along_x
from OCP.gp import gp_Dir, gp_Lin, gp_Pnt
from OCP.IntCurvesFace import IntCurvesFace_ShapeIntersector

from cm2optics.cad.led_housing import Box, build_led_housing, led_housing_fits, led_housing_layout, led_unit_parts
from cm2optics.cad.mesh_checks import min_wall_thickness_mm
from cm2optics.design import DesignError

SHARED = 1e-6  # mm³: shared faces and edges, not overlap


@pytest.fixture(scope="module")
def housing(design) -> cq.Solid:
    return build_led_housing(design).val()


def seated_parts(design) -> dict[str, cq.Solid]:
    parts = {name: wp.val() for name, wp in led_unit_parts(design).items()}
    if design.collimator is not None:
        parts["collimator"] = collimator_envelope(design)
    return parts


def chords_mm(shape: cq.Shape, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Lengths (mm) of the segments of the line ``origin + s·direction`` inside ``shape``."""
    tool = IntCurvesFace_ShapeIntersector()
    tool.Load(shape.wrapped, 1e-7)
    tool.Perform(gp_Lin(gp_Pnt(*map(float, origin)), gp_Dir(*map(float, direction))), -1e3, 1e3)
    hits = np.unique(np.round(sorted(tool.WParameter(i) for i in range(1, tool.NbPnt() + 1)), 9))
    assert len(hits) % 2 == 0, f"a line through {origin} along {direction} crosses the surface an odd number of times"
    return hits[1::2] - hits[0::2]


def test_one_valid_solid_with_its_analytic_box(design, housing):
    c, w = design.mechanics.clearance_mm, design.mechanics.min_wall_mm
    half = design.led_housing.outer_mm / 2
    back = -(design.led.package_height_mm + c + design.led_housing.back_mm)
    front = design.led_array.excitation_gap_mm + design.excitation_filter.thickness_mm + c + w
    bb = housing.BoundingBox()
    assert housing.isValid() and len(build_led_housing(design).solids().vals()) == 1
    assert (bb.xmin, bb.xmax, bb.ymin, bb.ymax) == pytest.approx((-half, half, -half, half), abs=1e-6)
    assert (bb.zmin, bb.zmax) == pytest.approx((back, front), abs=1e-6)


def test_volume_is_the_sum_of_its_sections(design, housing):
    """Volume from the cross-section area of each axial section, worked out by hand."""
    c, w = design.mechanics.clearance_mm, design.mechanics.min_wall_mm
    led, filt, col = design.led, design.excitation_filter, design.collimator
    side, half = design.led_housing.outer_mm, design.led_housing.outer_mm / 2
    gap = design.led_array.excitation_gap_mm
    full = side**2
    h = min(led.package_length_mm, filt.width_mm, filt.length_mm, *([col.footprint_mm] if col else [])) / 2
    notch = (half - led.package_width_mm / 2) * 2 * (h + c)  # the rail's way through the back wall
    sections = [
        (design.led_housing.back_mm, full - led.package_width_mm / 2 * (led.package_length_mm - 2 * w) - notch),
        (led.package_height_mm + 2 * c, full - (half + led.package_width_mm / 2 + c) * (led.package_length_mm + 2 * c)),
    ]
    seat = filt.width_mm + 2 * c
    if col is not None:
        r = col.footprint_mm / 2 + c
        flange_z0 = col.led_gap_mm + col.height_mm - col.flange_mm
        sections.append((flange_z0 - 2 * c, full - (math.pi * r**2 / 2 + half * 2 * r)))  # bore and its channel
        seat_height = gap + filt.thickness_mm + c - (flange_z0 - c)
    else:
        tube = filt.width_mm - 2 * design.led_housing.lip_mm
        window = (half - led.package_width_mm / 2) * 2 * (h + c)
        overlap = (tube / 2 - led.package_width_mm / 2) * tube
        sections.append((gap - 2 * c, full - (tube**2 + window - overlap)))
        seat_height = filt.thickness_mm + 2 * c
    sections.append((seat_height, full - (half + seat / 2) * seat))
    sections.append((w, full - (filt.width_mm - 2 * design.led_housing.lip_mm) ** 2))
    assert housing.Volume() == pytest.approx(sum(t * a for t, a in sections), rel=1e-9)


def test_stl_is_watertight(housing, tmp_path):
    path = tmp_path / "led_housing.stl"
    cq.exporters.export(cq.Workplane().add(housing), str(path), tolerance=0.002, angularTolerance=0.05)
    mesh = trimesh.load(path)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(housing.Volume(), rel=2e-3)


def test_fits_are_slip_fits(design):
    fits = led_housing_fits(design)
    expected = {"LED package", "excitation filter"} | ({"collimator flange"} if design.collimator else set())
    assert {f.part for f in fits} == expected
    assert all(0.05 <= f.clearance_mm <= 0.2 for f in fits), fits


def test_walls_are_printable(design, housing, tmp_path):
    w = design.mechanics.min_wall_mm
    layout = led_housing_layout(design)
    half = layout.half_mm
    # The thinnest walls by construction, from the layout's own numbers.
    walls = {
        "side walls at the LED pocket": half - layout.led_pocket.y1,
        "back wall": layout.led_pocket.z0 - layout.back_z_mm,
        "lip": layout.front_z_mm - layout.filter_seat.z1,
        "lip width": half - layout.aperture.x1,
        "posts beside the window": half - layout.windows[0].y1,
        "back wall between lead slot and window": layout.windows[0].x0 - layout.lead_slot.x1,
        "side walls at the seat": half - layout.filter_seat.y1,
    }
    if layout.bore_radius_mm is not None:
        walls["side walls at the bore"] = half - layout.bore_radius_mm
    assert min(walls.values()) >= w - 1e-9, walls
    assert min(walls.values()) == pytest.approx(w)  # the LED fills its housing: walls at the limit
    # Sampled: every chord of the solid along its axes, on a grid that misses its edges.
    grid = np.arange(-half + 0.0137, half, 0.1)
    zs = np.arange(layout.back_z_mm + 0.0113, layout.front_z_mm, 0.1)
    lines = [((-10, y, z), (1, 0, 0)) for y in grid[::3] for z in zs[::2]]
    lines += [((x, -10, z), (0, 1, 0)) for x in grid[::3] for z in zs[::2]]
    lines += [((x, y, -10), (0, 0, 1)) for x in grid for y in grid]
    shortest = min(chords_mm(housing, np.array(o), np.array(d)).min(initial=np.inf) for o, d in lines)
    assert shortest >= w - 1e-6
    # And as the exporter measures it, on the mesh.
    path = tmp_path / "led_housing.stl"
    cq.exporters.export(cq.Workplane().add(housing), str(path), tolerance=0.002, angularTolerance=0.05)
    assert min_wall_thickness_mm(trimesh.load(path), samples=3000) >= w - 1e-3


def test_parts_are_seated_without_clashing_and_held(design, housing):
    c = design.mechanics.clearance_mm
    parts = seated_parts(design)
    for name, part in parts.items():
        assert housing.intersect(part).Volume() < SHARED, name
    down = cq.Vector(0, 0, -(c + 0.05))
    up = cq.Vector(0, 0, c + 0.05)
    # The back wall carries the LED, the lip retains the filter.
    assert housing.intersect(parts["led"].translate(down)).Volume() > 1e-4
    assert housing.intersect(parts["excitation_filter"].translate(up)).Volume() > 1e-4
    if design.collimator is not None:
        # The flange rests on the corners beside the bore (and on the base plate's rail).
        assert housing.intersect(parts["collimator"].translate(down)).Volume() > 1e-4
        # The filter rests on the flange's exit face.
        assert parts["collimator"].intersect(parts["excitation_filter"].translate(down)).Volume() > 1e-4
    else:
        assert housing.intersect(parts["excitation_filter"].translate(down)).Volume() > 1e-4


def swept_along_x(design, name: str) -> cq.Solid:
    """The space a seated part sweeps when pushed out along +x past the housing's side."""
    out = design.led_housing.outer_mm
    if name == "collimator":
        return collimator_swept_along_x(design, out)
    bb = led_unit_parts(design)[name].val().BoundingBox()
    return Box(bb.xmin, out, bb.ymin, bb.ymax, bb.zmin, bb.zmax).solid().val()


def test_parts_slide_in_through_the_loading_window(design, housing):
    """Each part, pushed out along +x from its seat, leaves the housing without touching it."""
    for name in seated_parts(design):
        assert housing.intersect(swept_along_x(design, name)).Volume() < SHARED, name


def test_filter_must_rest_on_the_collimator(v2):
    with pytest.raises(DesignError, match="excitation_gap_mm"):
        build_led_housing(v2.with_changes({"led_array.excitation_gap_mm": 2.3}))
