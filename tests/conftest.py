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
