"""The aberration model's placement fitted to whole-pixel frames (a measured scan has no fine
ePSF): a known offset and flux recovered from foci about one pixel wide, each frame at its own
sub-pixel phase; and the pixel sampler against the model's placement of an ePSF."""

import numpy as np
import pytest

from cm2optics.calibrate.aberration_build import pixel_samplers
from cm2optics.emission.aberration_model import Aperture, LensletModel, NodalWavefront, fit_placement
from cm2optics.lsv.epsf import place_epsf

AXIS = (0.3, -0.2)
S = 4


def _model() -> LensletModel:
    cell = np.zeros((8, 9))
    cell[:, 0] = 0.97
    coefficients = np.zeros(63)
    coefficients[0] = 0.3  # defocus-like (p·p): a focus ≈ 1 pixel (4.8 µm) wide
    return LensletModel(
        NodalWavefront(coefficients, AXIS), Aperture(cell, tuple(() for _ in range(8))), 5e-4, (32, 32), 1.2e-3, S
    )


def test_sampler_is_the_models_placement_of_the_epsf():
    rng = np.random.default_rng(0)
    fine = rng.random((32, 40))
    eps = np.array([0.3, 0.85])
    (sample,) = pixel_samplers(eps[None], (8, 10), S)
    np.testing.assert_allclose(sample(fine), place_epsf(fine, (eps[0], eps[1]), S)[1:9, 1:11], atol=1e-12)


@pytest.mark.slow  # ≈ 30 s at load 6 (≈ 300 renders)
def test_placement_recovered_from_whole_pixel_frames_at_their_own_phases():
    rng = np.random.default_rng(3)
    base = _model()
    positions = rng.uniform([-3, -3, -0.3], [3, 3, 0.3], (36, 3))
    truth_offset = lambda q: np.array([2e-3 + 1e-3 * q[0], -1e-3 * q[1] + 2e-3 * q[2]])  # noqa: E731
    truth_flux = lambda q: np.exp(0.1 * q[2] - 0.02 * q[0])  # noqa: E731
    samplers = pixel_samplers(rng.uniform(0, 1, (len(positions), 2)), (8, 8), S)
    frames = [s(base.render(q, truth_offset(q)) * truth_flux(q)) for s, q in zip(samplers, positions, strict=True)]
    q = np.array([0.7, -1.3, 0.1])
    expected = base.render(q, truth_offset(q)) * truth_flux(q)

    def nmse(model: LensletModel) -> float:
        return float(((model.predict(q) - expected) ** 2).sum() / (expected**2).sum())

    refined = nmse(fit_placement(base, frames, positions, samplers=samplers))
    once = nmse(fit_placement(base, frames, positions, samplers=samplers, rounds=1))
    assert refined < 2e-3  # (the fine crops: 7e-5; the core's 20 % threshold leaves ≈ 0.02 px)
    assert refined < once  # one centroid of whole pixels does not move one for one with the focus
