"""The shape read from a mean residual patch (`calibrate.unexplained._shape`): a ghost is a copy
on one side of the focus; a focus blurred along one axis (light moved out to both sides) is
described as a wider focus, an aberration, not as a ghost."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, shift

from cm2optics.calibrate.unexplained import PATCH_HALF_PX, _shape

SIZE = 2 * PATCH_HALF_PX + 1


def _focus() -> np.ndarray:
    rows, cols = np.mgrid[0:SIZE, 0:SIZE] - PATCH_HALF_PX
    return 1000.0 * np.exp(-(rows**2 + cols**2) / (2 * 1.2**2))


@pytest.mark.parametrize(("offset", "share"), [((5, -3), 0.04), ((12, 8), 0.02), ((-7, 13), 0.03)])
def test_a_ghost_is_a_displaced_copy(offset, share):
    """Near the focus and beyond session 10's 8-px reach (the probe's ghost at (+12, +8) px)."""
    focus = _focus()
    residual = share * gaussian_filter(shift(focus, offset, order=1), 1.0)
    text = _shape(residual[None], np.array([focus.sum()]), focus[None], 19.2)
    assert text is not None and "displaced copy" in text and f"({offset[0]:+d}, {offset[1]:+d})" in text


def test_a_focus_blurred_along_x_is_wider_not_a_ghost():
    focus = _focus()
    residual = gaussian_filter(focus, (0.0, 1.5)) - focus
    text = _shape(residual[None], np.array([focus.sum()]), focus[None], 19.2)
    assert text is not None and "wider" in text and "not a ghost" in text
    direction = text.split("along (")[1].split(")")[0]
    assert direction.split(",")[0].strip() == "+0"  # along the columns
