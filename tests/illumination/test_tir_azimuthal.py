"""A TIR wall that departs from revolution (``collimator.tir_cos2``, ``tir_cos4``): the design key,
the swept mesh the sweep traces, the CAD part, and the beam it bends."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from cm2optics.design import DesignError, load_preset
from cm2optics.illumination.revolve import revolve_profile
from cm2optics.optics.collimator import collimator_profile, tir_wall_reach_mm, tir_wall_scale

ENCLOSED = Path(__file__).resolve().parents[2] / "benchmarks" / "designs" / "cm2-v2-enclosed-spread.yaml"


@pytest.fixture(scope="module")
def enclosed():
    return load_preset(str(ENCLOSED))


def _wall_volume_change_mm3(profile, cos2: float, cos4: float, linear: bool) -> float:
    """ΔV (mm³) of the wall's departure against the revolved wall, in closed form: at height z the
    section's area is ½∮ R² dφ with R = r_e + d (1 + c₂ cos 2φ + c₄ cos 4φ), i.e. the revolved
    area plus (π/2)(c₂² + c₄²) d²; integrated over the wall (d(z) = r(z) − r_e, linear between the
    samples when ``linear``, as the swept mesh has it) and its step to the flange (d = d_end)."""
    d = profile.tir_r_mm - profile.outer_radius_entry_mm
    z = profile.tir_z_mm
    if linear:
        integral = float(np.sum(np.diff(z) * (d[:-1] ** 2 + d[:-1] * d[1:] + d[1:] ** 2) / 3))
    else:
        integral = float(np.trapezoid(d**2, z))
    integral += d[-1] ** 2 * (profile.flange_bottom_z_mm - z[-1])
    return math.pi / 2 * (cos2**2 + cos4**2) * integral


def test_default_is_the_revolved_wall_and_bad_terms_are_refused(enclosed):
    zero = enclosed.with_changes({"collimator.tir_cos2": 0.0, "collimator.tir_cos4": 0.0})
    assert not zero.collimator.tir_is_freeform
    assert zero.parameter_hash() == enclosed.parameter_hash() and "tir_cos2" not in zero.to_yaml()
    moved = enclosed.with_changes({"collimator.tir_cos2": 0.03})
    assert moved.collimator.tir_is_freeform and "tir_cos2: 0.03" in moved.to_yaml()
    profile = collimator_profile(enclosed)
    assert np.array_equal(revolve_profile(profile, 64).vertices, revolve_profile(profile, 64, (), (0.0, 0.0)).vertices)
    with pytest.raises(DesignError, match="tir_cos2"):
        enclosed.with_changes({"collimator.tir_cos2": 0.45})
    with pytest.raises(DesignError, match="tir_cos2"):
        enclosed.with_changes({"collimator.tir_cos2": 0.3, "collimator.tir_cos4": -0.3})
    # The wall ends at r = 1.954 mm, 0.834 mm out from its 1.12-mm entry ring: a scale of 1.06 on
    # a flange side (φ = 0 or 90°) reaches past the 4-mm footprint's half-width.
    with pytest.raises(DesignError, match="footprint must exceed"):
        collimator_profile(enclosed.with_changes({"collimator.tir_cos2": 0.06}))
    with pytest.raises(DesignError, match="footprint must exceed"):
        collimator_profile(enclosed.with_changes({"collimator.tir_cos2": -0.06}))
    collimator_profile(enclosed.with_changes({"collimator.tir_cos2": 0.2, "collimator.tir_cos4": -0.2}))


def test_reach_and_scale_closed_forms():
    phi = np.array([0.0, math.pi / 4, math.pi / 2])
    assert np.allclose(tir_wall_scale(0.1, -0.2, phi), [0.9, 1.2, 0.7])
    assert tir_wall_reach_mm(1.0, 1.8, 0.0, 0.0) == pytest.approx(1.8)
    # c₂ = 0.1: r = 1 + 0.8·1.1 = 1.88 at φ = 0, the farthest point. With c₄ = −0.2 the wall is
    # 1 + 0.8·0.9 = 1.72 mm out at φ = 0 but swells towards the diagonals (1.96 mm at 45°) faster
    # than cos φ falls: its farthest reach lies off the axis, as the section's own points say.
    assert tir_wall_reach_mm(1.0, 1.8, 0.1, 0.0) == pytest.approx(1.88, abs=1e-9)
    phi = np.linspace(0, 2 * np.pi, 200_001)
    r = 1.0 + 0.8 * (1 + 0.1 * np.cos(2 * phi) - 0.2 * np.cos(4 * phi))
    farthest = np.max(np.maximum(np.abs(r * np.cos(phi)), np.abs(r * np.sin(phi))))
    assert 1.72 < tir_wall_reach_mm(1.0, 1.8, 0.1, -0.2) == pytest.approx(farthest, abs=1e-4)


def test_swept_mesh_carries_the_wall_analytic_volume_and_mirror_symmetry(enclosed):
    """The sweep's mesh: only the outer wall moves, its volume changes by the closed form, it is
    mirror-symmetric about the unit's two planes, and the wall still widens upwards everywhere."""
    from cm2optics.illumination.optimize import TIR_AZIMUTHAL_PARAMETERS, candidate_collimator, search_box

    assert search_box(True, fixed_profile=True, tir_azimuthal=True).keys() >= TIR_AZIMUTHAL_PARAMETERS.keys()
    c2, c4 = 0.05, -0.2
    design, mesh, profile = candidate_collimator(enclosed, {"collimator.tir_cos2": c2, "collimator.tir_cos4": c4}, 256)
    assert (design.collimator.tir_cos2, design.collimator.tir_cos4) == (c2, c4)
    revolved = revolve_profile(profile, 256)
    v, v0 = mesh.mesh.vertices, revolved.vertices
    moved = np.linalg.norm(v - v0, axis=1) > 1e-12
    assert moved.any()
    assert np.all(np.hypot(*v0[moved, :2].T) > profile.outer_radius_entry_mm + 1e-9)  # the wall only
    assert np.all(v[:, :2].max(axis=0) <= profile.footprint_mm / 2 + 1e-12)
    # The 256-gon's chords cut ≈ (Δφ²/4)⟨R′²⟩ of each section's area: 0.5 % of the change here.
    expected = _wall_volume_change_mm3(profile, c2, c4, linear=True)
    assert mesh.mesh.volume - revolved.volume == pytest.approx(expected, rel=1e-2)
    tree = cKDTree(v)  # the rings' azimuths are symmetric about both planes: so must the vertices be
    for mirror in ([-1, 1, 1], [1, -1, 1]):
        assert np.max(tree.query(v * mirror)[0]) < 1e-9
    wall = mesh.mesh.face_normals[np.all(np.isin(mesh.mesh.faces, np.flatnonzero(moved)), axis=1)]
    assert len(wall) > 1000 and np.all(wall[:, 2] < 1e-9)  # outwards and downwards: no overhang


@pytest.mark.slow
def test_cad_part_is_watertight_printable_and_carries_the_wall(enclosed):
    """The CAD part (a lofted wall): one closed, consistently wound solid, walls ≥ 0.4 mm, its
    volume change between two sets of terms the closed form's, its STL mirror-symmetric."""
    from cm2optics.cad.collimator import build_collimator
    from cm2optics.cad.mesh_checks import check_mesh
    from cm2optics.cad.tessellate import export_stl

    profile = collimator_profile(enclosed)
    meshes, volumes = {}, {}
    for terms in ((0.05, -0.2), (0.2, -0.2)):
        design = enclosed.with_changes({"collimator.tir_cos2": terms[0], "collimator.tir_cos4": terms[1]})
        solid = build_collimator(design).val()
        volumes[terms] = solid.Volume()  # the B-rep's own (the STL's chords move it by ~0.01 mm³)
        with tempfile.TemporaryDirectory() as folder:
            export_stl(solid, Path(folder) / "c.stl", 0.002)
            meshes[terms] = trimesh.load_mesh(Path(folder) / "c.stl", force="mesh")
    report = check_mesh(meshes[(0.05, -0.2)])
    assert report.watertight and report.winding_consistent
    assert report.min_wall_mm >= enclosed.mechanics.min_wall_mm - 1e-3
    change = volumes[(0.2, -0.2)] - volumes[(0.05, -0.2)]
    expected = _wall_volume_change_mm3(profile, 0.2, -0.2, False) - _wall_volume_change_mm3(profile, 0.05, -0.2, False)
    assert change == pytest.approx(expected, rel=0.02)
    v = meshes[(0.2, -0.2)].vertices
    query = trimesh.proximity.ProximityQuery(meshes[(0.2, -0.2)])
    for mirror in ([-1, 1, 1], [1, -1, 1]):
        # within twice the STL's 2-µm chord tolerance (a c₂ = 0.2 wall moves ≈ 0.17 mm between φ = 0 and 90°)
        assert np.max(np.abs(query.signed_distance(v[::50] * mirror))) < 4e-3


@pytest.mark.slow
def test_wall_bends_rays_in_its_two_planes_as_the_scaled_section_does(enclosed):
    """Rays from the LED's centre in the unit's two planes (φ = 0: x–z, across the plane of tilt;
    φ = 90°: y–z, in it) meet the wall where its normal lies in their plane (∂R/∂φ = 0 there), so
    each leaves as the 2-D trace of the revolved section with its wall scaled by 1 ± c₂
    (:func:`~cm2optics.optics.collimator.trace_meridional`) says: c₂ < 0 flattens the wall in the
    plane of tilt (its rays leave closer to the axis) and steepens it across (further out)."""
    import dataclasses

    from cm2optics.design.materials import Material
    from cm2optics.illumination.excitation import TransmissionTable
    from cm2optics.illumination.geometry import IlluminationScene, Medium, Part, Role, corner_normals
    from cm2optics.illumination.tracer import EmittedBatch, trace_rays
    from cm2optics.optics.collimator import trace_meridional

    c2 = -0.05
    profile = collimator_profile(enclosed)
    mesh = revolve_profile(profile, 512, (), (c2, 0.0))
    z_out = profile.exit_z_mm + 0.05
    portal = np.array([[-9, -9, z_out], [9, -9, z_out], [9, 9, z_out], [-9, 9, z_out]], dtype=float)
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    n = profile.refractive_index
    scene = IlluminationScene(
        design=enclosed,
        label="tir-cos2",
        parts=(
            Part("collimator", vertices, faces, Role.DIELECTRIC, corner_normals=corner_normals(vertices, faces)),
            Part("portal", portal, quad, Role.PORTAL),
            Part("sample", portal + [0, 0, 20.0], quad, Role.SAMPLE),
        ),
        poses=np.eye(4)[None],
        collimator=None,
        has_filter=False,
        has_housing=False,
        filter_material=Material.N_BK7,
        portal_z_mm=z_out,
        index_override={Medium.COLLIMATOR: lambda wl: np.full_like(wl, n)},
    )
    theta = np.radians(np.linspace(48.0, 76.0, 8))
    for phi, scale in ((0.0, 1 + c2), (math.pi / 2, 1 - c2)):
        d = np.column_stack([np.sin(theta) * math.cos(phi), np.sin(theta) * math.sin(phi), np.cos(theta)])
        batch = EmittedBatch(np.zeros(len(d), np.int32), np.zeros_like(d), d, np.full(len(d), 470.0), 1.0)
        record = trace_rays(scene, batch, TransmissionTable(0.0, 1.0, math.pi / 2, np.ones((2, 2))), seed=1)
        assert record.passed.all()
        out = record.exit_direction
        traced = np.degrees(np.arctan2(out[:, 0] * math.cos(phi) + out[:, 1] * math.sin(phi), out[:, 2]))
        assert np.allclose(out[:, 0] * math.sin(phi) - out[:, 1] * math.cos(phi), 0.0, atol=1e-3)  # in its plane
        entry = profile.outer_radius_entry_mm
        wall = entry + scale * (profile.tir_r_mm - entry)
        scaled = dataclasses.replace(profile, tir_r_mm=wall, outer_radius_exit_mm=float(wall[-1]))
        expected = np.degrees(trace_meridional(scaled, 0.0, theta).exit_angle_rad)
        revolved = np.degrees(trace_meridional(profile, 0.0, theta).exit_angle_rad)
        assert np.all(np.isfinite(expected))
        # Within 0.01° but for at most one ray: near the wall's top ring the swept mesh's smooth
        # normals round the corner onto the step below the flange (the CAD part keeps its faces).
        assert np.sum(np.abs(traced - expected) < 0.01) >= len(theta) - 1
        # The crossing beam leaves on the other side of the axis (negative angles): flatter in the
        # plane of tilt, it leaves closer to the axis; steeper across it, further out.
        moved = np.abs(expected) - np.abs(revolved)
        assert np.all(moved < -0.5) if scale > 1 else np.all(moved > 0.5)
