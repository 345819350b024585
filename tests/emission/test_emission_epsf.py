"""The emission module's effective PSFs: sampled at the pixel centres they are the binned foci."""

from __future__ import annotations

import numpy as np

from cm2optics.emission.psf import EmissionModel, PSFSettings
from cm2optics.emission.source import fluorescent_bead


def test_epsf_at_phase_zero_is_the_binned_focus_and_keeps_the_flux(v2):
    S = 4
    model = EmissionModel(v2, fluorescent_bead(2.0), settings=PSFSettings(binning=8, oversample=S))
    assert model._q % S == 0
    foci = model.foci(np.array([0.3, 0.2, 0.05]))
    assert foci
    for focus in foci:
        assert focus.epsf.shape == (focus.patch.shape[0] * S, focus.patch.shape[1] * S)
        np.testing.assert_allclose(focus.epsf[::S, ::S], focus.patch, atol=1e-6 * focus.patch.max())
        assert focus.epsf.sum() / S**2 == np.float32(focus.epsf.sum() / S**2)
        np.testing.assert_allclose(focus.epsf.sum() / S**2, focus.patch.sum(), rtol=0.02)
    plain = EmissionModel(v2, fluorescent_bead(2.0), settings=PSFSettings(binning=8)).foci(np.array([0.3, 0.2, 0.05]))
    assert all(f.epsf is None for f in plain)
