"""The printed MLA housing: one solid, watertight, walls and fits, no clash with its optics."""

from __future__ import annotations

import cadquery as cq
import pytest
import trimesh

from cm2optics.cad import components
from cm2optics.cad.mesh_checks import min_wall_thickness_mm
from cm2optics.cad.mla import build_mla
from cm2optics.cad.mla_housing import bore_steps, build_mla_housing, mla_housing_fits
from cm2optics.cad.tessellate import export_stl
from cm2optics.layout import mla_housing_envelope


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
    # The thinnest wall is the chamfered rim at the tower top: seat wall minus chamfer.
    expected = (
        (design.mla_housing.outer_mm - design.emission_filter.width_mm) / 2
        - design.mechanics.clearance_mm
        - design.mla_housing.chamfer_mm
    )
    assert wall == pytest.approx(expected, abs=0.01)


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
        if name in ("mla", "mask", "filter"):
            assert housing.intersect(solid.translate(cq.Vector(0, 0, -0.05))).Volume() > 1e-4, name


def test_bore_steps_stack_upwards(design):
    steps = bore_steps(design)
    assert all(a.z1_mm == pytest.approx(b.z0_mm) for a, b in zip(steps, steps[1:], strict=False))
