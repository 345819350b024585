"""Fixtures the calibration tests share."""

from __future__ import annotations

import pytest

from cm2optics.calibrate.simulate import AnalyticSimulator
from cm2optics.lsv.toy import AnalyticCM2


@pytest.fixture(scope="module")
def simulator(v2) -> AnalyticSimulator:
    """The closed-form CM²-like simulator at 8× binning, its spacing effect 0.5 magnification per mm."""
    return AnalyticSimulator(AnalyticCM2.from_design(v2, binning=8, sigma0_um=30.0), spacing_magnification_per_mm=0.5)
