"""Emission geometry and SBR: solid angles against closed forms, the hybrid gain from physics,
and how the film's thickness and cut-on move it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.emission.filter_angles import (
    Emitter,
    Excitation,
    Sources,
    excitation_footprint,
    field_sources,
    model_excitation,
    specular_rays,
    trace_from_sources,
)
from cm2optics.emission.sbr import Sample, signal_and_background
from cm2optics.optics import first_order
from cm2optics.spectra.absorption import fresnel_transmittance
from cm2optics.spectra.chain import emission_chain, excitation_half_angle_rad, excitation_spectrum
from cm2optics.spectra.library import led_spectrum

COARSE = {"field_step_mm": 0.5, "pupil_samples": 16, "beam_samples": 8}


def test_on_axis_source_collects_the_solid_angle_of_the_mask_opening(v2):
    # cm2-v2's mask sits 0.35 mm above the lenses, so the array's rim, not the 3-mm opening,
    # bounds its on-axis cone; a 2.4-mm opening makes the mask the stop this test measures
    # (and puts its edges on the pupil grid's cell edges, so the sum is exact).
    design = v2.with_changes({"aperture_mask.opening_mm": 2.4})
    rays = trace_from_sources(design, Sources(np.zeros((1, 2)), np.ones(1)), Emitter.ISOTROPIC, pupil_samples=60)
    h = first_order.object_plane_z_mm(design) - (design.mask_z_mm + design.aperture_mask.thickness_mm)
    a = design.aperture_mask.opening_mm / 2
    square = 4 * math.atan(a * a / (h * math.sqrt(h * h + 2 * a * a)))  # solid angle of a centred square
    assert rays.collection == pytest.approx(square / (4 * math.pi), rel=1e-3)
    assert np.degrees(rays.aoi_filter_rad.max()) == pytest.approx(
        math.degrees(math.atan(a * math.sqrt(2) / h)), abs=0.5
    )


def test_fluorescence_meets_the_filter_less_obliquely_than_the_glow(v2):
    signal = trace_from_sources(v2, field_sources(v2, 0.5), Emitter.ISOTROPIC, 16)
    glow = trace_from_sources(v2, excitation_footprint(v2), Emitter.LAMBERTIAN, 16)
    assert 0 < signal.collection < 0.01 and 0 < glow.collection < 0.1
    assert np.degrees(signal.aoi_filter_rad.max()) < 30  # the paper's point: the filter sits where angles are small
    assert np.degrees(glow.aoi_filter_rad.max()) > 35
    assert np.all(glow.aoi_film_rad >= 0) and np.degrees(glow.aoi_film_rad.max()) < 60


def test_beams_land_around_the_field_and_reflect_by_fresnel(v2):
    footprint = excitation_footprint(v2)
    assert footprint.weights.sum() == pytest.approx(1.0)
    assert v2.volume.field_mm / 2 < footprint.radius_mm(0.95) < 2 * v2.volume.field_mm
    _, directions, power = specular_rays(v2, 1.5, 8)
    assert np.all(directions[:, 2] < 0)  # back towards the device
    angles = np.arccos(-directions[:, 2])  # every ray of the tilt ± δ beam reaches the sample
    np.testing.assert_allclose(power * len(power), 1 - fresnel_transmittance(angles, 1.5))
    delta = math.degrees(excitation_half_angle_rad(v2))  # asin(1 mm / 4 mm) = 14.48°
    assert delta == pytest.approx(14.48, abs=0.01)
    assert np.degrees(angles.min()) == pytest.approx(v2.led_array.tilt_deg - delta, abs=1.0)


def test_excitation_light_is_the_led_through_its_filter(v2):
    light = excitation_spectrum(v2)
    led = led_spectrum(v2.led.peak_nm)
    ratio = light.values / led.values
    assert ratio[led.wavelength_nm == 470][0] == pytest.approx(0.95, abs=0.02)
    assert ratio[led.wavelength_nm == 520][0] < 1e-4
    assert ratio[led.wavelength_nm == 489][0] < 0.5  # the cone of angles pulls the long edge bluewards


@pytest.fixture(scope="module")
def v2_result(v2):
    return signal_and_background(v2, **COARSE)


def test_hybrid_gain_is_at_least_5_from_the_physics(v2_result):
    assert v2_result.sbr_gain >= 5
    assert v2_result.sbr_hybrid > v2_result.sbr_interference_only > 0
    kept = v2_result.signal["hybrid"].sum() / v2_result.signal["interference_only"].sum()
    assert 0.4 < kept < 0.9  # the film costs some of the green
    data = v2_result.to_dict()
    assert data["sbr_gain"] == pytest.approx(v2_result.sbr_gain, rel=1e-3)


def test_leakage_grows_with_angle_for_the_interference_only_chain(v2_result):
    centres = 0.5 * (v2_result.aoi_bin_edges_deg[1:] + v2_result.aoi_bin_edges_deg[:-1])
    background = v2_result.background["interference_only"]
    signal = v2_result.signal["interference_only"]
    per_ray_low = background[(centres < 20) & (background > 0)].mean()
    per_ray_high = background[(centres > 30) & (background > 0)].mean()
    assert per_ray_high > 5 * per_ray_low
    sbr = v2_result.sbr_vs_angle("interference_only")
    assert np.all(np.isnan(sbr[background == 0]))
    assert np.all(signal[centres > 30] == 0)


def test_sample_numbers_cancel_in_the_gain(v2, v2_result):
    other = signal_and_background(v2, Sample(absorbed_fraction=0.2, quantum_yield=0.5), **COARSE)
    assert other.sbr_gain == pytest.approx(v2_result.sbr_gain, rel=1e-9)
    assert other.sbr_interference_only == pytest.approx(v2_result.sbr_interference_only * 20 * 0.5 / 0.9, rel=1e-9)


@pytest.mark.parametrize(
    ("change", "direction"),
    [
        ({"absorption_filter.thickness_mm": 0.05}, -1),
        ({"absorption_filter.thickness_mm": 0.2}, +1),
        ({"absorption_filter.cut_on_nm": 505.0}, -1),
        ({"absorption_filter.cut_on_nm": 525.0}, +1),
    ],
)
def test_the_film_moves_the_gain_the_right_way(v2, v2_result, change, direction):
    gain = signal_and_background(v2.with_changes(change), **COARSE).sbr_gain
    assert (gain - v2_result.sbr_gain) * direction > 0.2 * v2_result.sbr_gain, (change, gain, v2_result.sbr_gain)


def _joined(*parts: Excitation) -> Excitation:
    return Excitation(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("hits_mm", "directions", "power")))


def test_light_landing_beyond_the_sensors_reach_costs_signal_not_background(v2_collimating):
    """Signal and background share the LEDs' photon budget: light added where no pixel can see it
    (100 mm off the axis) changes nothing; moving half the light there halves signal and
    background alike. (Counting the signal per landed photon doubled the SBR here: that is how a
    bare LED, which lands most of its light far out, outranked the collimated ones.)"""
    sampling = {"field_step_mm": 0.5, "pupil_samples": 12}
    design = v2_collimating.with_changes({"led_array.aim_mm": 2.5})  # its beams' steep side mirrors back
    near = model_excitation(design, 6)
    far = Excitation(near.hits_mm + [100.0, 0.0], near.directions, near.power)
    base = signal_and_background(design, excitation=near, **sampling)
    added = signal_and_background(design, excitation=_joined(near, far), **sampling)
    halves = [Excitation(e.hits_mm, e.directions, e.power / 2) for e in (near, far)]
    moved = signal_and_background(design, excitation=_joined(*halves), **sampling)
    assert added.excitation_landed == pytest.approx(2.0) and added.excitation_in_field == pytest.approx(
        base.excitation_in_field
    )
    for chain in ("interference_only", "hybrid"):
        assert base.background[chain].sum() > 0 and base.background_by_path["specular"][chain].sum() > 0
        assert added.signal[chain].sum() == pytest.approx(base.signal[chain].sum(), rel=1e-9)
        assert added.background[chain].sum() == pytest.approx(base.background[chain].sum(), rel=1e-9)
        assert moved.signal[chain].sum() == pytest.approx(base.signal[chain].sum() / 2, rel=1e-9)
        assert moved.background[chain].sum() == pytest.approx(base.background[chain].sum() / 2, rel=1e-9)
    assert moved.sbr_hybrid == pytest.approx(base.sbr_hybrid, rel=1e-9)


def test_the_signal_is_the_light_entering_the_field_by_fresnel(v2):
    """Equal power on every field point at normal incidence, then at 60°: the signal scales by the
    unpolarised Fresnel transmittance of the n = 1.5 surface, (1 − R(60°)) / (1 − R(0)), closed form."""
    field = field_sources(v2, 0.5)
    n, theta = 1.5, math.radians(60.0)
    theta_t = math.asin(math.sin(theta) / n)
    r_s = (math.cos(theta) - n * math.cos(theta_t)) ** 2 / (math.cos(theta) + n * math.cos(theta_t)) ** 2
    r_p = (math.cos(theta_t) - n * math.cos(theta)) ** 2 / (math.cos(theta_t) + n * math.cos(theta)) ** 2
    expected = (1 - (r_s + r_p) / 2) / (1 - ((n - 1) / (n + 1)) ** 2)
    signal = {}
    for angle in (0.0, theta):
        directions = np.tile([math.sin(angle), 0.0, math.cos(angle)], (len(field.weights), 1))
        excitation = Excitation(field.points_mm, directions, field.weights)
        result = signal_and_background(v2, Sample(surface_index=n), excitation, field_step_mm=0.5, pupil_samples=12)
        signal[angle] = result.signal["interference_only"].sum()
        if angle == 0.0:
            assert result.excitation_in_field == pytest.approx(1 - ((n - 1) / (n + 1)) ** 2)  # 0.96 enters
    assert signal[theta] / signal[0.0] == pytest.approx(expected, rel=1e-9)
    assert expected == pytest.approx(0.9108 / 0.96, rel=1e-3)


def test_bare_leds_light_the_field_less_and_leak_more_through_the_interference_filter(v2, v2_result):
    """The same device with bare LEDs at the same placement: their wide beam spends light outside
    the field, where it glows but excites nothing imaged, so per photon the LEDs emit the
    interference-only SBR falls. The hybrid chain's need not: traced, bare LEDs at the default's
    placement match its hybrid SBR within the noise (BENCHMARKS.md, "The SBR settled")."""
    bare = signal_and_background(v2.with_changes({"collimator": None}), **COARSE)
    assert bare.excitation_in_field < 0.5 * v2_result.excitation_in_field
    assert bare.sbr_interference_only < v2_result.sbr_interference_only


def test_the_hybrid_chain_of_a_design(v2):
    chain = emission_chain(v2)
    assert chain.film is not None and chain.without_film().film is None
    assert chain.transmittance(470.0) < 1e-8 < chain.without_film().transmittance(470.0)
    assert chain.spectrum(0.0).quantity == "transmittance"
    with pytest.raises(ValueError, match="aoi_filter_deg"):
        chain.spectrum(95.0)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"absorbed_fraction": 0.0}, "absorbed_fraction"),
        ({"quantum_yield": 1.5}, "quantum_yield"),
        ({"diffuse_reflectance": float("nan")}, "diffuse_reflectance"),
        ({"surface_index": 0.5}, "surface_index"),
    ],
)
def test_bad_sample_values_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        Sample(**kwargs)


def test_diced_array_partial_cells_count_as_in_the_psf_tracer(v2):
    """Partial lenslets left by dicing collect light: spectra's rays go through the emission tracer
    with every cell of lens_cells, so each ray lands exactly when some lenslet of the PSF tracer
    passes it, at the same angles."""
    from cm2optics.design.materials import refractive_index
    from cm2optics.emission.filter_angles import trace_rays
    from cm2optics.emission.optics import emission_optics
    from cm2optics.emission.trace import RayBatch
    from cm2optics.emission.trace import trace_rays as trace_emission

    diced = v2.with_changes({"mla.partial_border_mm": 0.3, "mla.partial_sides": ["+x", "-x", "+y", "-y"]})
    source = np.array([1.2, 0.4, first_order.object_plane_z_mm(diced)])
    t = np.linspace(-0.2, 0.2, 41)
    u, v = (g.ravel() for g in np.meshgrid(t, t))
    d = np.column_stack([u, v, -np.ones_like(u)]) / np.sqrt(1 + u * u + v * v)[:, None]
    origins, power = np.tile(source, (len(d), 1)), np.full(len(d), 1.0 / len(d))

    plain, cut = trace_rays(v2, origins, d, power), trace_rays(diced, origins, d, power)
    assert len(cut.power) > len(plain.power)  # the partial cells add light

    optics = emission_optics(diced)
    lam = diced.imaging.design_wavelength_nm
    n = len(d)
    indices = [
        np.full(n, refractive_index(part.material, lam))
        for part in (diced.emission_filter, diced.mla, diced.absorption_filter)
    ]
    passed, aoi = np.zeros(n, bool), np.zeros(n)
    for k in range(len(optics.lenslets)):
        traced = trace_emission(optics, RayBatch(origins, u, v, np.full(n, k), *indices), engine="numpy")
        aoi = np.where(traced.passed & ~passed, traced.aoi_filter_rad, aoi)
        passed |= traced.passed
    assert any(c.partial for c in optics.lenslets)
    assert len(cut.power) == passed.sum()
    np.testing.assert_allclose(np.sort(cut.aoi_filter_rad), np.sort(aoi[passed]), atol=1e-9)
