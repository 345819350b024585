"""Re-aimed LED units in the CAD assembly: the housings, base plate and unit parts follow the
poses, and the exact interference check agrees with the quick one the design search uses."""

from __future__ import annotations

import pytest

from cm2optics.cad.assembly import aim_interferences
from cm2optics.optics.layout import unit_clashes


@pytest.mark.slow
@pytest.mark.parametrize(
    ("changes", "clear"),
    [
        ({"led_array.aim_mm": 1.0, "led_array.tilt_deg": 40.0}, True),  # aimed short of the centre, flatter
        ({"led_array.aim_mm": -2.0}, False),  # aimed past the centre: the units drop into the tower
    ],
)
def test_aimed_units_in_the_assembly(v2, changes, clear):
    design = v2.with_changes(changes)
    clashes = aim_interferences(design)
    assert (not clashes) is clear, clashes
    assert (not unit_clashes(design)) is clear
    if not clear:
        assert any(c["a"] == "mla_housing" and c["b"].startswith("led_housing") for c in clashes)
