"""The printed MLA housing: one solid, watertight, walls and fits, no clash with its optics."""

from __future__ import annotations

import cadquery as cq
import pytest
import trimesh

from cm2optics.cad import components
from cm2optics.cad.mesh_checks import min_wall_thickness_mm
from cm2optics.cad.mla import build_mla
from cm2optics.cad.mla_housing import bore_steps, build_mla_housing, mla_housing_fits, mla_tab_geometry
from cm2optics.cad.tessellate import export_stl
from cm2optics.optics.layout import mla_housing_envelope


@pytest.fixture(scope="module")
def housing(design) -> cq.Solid:
    return build_mla_housing(design).val()


def test_one_valid_solid_inside_its_envelope(design, housing):
    env = mla_housing_envelope(design)
    bb = housing.BoundingBox()
    assert housing.isValid()
    assert bb.zmin == pytest.approx(env.flange_bottom_z_mm) and bb.zmax == pytest.approx(env.tower_top_z_mm)
    assert bb.xlen <= env.flange_side_mm + 1e-6


def test_watertight_and_walls_printable(design, housing, tmp_path):
    path = tmp_path / "h.stl"
    export_stl(housing, path, 0.001)
    mesh = trimesh.load(path, force="mesh")
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(housing.Volume(), rel=0.005)
    wall = min_wall_thickness_mm(mesh, samples=5000)
    assert wall >= design.mechanics.min_wall_mm
    # The thinnest walls: the chamfered rim at the tower top (seat wall minus chamfer) and the
    # corner tabs over the MLA (its corner sag plus the mask gap).
    rim = (
        (design.mla_housing.outer_mm - design.emission_filter.width_mm) / 2
        - design.mechanics.clearance_mm
        - design.mla_housing.chamfer_mm
    )
    tabs = mla_tab_geometry(design)
    assert wall == pytest.approx(min(rim, tabs.z1_mm - tabs.z0_mm), abs=0.01)


def test_fits_within_slip_fit_range(design):
    fits = mla_housing_fits(design)
    assert {f.part for f in fits} >= {"MLA", "aperture mask", "emission filter", "sensor package"}
    assert all(0.05 <= f.clearance_mm <= 0.2 for f in fits)


def test_seated_optics_do_not_clash_and_rest_on_ledges(design, housing):
    placed = {
        "mla": (build_mla(design), design.imaging.mla_to_sensor_mm),
        "mask": (components.build_aperture_mask(design), design.mask_z_mm),
        "filter": (components.build_emission_filter(design), design.emission_filter_z_mm),
        "package": (components.build_sensor_package(design), -design.sensor.package_height_mm),
    }
    if design.absorption_filter is not None:
        placed["film"] = (components.build_absorption_filter(design), design.imaging.film_to_sensor_mm)
    for name, (part, z) in placed.items():
        solid = part.val().translate(cq.Vector(0, 0, z))
        assert housing.intersect(solid).Volume() < 1e-6, name
        # Resting on a ledge: lowered by 0.05 mm it would clash (the seat supports it).
        if name in ("mask", "filter"):
            assert housing.intersect(solid.translate(cq.Vector(0, 0, -0.05))).Volume() > 1e-4, name
    # The MLA, pushed in from below, stops against its corner tabs: raised by 0.05 mm it clashes
    # with all four, and it passes the film's ledge and the spacer on its way in.
    mla = placed["mla"][0].val().translate(cq.Vector(0, 0, design.imaging.mla_to_sensor_mm))
    raised = housing.intersect(mla.translate(cq.Vector(0, 0, 0.05)))
    assert raised.Volume() > 1e-6 and len(raised.Solids()) == 4
    steps = {s.name: s for s in bore_steps(design)}
    below = [steps[n] for n in ("film seat", "spacer") if n in steps]
    assert all(s.width_mm >= steps["MLA seat"].width_mm and s.length_mm >= steps["MLA seat"].length_mm for s in below)


def test_nothing_lies_under_the_mla_and_the_tabs_barely_reach_over_it(design, housing):
    # Under the array's flat face each lenslet's beam is narrow: the housing leaves the whole
    # footprint of the array (plus the rays' spread: the spacer) open down to the film.
    steps = {s.name: s for s in bore_steps(design)}
    spacer = steps["spacer"]
    probe = cq.Solid.makeBox(
        spacer.width_mm - 0.02,
        spacer.length_mm - 0.02,
        spacer.z1_mm - spacer.z0_mm - 0.02,
        cq.Vector(-spacer.width_mm / 2 + 0.01, -spacer.length_mm / 2 + 0.01, spacer.z0_mm + 0.01),
    )
    assert housing.intersect(probe).Volume() < 1e-9
    # Over the lenses, only the four tabs: a triangle of legs lip_mm over each corner of the array.
    tabs = mla_tab_geometry(design)
    half_w, half_l = design.mla.width_mm / 2, design.mla.length_mm / 2
    over = cq.Solid.makeBox(2 * half_w, 2 * half_l, tabs.z1_mm - tabs.z0_mm, cq.Vector(-half_w, -half_l, tabs.z0_mm))
    lip = design.mla_housing.lip_mm
    assert housing.intersect(over).Volume() == pytest.approx(4 * lip * lip / 2 * (tabs.z1_mm - tabs.z0_mm), rel=1e-6)


def test_bore_steps_stack_upwards(design):
    steps = bore_steps(design)
    assert all(a.z1_mm == pytest.approx(b.z0_mm) for a, b in zip(steps, steps[1:], strict=False))
