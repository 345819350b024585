"""The ray trace, the housing scene, the spectral weights and the Fourier optics, against closed forms."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cm2optics.design.materials import refractive_index
from cm2optics.emission.optics import emission_optics, housing_bores, lenslets
from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind
from cm2optics.emission.spectral import spectral_bands
from cm2optics.emission.trace import RayBatch, trace_rays
from cm2optics.emission.wavefront import debye_fft, fft_size, fit_pupil_map, mft
from cm2optics.optics.backend import is_jit


@pytest.fixture(scope="module")
def optics(v2):
    return emission_optics(v2)


def _batch(optics, source, u, v, lenslet=4, lam=525.0):
    n = len(u)
    return RayBatch(
        np.tile(source, (n, 1)),
        u,
        v,
        np.full(n, lenslet),
        np.full(n, refractive_index(optics.filter.material, lam)),
        np.full(n, refractive_index(optics.lens_material, lam)),
        np.full(n, refractive_index(optics.film.material, lam)),
    )


def test_axial_ray_has_the_closed_form_optical_path(optics):
    source = np.array([0.0, 0.0, optics.object_plane_z_mm])
    rays = trace_rays(optics, _batch(optics, source, np.zeros(1), np.zeros(1)), "numpy")
    lam = 525.0
    f, film = optics.filter, optics.film
    expected = (
        (source[2] - f.z1_mm)
        + refractive_index(f.material, lam) * f.thickness_mm
        + (f.z0_mm - optics.vertex_z_mm)
        + refractive_index(optics.lens_material, lam) * (optics.vertex_z_mm - optics.flat_z_mm)
        + (optics.flat_z_mm - film.z1_mm)
        + refractive_index(film.material, lam) * film.thickness_mm
        + film.z0_mm
    )
    assert rays.passed[0] and rays.x_mm[0] == pytest.approx(0.0, abs=1e-12)
    assert rays.opl_mm[0] == pytest.approx(expected, abs=1e-12)
    n = refractive_index(optics.lens_material, lam)
    assert rays.fresnel[0] == pytest.approx(
        (1 - ((n - 1) / (n + 1)) ** 2) ** 2, rel=1e-9
    )  # two faces at normal incidence


def test_angle_at_the_filter_is_the_launch_angle(optics):
    """The angle of incidence on the filter is the angle of the ray leaving the source (air above it)."""
    source = np.array([0.0, 0.0, optics.object_plane_z_mm])
    theta = math.radians(20)
    rays = trace_rays(optics, _batch(optics, source, np.array([math.tan(theta)]), np.zeros(1), lenslet=5), "numpy")
    assert rays.aoi_filter_rad[0] == pytest.approx(theta, abs=1e-12)


@pytest.mark.skipif(not is_jit(), reason="needs a JIT variant of Mitsuba (LLVM ≥ 17 or CUDA)")
def test_drjit_and_numpy_engines_agree_and_the_housing_scene_matches_the_bores(optics):
    rng = np.random.default_rng(1)
    n = 40000
    source = np.array([1.3, -2.1, optics.object_plane_z_mm + 0.3])
    lens = rng.integers(0, 9, n)
    reach = source[2] - optics.vertex_z_mm
    cx = np.array([c.vertex_x_mm for c in optics.lenslets])[lens]
    cy = np.array([c.vertex_y_mm for c in optics.lenslets])[lens]
    u = (cx + rng.uniform(-0.7, 0.7, n) - source[0]) / reach
    v = (cy + rng.uniform(-0.7, 0.7, n) - source[1]) / reach
    batch = _batch(optics, source, u, v)
    batch = RayBatch(batch.source_mm, u, v, lens, batch.n_filter, batch.n_lens, batch.n_film)
    a = trace_rays(optics, batch, "numpy")
    b = trace_rays(optics, batch, "drjit")
    assert np.array_equal(a.traced, b.traced)
    ok = a.traced
    assert np.allclose(a.opl_mm[ok], b.opl_mm[ok], atol=1e-11)
    assert np.allclose(a.x_mm[ok], b.x_mm[ok], atol=1e-11)
    assert a.passed.sum() > 1000
    # Mitsuba's meshes (drjit) and the closed-form bores (numpy) block the same rays, up to the
    # float32 of Mitsuba's rays at grazing edges.
    assert (a.passed != b.passed).mean() < 1e-3


@pytest.mark.skipif(not is_jit(), reason="needs a JIT variant of Mitsuba (LLVM ≥ 17 or CUDA)")
def test_the_octagonal_tabs_block_the_same_rays_in_both_engines(optics):
    # Rays aimed at the outer corner of a corner lenslet, where the MLA's corner tabs sit: some
    # are shaded by a tab's 45° face, the rest pass, and both engines agree ray by ray.
    tabs = next(b for b in optics.bores if b.name == "MLA tabs")
    assert math.isfinite(tabs.diagonal_mm) and len(tabs.polygon_mm()) == 8
    rng = np.random.default_rng(2)
    n = 20000
    source = np.array([1.5, 1.5, optics.object_plane_z_mm])  # beyond the corner: its beam leaves the flat face
    corner = next(c for c in optics.lenslets if c.vertex_x_mm > 0 and c.vertex_y_mm > 0)
    reach = source[2] - optics.vertex_z_mm
    u = (rng.uniform(corner.x1_mm - 0.4, corner.x1_mm, n) - source[0]) / reach
    v = (rng.uniform(corner.y1_mm - 0.4, corner.y1_mm, n) - source[1]) / reach
    batch = _batch(optics, source, u, v, lenslet=corner.index)
    a = trace_rays(optics, batch, "numpy")
    b = trace_rays(optics, batch, "drjit")
    others = [bo for bo in optics.bores if bo.name != "MLA tabs"]
    c = trace_rays(dataclasses.replace(optics, bores=tuple(others)), batch, "numpy")
    shaded = (c.passed & ~a.passed).mean()
    assert 0.2 < shaded < 0.45  # a tab covers a triangle of legs lip_mm (0.3 mm): 28 % of this 0.4-mm square
    assert (a.passed != b.passed).mean() < 2e-3


def test_bores_follow_the_printed_housing(v2):
    from cm2optics.optics.housing import bore_steps, mla_tab_geometry

    ours = {b.name: b for b in housing_bores(v2)}
    for step in bore_steps(v2):
        if step.name == "film seat":
            continue  # the film's own clear aperture stands for its seat
        bore = ours[step.name]
        assert bore.half_x_mm == pytest.approx(step.width_mm / 2)
        assert bore.half_y_mm == pytest.approx(step.length_mm / 2)
        assert (bore.z0_mm, bore.z1_mm) == pytest.approx((step.z0_mm, step.z1_mm))
        assert not math.isfinite(bore.diagonal_mm)
    tabs, cad = ours["MLA tabs"], mla_tab_geometry(v2)
    assert (tabs.z0_mm, tabs.z1_mm, tabs.diagonal_mm) == pytest.approx((cad.z0_mm, cad.z1_mm, cad.diagonal_mm))
    assert (tabs.half_x_mm, tabs.half_y_mm) == pytest.approx((ours["MLA seat"].half_x_mm, ours["MLA seat"].half_y_mm))


def test_lenslets_match_the_cad_cells(v2):
    pytest.importorskip("cadquery")
    from cm2optics.cad.mla import lens_cells

    design = v2.with_changes({"mla.partial_border_mm": 0.3, "mla.partial_sides": ["+x", "-y"]})
    cells = lens_cells(design.mla)
    ours = lenslets(design)
    assert len(ours) == len(cells) == 16
    for a, b in zip(ours, cells, strict=True):
        assert (a.vertex_x_mm, a.vertex_y_mm, a.partial) == pytest.approx((b.vertex_x, b.vertex_y, b.partial))
        assert (a.x0_mm, a.x1_mm, a.y0_mm, a.y1_mm) == pytest.approx((b.x_min, b.x_max, b.y_min, b.y_max))


def test_spectral_weights(v2):
    bands = spectral_bands(v2)
    assert 5 <= len(bands) <= 12
    assert np.all(np.diff(bands.wavelength_nm) > 0)
    assert np.all(bands.table >= 0)
    normal = bands.detected_fraction(0.0, 0.0)
    assert 0.1 < normal < 0.5  # filter passband × film × QE over the green emission
    assert bands.detected_fraction(math.radians(40), 0.0) < 0.7 * normal  # the passband slides off blue
    unfiltered = spectral_bands(v2, filtered=False)
    assert unfiltered.detected_fraction(0.0, 0.0) > normal
    with pytest.raises(ValueError, match="band_nm"):
        spectral_bands(v2, band_nm=0.1)


def test_profiles_are_normalised_and_validated():
    for profile in (
        AngularProfile(),
        AngularProfile(ProfileKind.LAMBERTIAN),
        AngularProfile(ProfileKind.COSINE, 3.0),
        AngularProfile(ProfileKind.GAUSSIAN, 26.0),
        AngularProfile(ProfileKind.TABLE, angles_deg=(0.0, 30.0, 60.0, 90.0), relative=(1.0, 0.8, 0.3, 0.0)),
    ):
        theta = np.linspace(0, math.pi / 2, 20001)
        total = np.trapezoid(profile.intensity_sr(theta) * 2 * math.pi * np.sin(theta), theta)
        assert total == pytest.approx(1.0, rel=1e-4)
    assert AngularProfile().intensity_sr(0.3) == pytest.approx(1 / (2 * math.pi))
    with pytest.raises(ValueError, match="half-angle"):
        AngularProfile(ProfileKind.GAUSSIAN, 0.0)
    with pytest.raises(ValueError, match="angles_deg"):
        AngularProfile(ProfileKind.TABLE, angles_deg=(5.0, 10.0), relative=(1.0, 1.0))
    with pytest.raises(ValueError, match="diameter_um"):
        PointSource(-1.0)


def test_fft_and_matrix_fourier_transforms_agree():
    rng = np.random.default_rng(3)
    lam, h = 0.5e-3, 1.0e-3
    n_fft, spacing = fft_size(30, 0.08, h, lam)
    pupil = rng.random((37, 40)) + 1j * rng.random((37, 40))
    jl, jm = np.arange(40) - 19.5, np.arange(37) - 18
    l_axis, m_axis = 0.01 + jl * spacing, -0.02 + jm * spacing
    x0, y0 = -0.0123, 0.0071
    a = debye_fft(pupil * np.exp(0j), spacing, lam, n_fft, x0, y0, (20, 30))
    b = mft(pupil, l_axis, m_axis, x0 + np.arange(30) * h, y0 + np.arange(20) * h, lam, spacing)
    assert np.allclose(a, b, rtol=1e-4, atol=1e-4 * b.max())


def test_uniform_square_pupil_gives_the_sinc_squared_psf():
    """Closed form: a uniform square pupil of half-width a in direction cosines focuses to
    (2a)⁴/λ² · sinc²(2a x/λ) sinc²(2a y/λ) per unit power density, and Parseval holds."""
    lam, a = 0.5e-3, 0.08
    n = 201
    axis = np.linspace(-a, a, n)
    spacing = axis[1] - axis[0]
    pupil = np.ones((n, n), dtype=complex)
    x = np.linspace(-0.02, 0.02, 401)
    image = mft(pupil, axis, axis, x, np.array([0.0]), lam, spacing)[0]
    side = spacing * n  # the samples' cells tile [−a − s/2, a + s/2]
    expected = (side**2 / lam) ** 2 * np.sinc(side * x / lam) ** 2
    assert np.allclose(image, expected, rtol=2e-3, atol=2e-3 * expected.max())
    full = mft(pupil, axis, axis, x, x, lam, spacing)
    # ∬|U|² = ∬|A|²: the ±20-µm window holds all but the sinc² tails beyond 6 lobes (≈ 3 %).
    assert full.sum() * (x[1] - x[0]) ** 2 == pytest.approx(side**2 * (1 - 2 / (math.pi**2 * 6.4)), rel=0.01)


def test_pupil_map_fits_polynomials_exactly():
    rng = np.random.default_rng(5)
    L, M = rng.uniform(-0.1, 0.1, 300), rng.uniform(0.05, 0.2, 300)
    u = 0.3 + 2 * L - 0.5 * M + 7 * L**3 - 3 * L * M**2
    v = -0.1 + 1.5 * M + 0.2 * L * M + 9 * M**4
    pmap = fit_pupil_map(L, M, u, v, degree=4)
    assert pmap.residual < 1e-10
    uu, vv = pmap.grid(np.array([0.0, 0.05]), np.array([0.1]))
    assert uu[0, 1] == pytest.approx(0.3 + 0.1 - 0.05 + 7 * 0.05**3 - 3 * 0.05 * 0.01, abs=1e-9)
    assert vv[0, 0] == pytest.approx(-0.1 + 0.15 + 9e-4, abs=1e-9)
