"""Shared fixtures: the shipped presets and the original device's reference data."""

from __future__ import annotations

from pathlib import Path

import pytest

from cm2optics.design import SystemDesign, load_preset

REPO = Path(__file__).resolve().parents[1]
REFERENCE_DIR = REPO.parent / "shared" / "reference" / "cm2-v2"


@pytest.fixture(scope="session")
def v2() -> SystemDesign:
    return load_preset("cm2-v2")


#: The paper's collimator architecture (both sub-beams collimated, revolved) at the units' first
#: placement (45° / 6.7 mm, aimed at the field centre): cm2-v2's preset before issue 16 made the
#: uniform design the default. Tests of the collimating optics and the housings' layout use it.
PAPER_COLLIMATOR = {
    "led_array.offset_mm": 6.7,
    "led_array.tilt_deg": 45.0,
    "led_array.azimuth_deg": 0.0,
    "led_array.excitation_gap_mm": 2.0,
    "led_array.aim_mm": 0.0,
    "collimator.led_gap_mm": 0.2,
    "collimator.lens_half_angle_deg": 38.0,
    "collimator.cavity_radius_mm": 0.6,
    "collimator.entry_wall_mm": 0.41,
    "collimator.height_mm": 1.8,
    "collimator.lens_spread_deg": 0.0,
    "collimator.tir_spread_deg": 0.0,
    "collimator.tir_crossing": False,
    "collimator.lens_exponent": 0.5,
    "collimator.tir_exponent": 0.5,
    "collimator.lens_freeform_um": [],
}


@pytest.fixture(scope="session")
def v2_collimating(v2) -> SystemDesign:
    """cm2-v2 with the paper's collimating, revolved collimator at 45° / 6.7 mm (``PAPER_COLLIMATOR``)."""
    design = v2.with_changes(PAPER_COLLIMATOR)
    assert design.collimator.collimates and not design.collimator.is_freeform
    return design


@pytest.fixture(scope="session")
def v1() -> SystemDesign:
    return load_preset("cm2-v1")


@pytest.fixture(scope="module", params=["cm2-v2", "cm2-v1"])
def design(request) -> SystemDesign:
    """Each shipped preset in turn (a module-scoped parametrisation)."""
    return load_preset(request.param)


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    if not REFERENCE_DIR.is_dir():
        pytest.skip(f"reference data of the original device not found at {REFERENCE_DIR}")
    return REFERENCE_DIR
