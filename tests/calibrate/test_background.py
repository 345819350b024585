"""Background structure (`calibrate.background`): a ramp of light across the sensor that grows
with the exposure is described as such, apart from the foci, which are then read above it;
clean frames show none."""

from __future__ import annotations

import numpy as np
from lattice_scans import DEPTHS, lattice_analysis

from cm2optics.calibrate.background import background_entry, background_structure
from cm2optics.calibrate.unexplained import PATCH_HALF_PX, describe_unexplained

EXPOSURES = np.linspace(0.5, 2.0, len(DEPTHS))[np.random.default_rng(7).permutation(len(DEPTHS))]


def test_a_ramp_of_light_across_the_sensor_is_background_structure_and_the_foci_are_read_above_it():
    """0 → 60 counts across the columns at 1 ms (the median exposure 1.25 ms: 75 counts)."""
    analysis = lattice_analysis(1500.0, 60.0, 0, exposure_ms=EXPOSURES)
    found = background_structure(analysis, EXPOSURES)
    assert found is not None
    assert abs(found.range_counts - 60.0 * np.median(EXPOSURES)) < 8.0
    assert found.highest_px[1] > 170 and found.lowest_px[1] < 10
    entry = background_entry(found, analysis, 9)
    assert entry["lenslets"] == list(range(9)) and "grows with the exposure" in entry["description"]
    assert describe_unexplained(analysis, 19.2)  # read against the model alone, the foci look wrong
    assert (
        describe_unexplained(analysis, 19.2, background=found.patches(analysis.model.centroid_px, PATCH_HALF_PX)) == []
    )


def test_clean_frames_hold_no_background_structure():
    for seed in (1, 2):
        analysis = lattice_analysis(1500.0, 0.0, seed, exposure_ms=EXPOSURES)
        assert background_structure(analysis, EXPOSURES) is None
