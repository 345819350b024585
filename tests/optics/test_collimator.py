"""Freeform TIR collimator: profile against closed forms, ray collimation, the solid, and the
authors' part."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import cadquery as cq
import numpy as np
import pytest
import trimesh

from cm2optics.cad.collimator import VERTEX_FLAT_SAG_MM, build_collimator, compare_with_reference
from cm2optics.design import Collimator, DesignError, load_preset
from cm2optics.design.materials import Material, refractive_index
from cm2optics.optics import collimator as collimator_module
from cm2optics.optics.collimator import Surface, collimator_profile, profile_from_parameters, trace_meridional

REFERENCE = Path(__file__).resolve().parents[2].parent / "shared/reference/cm2-v2"


@pytest.fixture(scope="module")
def design(v2_collimating):
    """The paper's collimating architecture (the shaped, freeform default has its own tests)."""
    return v2_collimating


@pytest.fixture(scope="module")
def profile(design):
    return collimator_profile(design)


@pytest.fixture(scope="module")
def solid(design):
    return build_collimator(design)


@pytest.fixture(scope="module")
def focus_fan(profile):
    """Rays from the focus over the whole cavity opening (just inside its mouth ray)."""
    limit = math.radians(profile.max_angle_deg - 0.05)
    return trace_meridional(profile, 0.0, np.linspace(-limit, limit, 2001))


# ----------------------------------------------------------------------------- profile


def test_optics_module_does_not_import_cadquery():
    tree = ast.parse(Path(collimator_module.__file__).read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            imported.add(node.module.split(".")[0])
    assert "cadquery" not in imported and "OCP" not in imported


def test_index_is_the_material_at_the_led_peak(design, profile):
    assert profile.wavelength_nm == design.led.peak_nm
    expected = refractive_index(Material.CLEAR_RESIN, design.led.peak_nm)
    assert profile.refractive_index == pytest.approx(expected, abs=1e-12)


def test_lens_vertex_and_sag_match_the_hyperbola(design, profile):
    col, n = design.collimator, profile.refractive_index
    a, theta = col.cavity_radius_mm, math.radians(col.lens_half_angle_deg)
    vertex = (a / math.sin(theta)) * (n * math.cos(theta) - 1.0) / (n - 1.0)
    assert profile.lens_vertex_z_mm == pytest.approx(vertex, abs=1e-12)
    assert profile.lens_sag_mm == pytest.approx(a / math.tan(theta) - vertex, abs=1e-12)
    # Every sample on the conic of vertex radius d(n − 1) and conic constant −n².
    c, k = 1.0 / (vertex * (n - 1.0)), -(n**2)
    r = profile.lens_r_mm
    sag = c * r**2 / (1.0 + np.sqrt(1.0 - (1.0 + k) * c**2 * r**2))
    np.testing.assert_allclose(profile.lens_z_mm - vertex, sag, atol=1e-9)
    assert profile.lens_r_mm[-1] == pytest.approx(a) and profile.lens_r_mm[0] == 0.0


def test_equal_optical_paths_from_the_focus_to_the_exit_face(profile):
    """Malus–Dupin: a collimated beam is a plane wavefront, so the optical path from the focus
    to the exit face is the same along every designed ray (lens rays and TIR rays alike)."""
    n, top = profile.refractive_index, profile.exit_z_mm
    lens_path = np.hypot(profile.lens_r_mm, profile.lens_z_mm) + n * (top - profile.lens_z_mm)
    assert np.ptp(lens_path) < 1e-9
    a = profile.cavity_radius_mm
    wall_z = a / np.tan(np.radians(profile.tir_angle_deg))
    inside = np.hypot(profile.tir_r_mm - a, profile.tir_z_mm - wall_z)
    tir_path = np.hypot(a, wall_z) + n * inside + n * (top - profile.tir_z_mm)
    assert np.ptp(tir_path) < 1e-7


def test_tir_margin_is_positive_and_smallest_on_the_mouth_ray(profile):
    n = profile.refractive_index
    psi = math.acos(math.cos(math.radians(profile.max_angle_deg)) / n)  # in-material angle from the axis
    expected = 90.0 - math.degrees(psi) / 2 - math.degrees(math.asin(1.0 / n))
    assert profile.min_tir_margin_deg > 0.0
    assert profile.min_tir_margin_deg == pytest.approx(expected, abs=1e-9)


def test_envelope_matches_the_design(design, profile):
    col = design.collimator
    assert profile.entry_z_mm == col.led_gap_mm
    assert profile.height_mm == pytest.approx(col.height_mm)
    assert 1.0 <= profile.height_mm <= 2.0
    assert profile.exit_z_mm - profile.flange_bottom_z_mm == pytest.approx(col.flange_mm)
    assert profile.footprint_mm == col.footprint_mm == 4.0
    assert profile.exit_z_mm <= design.led_array.excitation_gap_mm
    # The TIR surface ends under the flange and inside the footprint.
    assert profile.tir_end_z_mm <= profile.flange_bottom_z_mm
    assert profile.outer_radius_exit_mm < col.footprint_mm / 2
    assert np.all(np.diff(profile.tir_z_mm) > 0) and np.all(np.diff(profile.tir_r_mm) > 0)
    # The cavity covers the emitter's width.
    assert col.cavity_radius_mm > design.led.emitter_mm / 2


def test_walls_are_printable(design, profile):
    col, min_wall = design.collimator, design.mechanics.min_wall_mm
    assert profile.outer_radius_entry_mm - col.cavity_radius_mm >= min_wall - 1e-12
    assert profile.exit_z_mm - profile.lens_vertex_z_mm >= min_wall
    assert col.flange_mm >= min_wall
    assert profile.min_wall_mm >= min_wall - 1e-12


# ----------------------------------------------------------------------------- rays


def test_point_source_lens_rays_leave_parallel(focus_fan):
    lens = focus_fan.first_surface == Surface.LENS
    assert lens.sum() > 500
    assert np.all(focus_fan.exited[lens])
    assert np.degrees(np.abs(focus_fan.exit_angle_rad[lens])).max() < 0.1


def test_point_source_cavity_rays_are_reflected_and_leave_parallel(focus_fan):
    wall = focus_fan.first_surface == Surface.CAVITY
    assert wall.sum() > 500
    assert np.all(focus_fan.tir_reflections[wall] == 1)
    assert np.all(focus_fan.exited[wall])
    assert np.degrees(np.abs(focus_fan.exit_angle_rad[wall])).max() < 0.5


def test_every_ray_into_the_cavity_is_collimated(profile, focus_fan):
    assert set(np.unique(focus_fan.first_surface)) == {Surface.LENS, Surface.CAVITY}
    assert np.all(focus_fan.exited)
    # Lens rays leave within the cavity's radius, TIR rays beyond the outer surface's start.
    lens = focus_fan.first_surface == Surface.LENS
    assert np.abs(focus_fan.exit_x_mm[lens]).max() <= profile.cavity_radius_mm + 1e-9
    assert np.abs(focus_fan.exit_x_mm[~lens]).min() > profile.outer_radius_entry_mm


def test_traced_tir_margins_match_the_profile(profile, focus_fan):
    margins = np.degrees(focus_fan.tir_margin_rad[np.isfinite(focus_fan.tir_margin_rad)])
    assert margins.min() > 0.0
    assert margins.min() == pytest.approx(profile.min_tir_margin_deg, abs=0.05)


def test_exit_angle_sign_follows_the_geometry(profile):
    """A source moved +x sends its ray through the lens vertex towards −x."""
    h = 0.1
    trace = trace_meridional(profile, h, math.atan2(-h, profile.lens_vertex_z_mm))
    assert trace.first_surface == Surface.LENS
    assert trace.exit_angle_rad < 0


def test_finite_emitter_spreads_by_its_size_over_the_focal_distance(design, profile):
    f, half = profile.lens_vertex_z_mm, design.led.emitter_mm / 2
    angles = np.radians(np.linspace(-85.0, 85.0, 3401))
    # The ray through the vertex meets the lens and the exit face as a plane-parallel plate.
    chief = trace_meridional(profile, half, math.atan2(-half, f))
    assert math.degrees(chief.exit_angle_rad) == pytest.approx(-math.degrees(math.atan(half / f)), abs=0.01)
    edge = trace_meridional(profile, half, angles)
    lens = (edge.first_surface == Surface.LENS) & edge.exited
    spread = np.degrees(np.abs(edge.exit_angle_rad[lens])).max()
    assert 1.0 <= spread / math.degrees(math.atan(half / f)) <= 1.4
    # Near the axis the spread is atan(h / f) itself and scales with h.
    near = trace_meridional(profile, 0.05, angles)
    lens_near = (near.first_surface == Surface.LENS) & near.exited
    spread_near = np.degrees(np.abs(near.exit_angle_rad[lens_near])).max()
    assert spread_near == pytest.approx(math.degrees(math.atan(0.05 / f)), rel=0.02)
    # The TIR path is longer than the lens's focal distance: it collimates the emitter better.
    tir = (edge.first_surface == Surface.CAVITY) & edge.exited
    assert np.median(np.abs(edge.exit_angle_rad[tir])) < 0.5 * np.median(np.abs(edge.exit_angle_rad[lens]))


# ----------------------------------------------------------------------------- infeasible designs


def test_lens_beyond_the_hyperbola_asymptote_is_rejected(design):
    col = design.collimator
    bad = Collimator(**{**col.__dict__, "lens_half_angle_deg": 50.0})  # arccos(1/1.516) ≈ 48.7°
    with pytest.raises(DesignError) as error:
        profile_from_parameters(bad, design.led.peak_nm)
    assert error.value.field == "collimator.lens_half_angle_deg"


def test_too_low_a_collimator_is_rejected_with_the_height_it_needs(design, profile):
    needed = profile.tir_end_z_mm + design.collimator.flange_mm - design.collimator.led_gap_mm

    def with_height(height_mm: float):
        # The excitation filter rests on the exit face: its gap follows the height.
        gap = design.collimator.led_gap_mm + height_mm
        return design.with_changes({"collimator.height_mm": height_mm, "led_array.excitation_gap_mm": gap})

    with pytest.raises(DesignError) as error:
        collimator_profile(with_height(needed - 0.01))
    assert error.value.field == "collimator.height_mm"
    assert f"needs ≥ {needed:.3f}" in error.value.allowed
    assert collimator_profile(with_height(needed + 1e-6)).tir_end_z_mm <= needed


def test_a_thin_entry_wall_is_rejected(design):
    with pytest.raises(DesignError) as error:
        collimator_profile(design.with_changes({"collimator.entry_wall_mm": 0.3}))
    assert error.value.field == "collimator"


def test_collimator_fields_are_validated(design):
    with pytest.raises(DesignError) as error:
        Collimator(**{**design.collimator.__dict__, "entry_wall_mm": 1.5})
    assert error.value.field == "entry_wall_mm"


def test_a_v1_design_has_no_collimator_profile():
    with pytest.raises(DesignError) as error:
        collimator_profile(load_preset("cm2-v1"))
    assert error.value.field == "collimator"


# ----------------------------------------------------------------------------- the solid


def test_solid_is_one_valid_watertight_solid(solid, tmp_path):
    assert len(solid.solids().vals()) == 1
    shape = solid.val()
    assert isinstance(shape, cq.Solid) and shape.isValid()
    path = tmp_path / "collimator.stl"
    cq.exporters.export(solid, str(path), tolerance=0.002, angularTolerance=0.05)
    mesh = trimesh.load_mesh(path)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(shape.Volume(), rel=2e-3)


def test_solid_envelope_is_the_design_footprint_and_height(design):
    # A copy without the triangulation (the part is built once per process and other tests
    # export it): OpenCascade bounds a tessellated shape's triangles instead.
    col, box = design.collimator, build_collimator(design).val().copy(mesh=False).BoundingBox()
    assert (box.xmin, box.xmax, box.ymin, box.ymax) == pytest.approx((-2.0, 2.0, -2.0, 2.0), abs=1e-6)
    assert (box.zmin, box.zmax) == pytest.approx((col.led_gap_mm, col.led_gap_mm + col.height_mm), abs=1e-6)


def test_solid_volume_matches_pappus(profile, solid):
    """2π ∫∫ r dA of the revolved half-section (Green's theorem on the sampled polygon), plus
    the flange's corners outside the revolved body."""
    a, g = profile.cavity_radius_mm, profile.entry_z_mm
    r_end = profile.outer_radius_exit_mm
    polygon = np.vstack(
        [
            [[0.0, profile.exit_z_mm]],
            np.column_stack([profile.lens_r_mm, profile.lens_z_mm]),
            [[a, g], [profile.outer_radius_entry_mm, g]],
            np.column_stack([profile.tir_r_mm, profile.tir_z_mm]),
            [[r_end, profile.exit_z_mm]],
        ]
    )
    r, z = polygon[:, 0], polygon[:, 1]
    r1, z1 = np.roll(r, -1), np.roll(z, -1)
    first_moment = abs(np.sum((r * r + r * r1 + r1 * r1) * (z1 - z)) / 6.0)
    flange = profile.exit_z_mm - profile.flange_bottom_z_mm
    volume = 2 * math.pi * first_moment + (profile.footprint_mm**2 - math.pi * r_end**2) * flange
    assert solid.val().Volume() == pytest.approx(volume, rel=1e-3)


def test_solid_surfaces_follow_the_computed_profile(profile, solid):
    faces = cq.Compound.makeCompound(solid.val().Faces())
    for r_samples, z_samples, tolerance in (
        (profile.lens_r_mm, profile.lens_z_mm, VERTEX_FLAT_SAG_MM * 1.01),
        (profile.tir_r_mm, profile.tir_z_mm, 1e-5),
    ):
        for i in np.linspace(0, len(r_samples) - 1, 25).astype(int):
            point = cq.Vertex.makeVertex(r_samples[i] * math.cos(0.7), r_samples[i] * math.sin(0.7), z_samples[i])
            assert faces.distance(point) < tolerance


# ----------------------------------------------------------------------------- the authors' part


def test_envelope_is_comparable_with_the_authors_part(design):
    stl = REFERENCE / "CM2_V2_freeform_illuminator.stl"
    if not stl.is_file():
        pytest.skip(f"the authors' reference part is not on this machine ({stl}); it lives outside the repository")
    table = compare_with_reference(design, stl)
    ours = {key: value["ours"] for key, value in table.items()}
    theirs = {key: value["reference"] for key, value in table.items()}
    assert ours["watertight"] and theirs["watertight"]
    np.testing.assert_allclose(ours["extent_mm"][:2], theirs["extent_mm"][:2], atol=0.01)  # 4 × 4 mm both
    assert ours["exit_face_side_mm"] == pytest.approx(theirs["exit_face_side_mm"], abs=0.01)
    assert theirs["height_mm"] == pytest.approx(2.0, abs=0.01)
    assert ours["height_mm"] == pytest.approx(design.collimator.height_mm, abs=1e-3)
    assert 0.8 < ours["volume_mm3"] / theirs["volume_mm3"] < 1.2
    assert ours["cavity_radius_mm"] == pytest.approx(design.collimator.cavity_radius_mm, abs=0.01)
    # Both TIR walls widen to ≈ 1.9 mm at the exit side.
    assert ours["outer_radius_range_mm"][1] == pytest.approx(theirs["outer_radius_range_mm"][1], abs=0.1)
