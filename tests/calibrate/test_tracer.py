"""TracerSimulator: the emission tracer driven by effect values written into the design's as-built
section; foci where focus_centres_px says, moved by a rotation and by the frame offset."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.calibrate.effects import library
from cm2optics.calibrate.tracer import TracerSimulator, design_with, source_for
from cm2optics.design import SystemDesign
from cm2optics.emission.source import ProfileKind

POSITIONS = np.array([[0.0, 0.0, 0.0], [0.5, -0.3, 0.2]])


@pytest.fixture(scope="module")
def simulator(v2: SystemDesign) -> TracerSimulator:
    return TracerSimulator(v2, binning=8)


@pytest.fixture(scope="module")
def nominal(simulator: TracerSimulator) -> np.ndarray:
    return simulator.rates(POSITIONS, {})


def _centroids(images: np.ndarray, centres: np.ndarray, half: int = 3) -> np.ndarray:
    """(N, J, 2) intensity centroids in (2·half + 1)² windows around ``centres`` (row, col px)."""
    out = np.full(centres.shape, np.nan)
    rows, cols = np.mgrid[-half : half + 1, -half : half + 1]
    for n, image in enumerate(images):
        for j, (r, c) in enumerate(centres[n]):
            r0, c0 = round(r), round(c)
            window = image[r0 - half : r0 + half + 1, c0 - half : c0 + half + 1]
            if window.shape == rows.shape and window.sum() > 0:
                out[n, j] = r0 + (window * rows).sum() / window.sum(), c0 + (window * cols).sum() / window.sum()
    return out


def test_protocol_and_mapping(simulator: TracerSimulator, v2: SystemDesign):
    assert simulator.lenslets == 9 and simulator.pixel_um == pytest.approx(19.2)
    assert simulator.shape == (v2.sensor.height_px // 8, v2.sensor.width_px // 8)
    assert all(simulator.supports(e) for e in library(9))
    built = design_with(
        v2,
        {
            "mla_spacing": {"delta_mm": 0.02},
            "mla_rotation": {"angle_deg": 0.4},
            "lenslet_transmission[3]": {"transmission": 0.5},
            "lenslet_decenter[8]": {"dx_mm": 0.01, "dy_mm": 0.0},
        },
        offset_px=(1.0, -2.0),
        pitch_um=19.2,
    )
    assert built.imaging.mla_to_sensor_mm == pytest.approx(v2.imaging.mla_to_sensor_mm + 0.02)
    assert built.as_built.mla_rotation_deg == 0.4 and built.as_built.transmission(3) == 0.5
    assert built.as_built.lenslet_offset_mm(8) == (0.01, 0.0)
    assert (built.as_built.sensor_offset_x_um, built.as_built.sensor_offset_y_um) == (38.4, -19.2)
    assert source_for({}, 5.0).profile.kind is ProfileKind.ISOTROPIC
    profile = source_for({"source_profile": {"falloff_per_rad2": 4.0}}, 5.0).profile
    assert profile.kind is ProfileKind.GAUSSIAN and math.isclose(profile.parameter, math.degrees(0.5))


def test_foci_sit_where_focus_centres_px_says(simulator: TracerSimulator, nominal: np.ndarray):
    assert nominal.shape == (2, *simulator.shape) and nominal.dtype == np.float32
    centres = simulator.focus_centres_px(POSITIONS)
    found = _centroids(nominal, centres)
    lit = np.isfinite(found[..., 0])
    assert lit.sum() >= 14
    assert np.nanmax(np.hypot(*(found - centres)[lit].T)) < 1.0


def test_rotation_and_frame_offset_move_the_foci(simulator: TracerSimulator, nominal: np.ndarray):
    centres = simulator.focus_centres_px(POSITIONS)
    before = _centroids(nominal, centres)
    rotated = _centroids(simulator.rates(POSITIONS, {"mla_rotation": {"angle_deg": 1.0}}), centres)
    # on-axis source: a corner focus moves (1 + m)·√2 mm·sin 1° ≈ 1.4 px along the tangent
    step = rotated[0] - before[0]
    corner = 0  # lenslet (row 0, col 0), at (−1, −1) mm: ccw rotation moves it to +x, −y
    assert step[corner, 1] > 1.0 and step[corner, 0] < -1.0
    assert np.hypot(*step[4]) < 0.2  # the central focus stays
    shifted = simulator.rates(POSITIONS[:1], {}, offset_px=(2.0, -1.0))
    np.testing.assert_allclose(shifted[0, 2:, :-1], nominal[0, :-2, 1:], atol=1e-3 * float(nominal.max()))
