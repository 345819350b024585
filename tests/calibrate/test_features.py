"""Focus windows: the pixels away from every focus, cleared disc by disc, equal the full-frame test."""

from __future__ import annotations

import numpy as np

from cm2optics.calibrate.features import away_from_foci


def test_away_from_foci_equals_the_distance_to_every_centre():
    rng = np.random.default_rng(3)
    shape = (40, 56)
    centres = rng.uniform(-6, 62, (5, 7, 2))  # some discs straddle or leave the frame
    radii = rng.uniform(0.5, 9.0, (5, 7))
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    distance = np.hypot(rows - centres[..., 0, None, None], cols - centres[..., 1, None, None])
    expected = np.all(distance > radii[..., None, None], axis=1)
    away = away_from_foci(shape, centres, radii)
    np.testing.assert_array_equal(away, expected)
    assert 0 < away.mean() < 1
    centres[2, 3] = np.nan  # an image with an unknown focus has no pixel away from its foci
    assert not away_from_foci(shape, centres, radii)[2].any()
