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


def test_per_lenslet_bases_project_each_lenslet_on_its_own_terms():
    rng = np.random.default_rng(5)
    S, J = 2, 3
    psf = rng.random((4, J, 10, 10))
    eps = rng.uniform(0, 1, (4, J, 2))
    held = np.arange(4)
    targets = np.stack([np.stack([place_epsf(psf[n, j], tuple(eps[n, j]), S) for j in range(J)]) for n in held])
    # lenslet j's basis spans its own four PSFs: no error; its first term only: an error, in that lenslet
    bases = [np.linalg.qr(psf[:, j].reshape(4, -1).T)[0].T.reshape(4, 10, 10) for j in range(J)]
    result = predicted_nodes_nmse(1.1 * psf, targets, eps, held, S, basis=bases, terms=(1, 4))
    assert result["full"] == pytest.approx(0.01) and result["full_per_lenslet"] == pytest.approx([0.01] * J)
    assert result["rank"] == pytest.approx(0.01) and result["K"] == 12 and result["K_per_lenslet"] == [4] * J
    assert result["rank_vs_terms"]["4"] == pytest.approx(0.01) and result["rank_vs_terms"]["1"] > 0.05
    assert result["rank_median"] == pytest.approx(0.01) and result["rank_per_lenslet_nodes"] == [4] * J
    # a dark focus does not enter its lenslet's figure, and adds nothing to the node's
    targets[0, 2] = 0.0
    psf[0, 2] = 0.0
    result = predicted_nodes_nmse(psf, targets, eps, held, S)
    assert result["full_per_lenslet_nodes"] == [4, 4, 3] and result["full"] == pytest.approx(0.0, abs=1e-20)
