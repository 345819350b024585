"""Physics of the emission model: first-order optics, diffraction, aberrations, vignetting, energy."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cm2optics.emission import analysis
from cm2optics.emission.psf import EmissionModel, PSFSettings
from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind, calibration_pinhole, fluorescent_bead
from cm2optics.emission.trace import paraxial_reach_mm, trace_rays
from cm2optics.optics import first_order


@pytest.fixture(scope="module")
def fine(v2):
    return EmissionModel(v2, calibration_pinhole(), settings=PSFSettings(binning=1))


@pytest.fixture(scope="module")
def coarse(v2):
    return EmissionModel(v2, fluorescent_bead(0.0), settings=PSFSettings(binning=4))


@pytest.fixture(scope="module")
def coarse_unfiltered(v2):
    return EmissionModel(v2, fluorescent_bead(0.0), settings=PSFSettings(binning=4), filtered=False)


def test_magnification_and_object_pixel_match_the_design(fine, v2):
    # At z = 0, the focal plane (best focus) and the centre of the calibration scan.
    m = analysis.measured_magnification(fine)
    assert m == pytest.approx(first_order.magnification(v2), rel=0.05)
    assert v2.sensor.pixel_um / m == pytest.approx(first_order.object_pixel_um(v2), rel=0.05)
    assert v2.sensor.pixel_um / m == pytest.approx(4.15, rel=0.05)  # the paper's calibrated object pixel


def test_axial_shear_is_linear_and_paraxial(fine):
    side = 5  # the lenslet at +x
    z = np.array([-0.5, -0.25, 0.0, 0.25, 0.5])
    centres = np.array([analysis.focus_position_mm(fine, (0.0, 0.0, zi), side) for zi in z])
    slope, intercept = np.polyfit(z, centres[:, 0], 1)
    residual = centres[:, 0] - (slope * z + intercept)
    assert np.max(np.abs(residual)) < 0.02 * abs(slope) * np.ptp(z)  # linear within 2 % of the excursion
    assert np.allclose(centres[:, 1], 0.0, atol=1e-6)  # the shear of the +x lenslet points along x
    paraxial = analysis.paraxial_shear(fine, side)
    assert slope == pytest.approx(paraxial[0], rel=0.05)
    assert slope > 0  # a source nearer the device pushes the side foci outwards


def test_the_focal_plane_is_the_best_focus(fine):
    # The design's focal plane (object-space z = 0, the centre of calibration scans) is where the
    # emission model's on-axis focus has the least wavefront error, not the paraxial conjugate.
    best_z = analysis.best_focus_z_mm(fine)
    assert abs(best_z) < 0.1
    best = analysis.on_axis_focus(fine, 0.0)
    # Under-corrected spherical aberration: the paraxial plane lies farther from the device.
    paraxial = analysis.on_axis_focus(fine, -first_order.focus_shift_mm(fine.design))
    assert 0.6 < first_order.focus_shift_mm(fine.design) < 1.0
    assert paraxial.rms_waves > 2.5 * best.rms_waves and paraxial.strehl < best.strehl


def test_on_axis_focus_is_diffraction_limited_at_best_focus(fine):
    best = analysis.on_axis_focus(fine, 0.0)
    # The ideal square aperture's FWHM is 0.886 λ / (2 NA') ...
    assert best.ideal_fwhm_um == pytest.approx(0.886 * best.wavelength_nm / 1000 / (2 * best.na), rel=0.05)
    # ... and the real focus has that size (the spherical aberration moves energy into a halo).
    assert best.fwhm_um == pytest.approx(best.ideal_fwhm_um, rel=0.2)
    # Object side: the core is of the order of the paper's ≈ 6-µm resolution (0.61 λ / NA_obj).
    assert best.fwhm_um / first_order.magnification(fine.design) < 0.61 * 0.53 / first_order.object_na(fine.design)


def test_calibration_volume_is_centred_on_the_sharpest_psfs(fine):
    # The ±0.5-mm calibration depth around z = 0 spans the usable depth symmetrically: the
    # on-axis wavefront error is least at its centre and about equal (≈ 0.75 wave RMS) at its
    # two ends, and what a lab sees of a 5-µm pinhole — the brightest pixel of the nine foci, per
    # unit energy — peaks near its centre and has halved by its ends.
    z = np.linspace(-0.5, 0.5, 11)
    rms = np.array([analysis.on_axis_focus(fine, zi).rms_waves for zi in z])
    assert np.argmin(rms) == 5
    assert abs(rms[0] - rms[-1]) < 0.15 * max(rms[0], rms[-1]) and 0.5 < rms[0] < 1.0
    sharpness = np.array([np.mean([f.patch.max() / f.energy for f in fine.foci((0.0, 0.0, zi))]) for zi in z])
    assert abs(z[np.argmax(sharpness)]) <= 0.25
    assert max(sharpness[0], sharpness[-1]) < 0.65 * sharpness.max()


def test_field_dependent_aberrations_grow_off_axis(fine):
    z = 0.0  # the best focus: the field adds coma and astigmatism to what is there
    rms = [
        fine.pupils((0.0, y, z), lenslets=[4], bands=[fine._mid_band])[0].rms_wavefront_waves()
        for y in (0.0, 1.0, 2.0, 3.0)
    ]
    assert all(b > a for a, b in zip(rms, rms[1:], strict=False)), rms
    assert rms[-1] > 3 * rms[0]


def test_side_foci_fall_off_or_are_vignetted_beyond_about_1p7_mm(coarse):
    # The paper: side foci go missing for sources > 1.7 mm off axis. Here every focus keeps ≥ 10 %
    # of its on-axis energy up to the onset radius, which the sensor sets along y (its short
    # side: the edge lenslets' foci reach its edge) and the array's diced sides along x.
    design = coarse.design
    assert len(analysis.foci_on_sensor(coarse, (0.0, 0.0, 0.0))) == 9
    assert len(analysis.foci_on_sensor(coarse, (0.0, 1.0, 0.0))) == 9
    assert len(analysis.foci_on_sensor(coarse, (1.0, 1.0, 0.0))) == 9
    assert len(analysis.foci_on_sensor(coarse, (0.0, 2.0, 0.0))) < 9
    assert len(analysis.foci_on_sensor(coarse, (2.2, 0.0, 0.0))) < 9
    assert len(analysis.foci_on_sensor(coarse, (0.0, 3.5, 0.0))) <= 6
    along_y = analysis.vignetting_radius_mm(coarse, 90.0, step_mm=0.05, max_mm=2.5, start_mm=1.3)
    along_x = analysis.vignetting_radius_mm(coarse, 0.0, step_mm=0.05, max_mm=2.5, start_mm=1.3)
    m, pitch = analysis.measured_magnification(coarse), design.mla.pitch_mm
    edge = (coarse.optics.sensor_half_y_mm - (1 + m) * pitch) / m  # the row-0 focus's centre at the edge
    assert edge - 0.15 <= along_y <= edge + 0.05, (along_y, edge)
    assert 1.7 <= along_x <= 2.1, along_x
    assert (along_x + along_y) / 2 == pytest.approx(1.7, abs=0.15)


def test_the_housing_does_not_vignette_the_field(v2):
    # With no housing at all (only the mask's opening and the film, which are optics), every
    # focus of the lateral calibration grid gets at most 6 % more light: the corner tabs that
    # hold the MLA shade ≤ 5 % of a corner lenslet, and nothing shades the light under the array.
    coarse = EmissionModel(v2, fluorescent_bead(0.0), settings=PSFSettings(binning=8))
    bare = EmissionModel(v2, fluorescent_bead(0.0), settings=PSFSettings(binning=8))
    bare.optics = dataclasses.replace(
        bare.optics, bores=tuple(b for b in bare.optics.bores if b.name == "mask opening")
    )
    reference = {f.lenslet: f.energy for f in bare.foci((0.0, 0.0, 0.0))}
    worst = 1.0
    for x in (0.0, 1.0, 2.0, 3.0, 4.0):  # one quadrant: the design is symmetric
        for y in (0.0, 1.0, 2.0, 3.0, 4.0):
            housed = {f.lenslet: f.energy for f in coarse.foci((x, y, 0.0))}
            for f in bare.foci((x, y, 0.0)):
                if f.energy >= 0.1 * reference[f.lenslet]:
                    worst = min(worst, housed.get(f.lenslet, 0.0) / f.energy)
    assert worst >= 0.94


def _chief_angles(model: EmissionModel, position_mm, lenslet: int) -> tuple[float, float]:
    """Angles at the filter and at the film (rad) of the ray from the source through the lenslet's vertex."""
    source = model.device_point_mm(position_mm)
    cell = model.optics.lenslets[lenslet]
    band = model._mid_band
    reach = paraxial_reach_mm(model.optics, source[2], model._indices[band, 0], model.optics.vertex_z_mm)
    u = np.array([(cell.vertex_x_mm - source[0]) / reach])
    v = np.array([(cell.vertex_y_mm - source[1]) / reach])
    rays = trace_rays(model.optics, model._batch(source, u, v, np.array([lenslet]), np.array([band])))
    return float(rays.aoi_filter_rad[0]), float(rays.aoi_film_rad[0])


def test_energy_per_focus_follows_the_filter_angle(coarse, coarse_unfiltered):
    k = analysis.central_lenslet(coarse)
    position = (3.5, 0.0, 0.0)
    filtered = analysis.relative_energy(coarse, position, k)
    unfiltered = analysis.relative_energy(coarse_unfiltered, position, k)
    theta, theta_film = _chief_angles(coarse, position, k)
    theta0, film0 = _chief_angles(coarse, (0.0, 0.0, 0.0), k)
    expected = coarse.bands.detected_fraction(theta, theta_film) / coarse.bands.detected_fraction(theta0, film0)
    assert math.degrees(theta) > 15
    assert filtered / unfiltered == pytest.approx(expected, rel=0.05)
    assert filtered / unfiltered < 0.97  # the blue shift of the interference filter costs light off axis


def _mean_profile(model: EmissionModel, profile: AngularProfile, position_mm, lenslet: int) -> float:
    """The profile averaged over the solid angle of the rays that pass through the lenslet."""
    source = model.device_point_mm(position_mm)
    cell = model.optics.lenslets[lenslet]
    band = model._mid_band
    reach = paraxial_reach_mm(model.optics, source[2], model._indices[band, 0], model.optics.vertex_z_mm)
    g = np.linspace(-0.6, 0.6, 61)
    gx, gy = np.meshgrid(cell.vertex_x_mm + g, cell.vertex_y_mm + g)
    u, v = ((gx - source[0]) / reach).ravel(), ((gy - source[1]) / reach).ravel()
    rays = trace_rays(model.optics, model._batch(source, u, v, np.full(u.size, lenslet), np.full(u.size, band)))
    weight = rays.passed * (1 + u * u + v * v) ** -1.5
    return float(np.sum(weight * profile.relative_intensity(rays.aoi_filter_rad)) / np.sum(weight))


def test_energy_per_focus_follows_the_source_profile(v2, coarse):
    profile = AngularProfile(ProfileKind.GAUSSIAN, 20.0)
    gaussian = EmissionModel(v2, PointSource(0.0, profile), settings=PSFSettings(binning=4))
    k = analysis.central_lenslet(coarse)
    position = (2.5, 1.0, 0.0)
    ratio = analysis.relative_energy(gaussian, position, k) / analysis.relative_energy(coarse, position, k)
    expected = _mean_profile(coarse, profile, position, k) / _mean_profile(coarse, profile, (0.0, 0.0, 0.0), k)
    assert ratio == pytest.approx(expected, rel=0.02)
    theta, _ = _chief_angles(coarse, position, k)
    assert ratio == pytest.approx(float(profile.relative_intensity(theta)), rel=0.1)


def test_calibration_pinhole_loses_85_percent_at_the_edge_of_the_field(v2):
    model = EmissionModel(v2, calibration_pinhole(), settings=PSFSettings(binning=4))
    assert analysis.relative_energy(model, (4.0, 0.0, 0.0)) == pytest.approx(0.15, abs=0.04)


def test_energy_is_conserved_from_rays_to_pixels(coarse):
    for position in ((0.0, 0.0, 0.0), (1.5, -1.0, 0.4), (3.5, 3.0, -0.5)):
        for focus in coarse.foci(position):
            assert focus.energy == pytest.approx(focus.ray_power, rel=0.03), (position, focus.lenslet, focus.geometric)


def test_detection_probability_is_physical(coarse):
    total = sum(f.energy for f in coarse.foci((0.0, 0.0, 0.0)))
    # nine lenslets of ≈ 0.0094 sr each at ≈ 9.5 mm, isotropic into 2π, × filters × QE (≈ 0.26)
    solid = 9 * (1.0 / first_order.working_distance_mm(coarse.design) ** 2)
    assert total == pytest.approx(solid / (2 * math.pi) * 0.26, rel=0.25)
