"""The held-out metric of node PSFs predicted by a model fitted without them, against closed forms."""

import numpy as np
import pytest

from cm2optics.lsv.epsf import place_epsf
from cm2optics.lsv.epsf_validate import predicted_nodes_nmse


def test_predicted_nodes_nmse_is_zero_for_the_frames_own_psf_and_a_flux_error_squared_otherwise():
    rng = np.random.default_rng(4)
    S, J = 4, 2
    psf = rng.random((3, J, 16, 16))
    eps = rng.uniform(0, 1, (5, J, 2))
    held = np.array([1, 3, 4])
    targets = np.zeros((5, J, 7, 7))
    for i, n in enumerate(held):
        targets[n] = np.stack([place_epsf(psf[i, j], tuple(eps[n, j]), S) for j in range(J)])
    assert predicted_nodes_nmse(psf, targets, eps, held, S)["full"] == pytest.approx(0.0, abs=1e-20)
    assert predicted_nodes_nmse(1.1 * psf, targets, eps, held, S)["full"] == pytest.approx(0.01)
    basis = np.linalg.qr(psf.reshape(3, -1).T)[0].T.reshape(psf.shape)  # spans the three PSFs
    result = predicted_nodes_nmse(psf, targets, eps, held, S, basis=basis[:3])
    assert result["rank"] == pytest.approx(0.0, abs=1e-20) and result["K"] == 3
