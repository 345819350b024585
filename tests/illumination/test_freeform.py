"""Freeform lens: Zernike sag, the part the CAD module builds from it, and the beam it bends."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cm2optics.cad.collimator import build_collimator
from cm2optics.cad.mesh_checks import check_mesh
from cm2optics.cad.tessellate import export_stl
from cm2optics.design.materials import Material
from cm2optics.illumination.excitation import TransmissionTable
from cm2optics.illumination.geometry import IlluminationScene, Medium, Part, Role
from cm2optics.illumination.revolve import revolve_profile
from cm2optics.illumination.tracer import EmittedBatch, trace_rays
from cm2optics.optics.collimator import collimator_profile
from cm2optics.optics.freeform import lens_sag_mm, noll_indices, zernike

NO_FILTER = TransmissionTable(0.0, 1.0, math.pi / 2, np.ones((2, 2)))


def _stl_mesh(design) -> trimesh.Trimesh:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "c.stl"
        export_stl(build_collimator(design).val(), path, 0.002)
        return trimesh.load_mesh(path, force="mesh")


def test_noll_zernike_terms_are_the_textbook_ones_and_orthonormal():
    assert [noll_indices(j) for j in range(1, 12)] == [
        (0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1), (3, 1), (3, -3), (3, 3), (4, 0)
    ]  # fmt: skip
    rng = np.random.default_rng(0)
    rho, phi = np.sqrt(rng.uniform(0, 1, 400_000)), rng.uniform(0, 2 * np.pi, 400_000)
    z = np.array([zernike(j, rho, phi) for j in range(1, 16)])
    gram = z @ z.T / rho.size  # ⟨Z_i Z_j⟩ over the unit disc
    assert np.allclose(gram, np.eye(15), atol=0.02)
    assert np.allclose(zernike(2, rho, phi), 2 * rho * np.cos(phi))
    assert np.allclose(zernike(4, rho, phi), math.sqrt(3) * (2 * rho**2 - 1))
    # c₂ = 10 µm over a 0.5-mm radius: a plane of slope 2·0.010/0.5 = 0.04.
    x = np.array([-0.2, 0.0, 0.3])
    assert np.allclose(lens_sag_mm((0.0, 10.0), x, np.zeros(3), 0.5), 0.04 * x)
    # Past the rim (x = 0.6 mm): clipped, the rim's sag 0.02 mm; unclipped, the plane goes on.
    assert lens_sag_mm((0.0, 10.0), np.array([0.6]), np.zeros(1), 0.5) == pytest.approx(0.02)
    assert lens_sag_mm((0.0, 10.0), np.array([0.6]), np.zeros(1), 0.5, clip=False) == pytest.approx(0.024)


@pytest.fixture(scope="module")
def revolved(v2):
    """cm2-v2 with its lens's Zernike terms removed: the revolved part of the same profile."""
    design = v2.with_changes({"collimator.lens_freeform_um": []})
    assert v2.collimator.is_freeform and not design.collimator.is_freeform
    return design


def test_zero_freeform_terms_reproduce_the_revolved_part(revolved):
    zero = revolved.with_changes({"collimator.lens_freeform_um": [0.0, 0.0, 0.0]})
    assert not zero.collimator.is_freeform
    assert zero.parameter_hash() == revolved.parameter_hash()  # and the same YAML
    a, b = _stl_mesh(revolved), _stl_mesh(zero)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    profile = collimator_profile(revolved)
    assert np.array_equal(revolve_profile(profile, 64).vertices, revolve_profile(profile, 64, (0.0, 0.0)).vertices)


def test_freeform_part_is_watertight_printable_and_carries_the_sag(v2_collimating):
    """The CAD part with a tilt and a defocus term on the collimating (hyperbolic) lens: one
    closed solid, walls ≥ 0.4 mm, its lens vertices on the displaced hyperbola within 0.1 µm (the
    tracer reads this mesh)."""
    coefficients = (0.0, 15.0, -8.0, 6.0)
    design = v2_collimating.with_changes({"collimator.lens_freeform_um": list(coefficients)})
    mesh = _stl_mesh(design)
    report = check_mesh(mesh)
    assert report.watertight and report.winding_consistent
    assert report.min_wall_mm >= design.mechanics.min_wall_mm - 1e-4
    profile = collimator_profile(v2_collimating)
    a = profile.cavity_radius_mm
    v = mesh.vertices
    r = np.hypot(v[:, 0], v[:, 1])
    lens = (r < 0.95 * a) & (v[:, 2] > profile.entry_z_mm) & (v[:, 2] < profile.exit_z_mm - 0.1)
    assert lens.sum() > 50
    expected = profile.lens_height_mm(r[lens]) + lens_sag_mm(coefficients, v[lens, 0], v[lens, 1], a)
    assert np.max(np.abs(v[lens, 2] - expected)) < 1e-4  # STL vertices lie on the face, fitted to ≈ 10 nm
    # Every Zernike term but piston has zero mean over the lens disc: the volume stays.
    assert mesh.volume == pytest.approx(_stl_mesh(v2_collimating).volume, rel=1e-3)


def test_default_freeform_lens_is_one_smooth_face_on_the_sag(v2, tmp_path):
    """The default's lens is one B-spline face: its points over the cavity's disc (a 60 × 60
    grid of its parameters) lie within 1 µm of ``z_lens(r) + S(x, y)`` (the profile's 401 lens
    points interpolated, the Zernike sag); the part's STEP file stays small (not a faceted
    solid)."""
    from OCP.BRep import BRep_Tool

    from cm2optics.cad.tessellate import export_step

    part = build_collimator(v2)
    splines = [f for f in part.faces().vals() if f.geomType() == "BSPLINE"]
    assert len(splines) == 1
    surface = BRep_Tool.Surface_s(splines[0].wrapped)
    u0, u1, v0, v1 = surface.Bounds()
    points = np.array([surface.Value(u, v).Coord() for u in np.linspace(u0, u1, 60) for v in np.linspace(v0, v1, 60)])
    profile = collimator_profile(v2)
    a = profile.cavity_radius_mm
    r = np.hypot(points[:, 0], points[:, 1])
    points, r = points[r < a], r[r < a]
    assert len(points) > 2000
    expected = np.interp(r, profile.lens_r_mm, profile.lens_z_mm) + lens_sag_mm(
        v2.collimator.lens_freeform_um, points[:, 0], points[:, 1], a
    )
    assert np.max(np.abs(points[:, 2] - expected)) < 1e-3
    export_step(part, tmp_path / "c.step")
    assert (tmp_path / "c.step").stat().st_size < 500_000


def test_lens_tilt_term_deflects_the_beam_by_the_closed_form_angle(v2):
    """A Z₂ term c tilts the lens by α = atan(2c/a): a ray from the LED along the axis meets it
    at incidence α, refracts to β = asin(sin α / n) from the normal, runs α − β off the axis and
    leaves the flat exit face at γ = asin(n sin(α − β)), towards −x."""
    n = 1.5
    profile = collimator_profile(v2)
    a = profile.cavity_radius_mm
    alpha = math.radians(4.0)
    c_um = 1e3 * a * math.tan(alpha) / 2
    gamma = math.asin(n * math.sin(alpha - math.asin(math.sin(alpha) / n)))
    exit_z = profile.exit_z_mm
    directions = {}
    for label, terms in (("revolved", ()), ("tilted", (0.0, c_um))):
        mesh = revolve_profile(profile, 256, terms)
        portal = np.array(
            [[-9, -9, exit_z + 0.05], [9, -9, exit_z + 0.05], [9, 9, exit_z + 0.05], [-9, 9, exit_z + 0.05]]
        )
        plane = portal + [0, 0, 20.0]
        quad = np.array([[0, 1, 2], [0, 2, 3]])
        scene = IlluminationScene(
            design=v2,
            label=label,
            parts=(
                Part("collimator", np.asarray(mesh.vertices), np.asarray(mesh.faces), Role.DIELECTRIC),
                Part("portal", portal, quad, Role.PORTAL),
                Part("sample", plane, quad, Role.SAMPLE),
            ),
            poses=np.eye(4)[None],
            collimator=None,
            has_filter=False,
            has_housing=False,
            filter_material=Material.N_BK7,
            portal_z_mm=exit_z + 0.05,
            index_override={Medium.COLLIMATOR: lambda wl: np.full_like(wl, n)},
        )
        # A thin cone (0.3° from the axis) from the LED centre: it meets the lens near its vertex.
        phi = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
        theta = math.radians(0.3)
        d = np.column_stack(
            [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.full(phi.size, np.cos(theta))]
        )
        batch = EmittedBatch(np.zeros(phi.size, np.int32), np.zeros_like(d), d, np.full(phi.size, 470.0), 1.0)
        record = trace_rays(scene, batch, NO_FILTER, seed=1)
        out = record.exit_direction[record.passed & (record.bounces == 4)]  # lens, exit face, portal, sample
        assert len(out) > 1500
        directions[label] = np.median(out, axis=0)
    assert math.degrees(math.atan2(directions["revolved"][0], directions["revolved"][2])) == pytest.approx(
        0.0, abs=0.02
    )
    deflection = math.atan2(-directions["tilted"][0], directions["tilted"][2])
    assert math.degrees(deflection) == pytest.approx(math.degrees(gamma), abs=0.01)
    assert abs(directions["tilted"][1]) < 1e-3


def test_freeform_sweep_candidates_carry_their_zernike_terms(v2):
    from cm2optics.illumination.optimize import AIM_PARAMETERS, FREEFORM_PARAMETERS, candidate_collimator, search_box

    assert search_box(True, freeform=True, fixed_profile=True) == AIM_PARAMETERS | FREEFORM_PARAMETERS
    base = v2.with_changes({"collimator.lens_freeform_um": [0.0, 0.0, 0.0, 0.0, 1.5]})
    values = {"collimator.lens_freeform_um[3]": 4.0, "collimator.lens_freeform_um[7]": -2.0}
    design, mesh, profile = candidate_collimator(base, values)
    assert design.collimator.lens_freeform_um == (0.0, 0.0, 4.0, 0.0, 1.5, 0.0, -2.0)
    assert design.collimator.tir_crossing == v2.collimator.tir_crossing  # the profile is untouched
    revolved = revolve_profile(profile, 128)
    moved = np.linalg.norm(mesh.mesh.vertices - revolved.vertices, axis=1) > 1e-9
    r = np.hypot(*revolved.vertices[moved, :2].T)
    assert moved.any() and np.all(r <= profile.cavity_radius_mm + 1e-6)  # only the lens and the cavity wall
