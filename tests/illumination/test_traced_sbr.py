"""The SBR of a traced illumination: fed the model's own beams as if traced, it must give the
emission model's SBR (the same glow, the same mirrored rays); and it reads the traced beam."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.emission.filter_angles import _beam_hits, excitation_footprint
from cm2optics.emission.sbr import signal_and_background
from cm2optics.illumination.geometry import build_scene
from cm2optics.illumination.traced_sbr import COARSE_SAMPLING, traced_background, traced_sbr
from cm2optics.illumination.tracer import RayRecord, Status

BEAM_SAMPLES = 6


def _record_of(hits: np.ndarray, directions: np.ndarray) -> RayRecord:
    n = len(hits)
    return RayRecord(
        unit=np.zeros(n, np.int32),
        status=np.full(n, int(Status.SAMPLE), np.int32),
        hit_mm=hits[:, :2].copy(),
        passed=np.ones(n, bool),
        exit_direction=directions.copy(),
        wavelength_nm=np.full(n, 470.0),
        bounces=np.full(n, 3, np.int32),
        power_mw=1.0,
        units=4,
        rays_per_unit=n // 4,
    )


@pytest.fixture(scope="module")
def model_beams(v2_collimating):
    design = v2_collimating.with_changes(
        {"led_array.aim_mm": 2.5}
    )  # an aim whose steep side a flat sample mirrors back
    hits, directions, _ = _beam_hits(design, BEAM_SAMPLES)
    assert np.all(directions[:, 2] > 0)  # every beam ray lands: equal shares as the model's
    return design, build_scene(design, None), _record_of(hits, directions)


def test_the_model_beams_traced_give_the_models_sbr(model_beams):
    design, scene, record = model_beams
    glow = excitation_footprint(design, samples=BEAM_SAMPLES)
    model = signal_and_background(design, glow=glow, beam_samples=BEAM_SAMPLES, **COARSE_SAMPLING)
    traced = traced_sbr(record, scene, **COARSE_SAMPLING)
    assert model.background_by_path["specular"]["interference_only"].sum() > 0
    for path in ("diffuse", "specular"):
        for chain in ("interference_only", "hybrid"):
            assert traced.background_by_path[path][chain] == pytest.approx(model.background_by_path[path][chain])
    assert traced.sbr_hybrid == pytest.approx(model.sbr_hybrid)


def test_rays_that_did_not_land_are_left_out(model_beams):
    _, scene, record = model_beams
    status = record.status.copy()
    status[::2] = int(Status.ABSORBED)
    glow, (origins, directions, power) = traced_background(RayRecord(**{**record.__dict__, "status": status}), scene)
    assert len(origins) == (record.rays + 1) // 2
    assert power.sum() < 1.0  # the Fresnel share of the landed power
    assert np.allclose(origins[:, 2], scene.sample_z_mm) and np.all(directions[:, 2] < 0)
    with pytest.raises(ValueError, match="no traced ray landed"):
        traced_background(RayRecord(**{**record.__dict__, "status": np.zeros_like(status)}), scene)


def test_the_sweeps_sbr_floor_scales_the_score_by_the_shortfall(model_beams):
    from cm2optics.illumination.optimize import SBRFloor

    _, scene, record = model_beams
    sbr = traced_sbr(record, scene, **COARSE_SAMPLING)
    short = SBRFloor(2.0 * sbr.sbr_interference_only, 0.5 * sbr.sbr_hybrid).check(record, scene, 0, 0.3)
    assert not short["meets_sbr"] and short["score"] == pytest.approx(0.15)  # half the floor: half the score
    assert short["sbr_hybrid"] == pytest.approx(sbr.sbr_hybrid, rel=1e-4)
    clear = SBRFloor(0.5 * sbr.sbr_interference_only).check(record, scene, 0, -0.1)
    assert clear["meets_sbr"] and clear["score"] == -0.1
    with pytest.raises(ValueError, match="must be a finite number"):
        SBRFloor(hybrid=-1.0)
