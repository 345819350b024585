"""The prescribed (cone) TIR wall and the truncated wall: profile against closed forms, the
YAML's fields, the solid, and the sweep's box and options."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from cm2optics.cad.collimator import build_collimator
from cm2optics.cad.mesh_checks import check_mesh
from cm2optics.cad.tessellate import export_stl
from cm2optics.design import DesignError, design_from_dict
from cm2optics.optics.collimator import collimator_profile

CONE = {
    "collimator.led_gap_mm": 0.0,
    "collimator.cavity_radius_mm": 0.73,
    "collimator.lens_half_angle_deg": 26.0,
    "collimator.entry_wall_mm": 0.4,
    "collimator.height_mm": 2.0,
    "led_array.excitation_gap_mm": 2.0,
    "collimator.tir_max_radius_mm": 1.95,
    "collimator.tir_cone_deg": 30.0,
    "collimator.tir_cone_curvature_per_mm": 0.0,
}


@pytest.fixture(scope="module")
def cone(v2_collimating):
    """The paper's collimating part with the LED at the cavity mouth and a 30° cone wall."""
    return v2_collimating.with_changes(CONE)


def test_cone_wall_is_the_prescribed_cone_up_to_its_radius(cone):
    profile = collimator_profile(cone)
    r0 = 0.73 + 0.4
    np.testing.assert_allclose(profile.tir_r_mm, r0 + math.tan(math.radians(30.0)) * profile.tir_z_mm, atol=1e-12)
    assert profile.tir_r_mm[0] == pytest.approx(r0) and profile.tir_z_mm[0] == 0.0
    assert profile.tir_r_mm[-1] == pytest.approx(1.95, abs=1e-12)
    assert profile.tir_z_mm[-1] == pytest.approx((1.95 - r0) / math.tan(math.radians(30.0)), abs=1e-9)


def test_cone_wall_angles_are_those_of_the_rays_from_the_led_centre(cone):
    """A ray leaving the LED's centre at 50° crosses the cavity wall at z_w = a / tan 50°, is
    refracted to u_z = cos 50° / n, and meets the cone where the closed form says: the wall
    point there reports that ray's angle."""
    profile = collimator_profile(cone)
    n, a, theta = profile.refractive_index, 0.73, math.radians(50.0)
    z_w, uz = a / math.tan(theta), math.cos(theta) / n
    ur, slope = math.sqrt(1 - uz**2), math.tan(math.radians(30.0))
    # a + s u_r = r0 + slope (z_w + s u_z)
    s = (1.13 + slope * z_w - a) / (ur - slope * uz)
    z_hit = z_w + s * uz
    angle = np.interp(z_hit, profile.tir_z_mm, profile.tir_angle_deg)
    assert angle == pytest.approx(50.0, abs=0.05)
    # incidence on the 30° cone: the normal (cos 30°, −sin 30°) against u
    incidence = math.degrees(math.acos(abs(ur * math.cos(math.radians(30)) - uz * math.sin(math.radians(30)))))
    assert profile.min_tir_margin_deg <= incidence - math.degrees(math.asin(1 / n)) + 1e-6


def test_truncation_keeps_the_designed_wall_below_the_radius(v2_collimating):
    whole = collimator_profile(v2_collimating)
    cut = collimator_profile(v2_collimating.with_changes({"collimator.tir_max_radius_mm": 1.5}))
    k = len(cut.tir_r_mm) - 1
    np.testing.assert_array_equal(cut.tir_r_mm[:k], whole.tir_r_mm[:k])
    np.testing.assert_array_equal(cut.tir_z_mm[:k], whole.tir_z_mm[:k])
    assert cut.tir_r_mm[-1] == pytest.approx(1.5) and whole.tir_r_mm[k] >= 1.5 > whole.tir_r_mm[k - 1]
    assert cut.outer_radius_exit_mm == pytest.approx(1.5)


def test_new_fields_leave_old_files_and_hashes_alone(v2, cone):
    collimator = v2.to_dict()["collimator"]
    assert not {"tir_max_radius_mm", "tir_cone_deg", "tir_cone_curvature_per_mm"} & set(collimator)
    data = cone.to_dict()
    assert data["collimator"]["tir_cone_deg"] == 30.0 and data["collimator"]["tir_max_radius_mm"] == 1.95
    again = design_from_dict(data)
    assert again == cone and again.parameter_hash() == cone.parameter_hash() != v2.parameter_hash()


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"collimator.tir_cone_deg": 30.0, "collimator.tir_spread_deg": 10.0}, "tir_cone_deg"),
        ({"collimator.tir_cone_curvature_per_mm": 0.2}, "tir_cone_curvature_per_mm"),
        ({"collimator.tir_max_radius_mm": 2.5}, "tir_max_radius_mm"),
        ({"collimator.tir_max_radius_mm": 0.9}, "tir_max_radius_mm"),
    ],
)
def test_bad_wall_fields_are_refused(v2_collimating, changes, field):
    with pytest.raises(DesignError) as error:
        v2_collimating.with_changes(changes)
    assert error.value.field == f"collimator.{field}"


def test_cone_wall_turning_inwards_is_refused(cone):
    with pytest.raises(DesignError, match="turns inwards"):
        collimator_profile(cone.with_changes({"collimator.tir_cone_curvature_per_mm": -1.5}))


def test_cone_part_with_the_led_at_the_mouth_is_a_printable_solid(cone, tmp_path):
    solid = build_collimator(cone)
    assert len(solid.solids().vals()) == 1 and solid.val().isValid()
    path = tmp_path / "collimator.stl"
    export_stl(solid.val(), path, 0.002)
    report = check_mesh(trimesh.load_mesh(path), wall_samples=4000)
    assert report.watertight and report.min_wall_mm >= cone.mechanics.min_wall_mm - 0.01
    (x0, y0, z0), (x1, y1, z1) = report.bbox_mm
    assert z0 == pytest.approx(0.0, abs=1e-6) and z1 == pytest.approx(2.0, abs=1e-6)


def test_cone_box_replaces_the_profile_box():
    from cm2optics.illumination.optimize import (
        AIM_PARAMETERS,
        CONE_PARAMETERS,
        CONE_WALL_FIELDS,
        _changes,
        search_box,
    )

    assert search_box(True, cone_wall=True) == CONE_PARAMETERS | AIM_PARAMETERS
    assert CONE_PARAMETERS["collimator.cavity_radius_mm"][0] > math.hypot(0.5, 0.5)  # encloses the 1-mm emitter
    assert _changes({"collimator.tir_cone_deg": 30.0}, design=_Stub())["collimator.tir_spread_deg"] == 0.0
    # the designed wall swept from a cone-wall base drops the base's cone, whole
    designed = _changes({"collimator.tir_spread_deg": 10.0}, design=_Stub())
    assert all(designed[f"collimator.{name}"] == 0.0 for name in CONE_WALL_FIELDS)


class _Stub:
    collimator = None


def test_cli_refuses_cone_wall_with_fixed_profile(tmp_path):
    from typer.testing import CliRunner

    from cm2optics.cli import app

    result = CliRunner().invoke(
        app, ["illum", "optimize", "--cone-wall", "--fixed-profile", "--free-aim", "--out", str(tmp_path / "o")]
    )
    assert result.exit_code == 2 and "--cone-wall" in result.output
    assert not (tmp_path / "o").exists()
