"""The nodal-aberration model's parts against closed forms: a known nodal wavefront recovered
from its pupils with each node's piston and tilt added, a known clipped aperture recovered from
its extents, the pixel integral, Parseval for the render, a known placement recovered, and the
render on coarse pixels against the fine one."""

import numpy as np
import pytest

from cm2optics.emission.aberration_model import (
    DIRECTIONS,
    PUPIL_UNIT,
    RENDER_SAMPLES_PER_UNIT,
    Aperture,
    LensletModel,
    NodalWavefront,
    PupilSamples,
    core_centroid,
    fit_aperture,
    fit_placement,
    fit_wavefront,
    nodal_terms,
    pixel_integrate,
    pupil_extents,
)

AXIS = (0.3, -0.2)


def _open_aperture(radius: float = 0.97) -> Aperture:
    cell = np.zeros((8, 9))
    cell[:, 0] = radius
    return Aperture(cell, tuple(() for _ in range(8)))


def _grid_positions() -> np.ndarray:
    x, y, z = np.meshgrid(np.arange(-4, 5.0), np.arange(-4, 5.0), [-0.4, 0.0, 0.3], indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], -1)


def test_wavefront_recovered_with_each_nodes_piston_and_tilt_free():
    rng = np.random.default_rng(1)
    n_terms = nodal_terms(np.zeros((1, 2)), np.zeros(2), 0.0).shape[1]
    truth = NodalWavefront(rng.normal(0, 0.05, n_terms), AXIS)
    axis = np.linspace(-0.9, 0.9, 31)
    p = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    pupils = []
    for position in rng.uniform([-3, -3, -0.5], [3, 3, 0.4], (40, 3)):
        piston, tilt = rng.normal(size=1), rng.normal(size=2)  # the node's own, not the model's
        waves = truth(p, position) + piston + p @ tilt
        pupils.append(PupilSamples(tuple(position), p, waves, np.full(len(p), 1.0), 0.06, 5e-4))
    fitted = fit_wavefront(pupils, AXIS)
    np.testing.assert_allclose(fitted.coefficients, truth.coefficients, atol=1e-8)
    # __call__ (field factors summed first) equals the terms times the coefficients
    position = (1.5, -2.0, 0.2)
    h = np.array(position[:2]) - AXIS
    np.testing.assert_allclose(truth(p, position), nodal_terms(p, h, position[2]) @ truth.coefficients, atol=1e-12)


def test_clipped_aperture_recovered_from_extents():
    positions = _grid_positions()
    cell = np.zeros((8, 9))
    cell[:, 0], cell[:, 3], cell[:, 6] = 0.97, -0.004, 0.05  # a smooth cell: 1, x², z
    clips = [() for _ in range(8)]
    clips[0] = (np.array([1.9, -0.9, 0.0, 0.2, 0.0, 0.0]),)  # +x cut by a bore beyond x ≈ 1 mm
    truth = Aperture(cell, tuple(clips))
    fitted = fit_aperture(positions, truth.extents(positions), AXIS, tolerance=0.01)
    between = np.random.default_rng(2).uniform([-4, -4, -0.4], [4, 4, 0.3], (200, 3))
    np.testing.assert_allclose(fitted.extents(between), truth.extents(between), atol=2e-3)
    assert len(fitted.clips[0]) == 1 and not any(fitted.clips[k] for k in range(2, 8))


def test_pupil_extents_of_a_square():
    axis = np.linspace(-0.5, 0.5, 11)
    p = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    extents = pupil_extents(p, 0.1)
    np.testing.assert_allclose(extents[0::2], 0.55)
    np.testing.assert_allclose(extents[1::2], 1.0 / np.sqrt(2) + 0.05)
    assert np.allclose(np.linalg.norm(DIRECTIONS, axis=1), 1)


def test_pixel_integral_keeps_constants_and_ramps_and_spreads_a_delta_over_one_pixel():
    S = 4
    ramp = np.add.outer(np.zeros(40), np.arange(40.0))
    np.testing.assert_allclose(pixel_integrate(ramp + 3.0, S)[10:30, 10:30], (ramp + 3.0)[10:30, 10:30])
    delta = np.zeros((21, 21))
    delta[10, 10] = 1.0
    spread = pixel_integrate(delta, S)
    assert spread.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(spread[10, 8:13], np.array([0.5, 1, 1, 1, 0.5]) / S / S)
    with pytest.raises(ValueError, match="even"):
        pixel_integrate(delta, 3)


def test_render_obeys_parseval_and_moves_with_its_offset():
    model = LensletModel(NodalWavefront(np.zeros(63), AXIS), _open_aperture(), 5e-4, (128, 128), 1.2e-3, 4)
    image = model.render((0.0, 0.0, 0.0))
    passed = _open_aperture().mask(np.zeros((1, 2)), (0.0, 0.0, 0.0))
    assert passed.all()
    axis = np.arange(-1.25, 1.25 + 1e-9, 1.0 / RENDER_SAMPLES_PER_UNIT)
    grid = np.stack(np.meshgrid(axis, axis), -1)
    pupil_power = _open_aperture().mask(grid, (0.0, 0.0, 0.0)).sum() * (PUPIL_UNIT / RENDER_SAMPLES_PER_UNIT) ** 2
    assert image.sum() * 1.2e-3**2 == pytest.approx(pupil_power, rel=0.02)  # power ∬|U|² = Σ|A|² ΔL ΔM
    moved = model.render((0.0, 0.0, 0.0), (3.0e-3, -1.8e-3))
    np.testing.assert_allclose(
        core_centroid(moved, 1.2e-3) - core_centroid(image, 1.2e-3), [3.0e-3, -1.8e-3], atol=5e-5
    )


def test_placement_recovered_from_crops_rendered_with_it():
    rng = np.random.default_rng(3)
    coefficients = np.zeros(63)
    coefficients[0] = 0.3  # defocus-like (p·p), constant over the field
    base = LensletModel(NodalWavefront(coefficients, AXIS), _open_aperture(), 5e-4, (64, 64), 1.2e-3, 4)
    positions = rng.uniform([-3, -3, -0.3], [3, 3, 0.3], (36, 3))
    truth_offset = lambda q: np.array([2e-3 + 1e-3 * q[0], -1e-3 * q[1] + 2e-3 * q[2]])  # noqa: E731
    truth_flux = lambda q: np.exp(0.1 * q[2] - 0.02 * q[0])  # noqa: E731
    crops = [base.render(q, truth_offset(q)) * truth_flux(q) for q in positions]
    fitted = fit_placement(base, crops, positions)
    q = np.array([0.7, -1.3, 0.1])
    expected = base.render(q, truth_offset(q)) * truth_flux(q)
    predicted = fitted.predict(q)
    assert ((predicted - expected) ** 2).sum() / (expected**2).sum() < 1e-3


def test_render_on_coarse_pixels_is_the_fine_epsf_taken_every_fourth_sample():
    coefficients = np.zeros(63)
    coefficients[3] = 0.4  # (p·p)(h·h): field-dependent defocus
    wavefront, aperture = NodalWavefront(coefficients, AXIS), _open_aperture()
    coarse = LensletModel(wavefront, aperture, 5e-4, (24, 24), 4.8e-3, 4).render((1.0, 0.5, 0.1), (2e-3, 1e-3))
    fine = LensletModel(wavefront, aperture, 5e-4, (96, 96), 1.2e-3, 16).render((1.0, 0.5, 0.1), (2e-3, 1e-3))
    np.testing.assert_allclose(coarse, fine[::4, ::4], rtol=1e-6, atol=1e-9 * fine.max())
