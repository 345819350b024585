"""The candidate designs kept under ``benchmarks/designs`` (issue 16; their figures in BENCHMARKS.md)
stay buildable as the collimator code changes: each loads, its collimator profile is computed
inside its footprint and below its flange, its excitation filter rests on the part's exit face,
and its units clear the imaging tower and the base plate."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from cm2optics.design import DesignError, load_preset
from cm2optics.optics.collimator import collimator_profile, tir_wall_reach_mm
from cm2optics.optics.layout import unit_clashes

DESIGNS = sorted((Path(__file__).resolve().parents[2] / "benchmarks" / "designs").glob("*.yaml"))


def test_the_designs_folder_is_found():
    assert len(DESIGNS) >= 3


@pytest.mark.parametrize("path", DESIGNS, ids=lambda p: p.stem)
def test_kept_designs_build_and_clear_the_housing(path):
    design = load_preset(str(path))
    collimator = design.collimator
    profile = collimator_profile(design)  # a DesignError when the wall leaves the footprint or the height
    assert profile.tir_r_mm.max() < collimator.footprint_mm / 2
    reach = tir_wall_reach_mm(
        profile.outer_radius_entry_mm, profile.tir_r_mm[-1], collimator.tir_cos2, collimator.tir_cos4
    )
    assert reach < collimator.footprint_mm / 2  # a wall that departs from revolution fits at every azimuth
    assert profile.tir_z_mm.max() <= profile.flange_bottom_z_mm + 1e-9
    assert design.led_array.excitation_gap_mm == pytest.approx(collimator.led_gap_mm + collimator.height_mm)
    assert unit_clashes(design) == []
    if collimator.led_gap_mm == 0.0:  # the LED at the cavity's mouth: its die must fit inside the cavity
        assert collimator.cavity_radius_mm > design.led.emitter_mm / math.sqrt(2)


def test_die_clearance_design_clears_the_die_by_a_printable_margin():
    """`cm2-v2-die-clearance.yaml` (session 13): the enclosing cavity clears the LED die's corners by
    ≥ 0.1 mm (the ± 50 µm LED placement of issue 16 item 4 + a resin printer's ≈ 50 µm), and its wall,
    which would reach past the footprint around that wider cavity, is cut at ``tir_max_radius_mm``."""
    path = next(p for p in DESIGNS if p.stem == "cm2-v2-die-clearance")
    design = load_preset(str(path))
    collimator = design.collimator
    assert collimator.led_gap_mm == 0.0
    assert collimator.cavity_radius_mm - design.led.emitter_mm / math.sqrt(2) >= 0.1
    profile = collimator_profile(design)
    assert 0.0 < collimator.tir_max_radius_mm < collimator.footprint_mm / 2
    assert profile.tir_r_mm[-1] == pytest.approx(collimator.tir_max_radius_mm, abs=1e-9)
    assert profile.outer_radius_entry_mm == pytest.approx(collimator.cavity_radius_mm + collimator.entry_wall_mm)
    uncut = {"collimator.tir_max_radius_mm": 0.0, "collimator.height_mm": 3.0, "led_array.excitation_gap_mm": 3.0}
    with pytest.raises(DesignError, match="footprint"):  # the uncut wall, however tall, does not fit
        collimator_profile(design.with_changes(uncut))
