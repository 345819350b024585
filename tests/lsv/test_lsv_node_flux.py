"""The rank-K model keeps each calibration node's flux (cm2optics.lsv.build.keep_node_flux)."""

from __future__ import annotations

import numpy as np

from cm2optics.lsv.build import keep_node_flux
from cm2optics.lsv.decompose import decompose


def _crops(n: int = 40, size: int = 48) -> np.ndarray:
    """(n, 1, size, size) foci: a sharp core plus a faint wide halo whose share of the flux grows
    with the node (a defocus halo: much flux, little squared energy)."""
    r, c = np.mgrid[0:size, 0:size] - size // 2
    rho2 = r**2 + c**2
    out = []
    for k in range(n):
        core = np.exp(-rho2 / (2 * (1.0 + 0.05 * k) ** 2))
        halo = np.exp(-rho2 / (2 * (8.0 + 0.2 * k) ** 2)) * (0.002 + 0.0004 * k)
        out.append((core + halo)[None])
    return np.stack(out).astype(np.float32)


def test_each_node_keeps_its_flux_with_the_least_change_of_shape():
    crops = _crops()
    decomposition = decompose(crops, 2)
    flux = crops.reshape(len(crops), -1).sum(axis=1)
    B = decomposition.basis.reshape(2, -1)
    before = decomposition.coefficients @ B.sum(axis=1)
    assert np.max(np.abs(before / flux - 1)) > 0.03  # the truncation drops the halos' flux
    kept, ratio = keep_node_flux(decomposition, crops)
    after = kept.coefficients @ B.sum(axis=1)
    np.testing.assert_allclose(after, flux, rtol=1e-4)
    np.testing.assert_allclose(ratio, before / flux, rtol=1e-6)
    # among coefficient vectors with the right flux, the moved ones fit the crops best (least squares)
    flat = crops.reshape(len(crops), -1).astype(np.float64)
    error = ((kept.coefficients @ B - flat) ** 2).sum(axis=1)
    rng = np.random.default_rng(0)
    b = B.sum(axis=1).astype(np.float64)
    for _ in range(5):
        step = rng.normal(size=2)
        step -= (step @ b) / (b @ b) * b  # keeps the flux
        other = ((kept.coefficients + 0.05 * step) @ B - flat) ** 2
        assert np.all(other.sum(axis=1) >= error - 1e-9)


def test_a_node_the_basis_holds_exactly_is_unchanged():
    crops = _crops(6)
    decomposition = decompose(crops, 6)  # full rank: every node exact
    kept, ratio = keep_node_flux(decomposition, crops)
    np.testing.assert_allclose(ratio, 1.0, atol=1e-4)
    np.testing.assert_allclose(
        kept.coefficients, decomposition.coefficients, atol=1e-4 * np.abs(decomposition.coefficients).max()
    )
