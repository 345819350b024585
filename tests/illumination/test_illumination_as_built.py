"""The illumination as built: the design's ``illumination_as_built`` section, validated, and
honoured by the tracer (``cm2 illum run``)."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.design import DesignError, load_preset
from cm2optics.design.io import design_from_dict
from cm2optics.illumination.as_built import as_built_scene
from cm2optics.illumination.compare import compare_designs, configurations, setup_from_options
from cm2optics.illumination.geometry import build_scene

BUILT = {
    "illumination_as_built.led_flux": [0.5, 1.0, 1.0, 1.0],
    "illumination_as_built.led_tilt_deg": [[0.0, 0.0], [2.0, -1.0], [0.0, 0.0], [0.0, 0.0]],
}


def test_the_section_is_validated_round_trips_and_leaves_a_nominal_design_unchanged():
    v2 = load_preset("cm2-v2")
    assert "illumination_as_built" not in v2.to_dict()
    nominal = v2.with_changes({"illumination_as_built.led_flux": [1.0] * 4})
    assert nominal.parameter_hash() == v2.parameter_hash()  # all-default: the design as drawn
    built = v2.with_changes(BUILT)
    assert built.parameter_hash() != v2.parameter_hash()
    assert built.to_dict()["illumination_as_built"] == {
        "led_flux": [0.5, 1.0, 1.0, 1.0],
        "led_tilt_deg": [[0.0, 0.0], [2.0, -1.0], [0.0, 0.0], [0.0, 0.0]],
    }
    assert design_from_dict(built.to_dict()) == built
    assert built.illumination_as_built.tilt_deg(1) == (2.0, -1.0)
    assert built.illumination_as_built.decenter_mm(3) == (0.0, 0.0)
    with pytest.raises(DesignError, match="one value per LED unit"):
        v2.with_changes({"illumination_as_built.led_flux": [0.5, 1.0]})
    with pytest.raises(DesignError, match="led_flux"):
        v2.with_changes({"illumination_as_built.led_flux": [2.5, 1, 1, 1]})
    with pytest.raises(DesignError, match="collimator_decenter_mm"):
        v2.with_changes({"illumination_as_built.collimator_decenter_mm": [[0.5, 0], [0, 0], [0, 0], [0, 0]]})


def test_the_scene_as_built_turns_the_unit_about_its_led_and_carries_the_flux():
    v1 = load_preset("cm2-v1").with_changes(BUILT)
    nominal = build_scene(v1, None)
    scene = as_built_scene(nominal)
    assert scene.led_flux == (0.5, 1.0, 1.0, 1.0)
    assert np.allclose(scene.poses[[0, 2, 3]], nominal.poses[[0, 2, 3]])
    assert np.allclose(scene.poses[1][:3, 3], nominal.poses[1][:3, 3])  # turned about the LED's centre
    cos_angle = scene.unit_axes[1] @ nominal.unit_axes[1]
    assert np.degrees(np.arccos(cos_angle)) == pytest.approx(np.hypot(2.0, 1.0), abs=0.01)


def test_illum_run_honours_the_led_flux():
    """LED 0 at half flux emits half the rays, of the same power: its delivered power halves
    (within the Monte Carlo error), the others' stay, the array's total is their sum."""
    v1 = load_preset("cm2-v1")
    half = v1.with_changes({"illumination_as_built.led_flux": [0.5, 1.0, 1.0, 1.0]})
    results = []
    for design in (v1, half):
        setup = setup_from_options(design, rays=40_000, seed=3)
        results.append(compare_designs(design, setup, configurations(design, None))[-1])
    nominal, built = results
    assert built.rays == 3 * 10_000 + 5_000 and built.rays_per_led == 10_000
    assert built.led_flux_mw == nominal.led_flux_mw  # the LED's nominal flux, mW
    for unit, factor in ((0, 0.5), (2, 1.0)):
        a, b = nominal.per_led[unit], built.per_led[unit]
        error = np.hypot(factor * a["power_mw_stderr"], b["power_mw_stderr"])
        assert abs(b["power_mw"] - factor * a["power_mw"]) < 4 * error
    assert built.power_mw.value == pytest.approx(sum(p["power_mw"] for p in built.per_led), rel=1e-4)
