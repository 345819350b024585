"""Cross-check against an independent code: one lenslet's PSF against Optiland's FFT PSF.

Same prescription (the central lenslet of cm2-v2 with its filter plate and film, constant indices
at one wavelength), same field (on axis and 1 mm off axis, in the nominal focal plane), same
wavelength. ``debye`` is our production model; ``classical`` is the FFT-PSF model of optical
design codes evaluated on our own ray trace (see cm2optics.emission.crosscheck).
"""

from __future__ import annotations

import warnings

import pytest

pytest.importorskip("optiland")

from cm2optics.emission.crosscheck import compare_with_optiland  # noqa: E402


@pytest.mark.parametrize("method", ["debye", "classical"])
@pytest.mark.parametrize("field_mm", [0.0, 1.0])
def test_lenslet_psf_agrees_with_optiland(v2, field_mm, method):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba's pedantic warnings inside Optiland
        result = compare_with_optiland(v2, field_mm=field_mm, method=method)
    assert result.ncc >= 0.95, result
    assert result.strehl_ratio == pytest.approx(1.0, abs=0.05), result
