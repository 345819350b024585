"""`cm2 calibrate illumination`: a measured map against the traced design — registration, the
illumination effects named by the BIC and measured, the report.

Synthetic maps (:mod:`illumination_maps`): the design as built traced with 5× to 10× the model's
rays on a 200 × 200 camera grid of 50 µm, Poisson noise, the optical axis at ``OFFSET_MM`` from the
image's centre (the fitted offset is the axis's position in the image); the tool is not told what
was injected. Tolerances of the illumination effects (beside the scan library's in
``test_calibrate.py``; ≈ 2σ of the precision measured at these ray counts, BENCHMARKS.md):
relative LED flux ± 0.1 on cm2-v2 (± 0.19 on V1 at 200 000 model rays, whose even map fixes a
flux less well: 3× the spread measured over 15 runs), unit tilt ± 1° about each axis (± 0.5° for
the pair's tilt with 1 000 000 model rays), collimator decentre ± 0.05 mm, offset ± 0.08 mm on
cm2-v2 (V1's map does not fix it). Detection limit (BENCHMARKS.md): a 2° tilt is not named at
400 000 model rays. Of the effect matrix (every effect alone at two magnitudes) LED 0 at 70 %, unit 3
tilted (3°, 3°) (named at 500 000 model rays, measured by the final refit at 2 000 000) and the 0.25-mm
collimator decentre are here (slow) and the 0.15-mm one as a strict xfail (below the noise at
500 000 model rays once χ² counts the tent kernel's correlation); the other cases have not passed a
run yet. The clean maps of ten seeds (a 20 M-ray truth, the model's seed varied with the map's) yield
nothing: a far collimator decentre, whose traces the model's Monte Carlo noise decorrelates, is
judged on 8 independent traces (3 of 10 seeds kept one with a single held-out trace; BENCHMARKS.md,
sessions 13–14).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import tifffile
import yaml
from typer.testing import CliRunner

from cm2optics.calibrate.illumination import (
    HELD_OUT_TRACES,
    TracedMaps,
    _effect_slots,
    _Fit,
    _held_out_threshold,
    _nuisance_slots,
    bin_measured_map,
    calibrate_illumination,
    illumination_effects,
    tent_deposit,
    tent_weights,
)
from cm2optics.cli import app
from cm2optics.design import design_from_dict

sys.path.insert(0, str(Path(__file__).parent))
from illumination_maps import measured_map, unit_pixel_maps  # noqa: E402

OFFSET_MM = (0.1, -0.05)


def test_the_comparison_grid_averages_the_map_and_moves_it_smoothly():
    """A ramp v = 10 + 2·x (x in mm) on a 20-µm grid: every centre holds the ramp there (the tent
    kernel is symmetric), and
    the map with the axis at offset o holds the ramp at x + o (bilinear resampling is exact on a ramp)."""
    n, pixel_um = 500, 20.0
    x = (np.arange(n) - (n - 1) / 2) * pixel_um / 1000
    image = np.broadcast_to(10 + 2 * x[None, :], (n, n))
    grid = bin_measured_map(image, pixel_um, 0.5, 4.0)
    assert grid.values.size > 100 and np.all(np.hypot(*grid.centres_mm.T) <= 4.0)
    assert np.allclose(grid.values, 10 + 2 * grid.centres_mm[:, 0], atol=1e-9)
    assert np.allclose(grid.values_at(np.array([0.13, -0.2])), 10 + 2 * (grid.centres_mm[:, 0] + 0.13), atol=1e-9)


def test_rays_share_their_power_by_the_pixels_kernel_and_move_the_model_smoothly():
    """Every point's deposit is the product of its tent weights along x and y (the kernel the map's
    pixels get); one well inside the grid deposits exactly 1; moving all points by δ changes the
    deposit by at most 2δ/pitch per point (box bins: whole points jump between bins)."""
    grid = bin_measured_map(np.ones((500, 500)), 20.0, 0.5, 4.0)
    centres = -grid.half_mm + grid.bin_mm * (np.arange(grid.side) + 0.5)
    points = np.random.default_rng(1).uniform(-2.1, 2.1, (400, 2))
    group = np.arange(400) % 2
    weights, squares = tent_deposit(grid, points, group, 2)
    for g in (0, 1):
        mine = points[group == g]
        expected = np.einsum(
            "yp,xp->yx", tent_weights(centres, mine[:, 1], 0.5), tent_weights(centres, mine[:, 0], 0.5)
        )
        expected_sq = np.einsum(
            "yp,xp->yx", tent_weights(centres, mine[:, 1], 0.5) ** 2, tent_weights(centres, mine[:, 0], 0.5) ** 2
        )
        assert np.allclose(weights[g], expected.ravel()[grid.index], atol=1e-12)
        assert np.allclose(squares[g], expected_sq.ravel()[grid.index], atol=1e-12)
    assert weights.sum() == pytest.approx(400.0, abs=1e-9)  # |x|, |y| ≤ 2.1: all four centres used
    moved, _ = tent_deposit(grid, points + 1e-3, group, 2)
    assert 0 < np.abs(moved - weights).sum() <= 400 * 4 * 2 * 1e-3 / 0.5


def test_noise_only_maps_give_the_tent_kernels_correlation_and_chi2_of_n_degrees_of_freedom():
    """400 noise-only maps on the comparison grid: a camera frame's Poisson counts (≈ 100 per
    pixel, a gentle ramp) plus a traced model's Monte Carlo noise (Poisson, 3000 rays on average
    spread evenly over 4.6 × 4.6 mm, each deposited by the tent kernel). The closed forms: each
    centre's variance is the code's (counts / effective pixels + Σ weight² per ray), neighbours
    along an axis correlate by ¼ and diagonally by 1/16; the whitened χ² has mean B and variance
    2B; a smooth pattern (a constant) fitted to the noise lowers the whitened χ² by χ²(1), mean 1
    — weighted by σ alone it lowered it by ≈ 2 (the correlation's (1 + 2·¼)² = 2.25 inside the
    field), which made a smooth effect look twice as significant as it is."""
    rng = np.random.default_rng(3)
    draws, n, pixel_um, rays, reach, scale = 400, 120, 50.0, 3000, 2.3, 0.1
    x = (np.arange(n) - (n - 1) / 2) * pixel_um / 1000
    mean_image = np.broadcast_to(100 * (1 + 0.1 * x[None, :]), (n, n))
    grid = bin_measured_map(mean_image, pixel_um, 0.5, 2.5)
    assert np.abs(grid.centres_mm).max() + grid.bin_mm <= reach  # every used kernel inside the rays' square
    frames = rng.poisson(mean_image, (draws, n, n)).astype(float)
    norm = np.outer(grid.rows.sum(1), grid.cols.sum(1)).ravel()[grid.index]
    camera = (grid.rows @ frames @ grid.cols.T).reshape(draws, -1)[:, grid.index] / norm
    counts = rng.poisson(rays, draws)
    points = rng.uniform(-reach, reach, (counts.sum(), 2))
    traced, _ = tent_deposit(grid, points, np.repeat(np.arange(draws), counts), draws)
    density = rays / (2 * reach) ** 2  # rays per mm²: E[Σ w] = density·h², E[Σ w²] = density·(2h/3)²
    values = camera + scale * traced
    expected = grid.values + scale * density * 0.25
    variance = grid.values / grid.pixels + scale**2 * density * (2 * 0.5 / 3) ** 2
    z = (values - expected) / np.sqrt(variance)
    assert np.var(z, axis=0).mean() == pytest.approx(1.0, abs=0.04)
    correlation = np.corrcoef(z.T)
    step = np.abs(grid.index[:, None] - grid.index[None, :])
    same_row = (grid.index[:, None] // grid.side) == (grid.index[None, :] // grid.side)
    assert correlation[(step == 1) & same_row].mean() == pytest.approx(0.25, abs=0.02)
    assert correlation[step == grid.side].mean() == pytest.approx(0.25, abs=0.02)
    assert correlation[(step == grid.side + 1) | (step == grid.side - 1)].mean() == pytest.approx(1 / 16, abs=0.02)
    white = grid.whiten(z.T).T
    chi2 = (white**2).sum(1)
    b = grid.values.size
    assert chi2.mean() == pytest.approx(b, abs=3 * np.sqrt(2 * b / draws))
    assert chi2.var() / (2 * b) == pytest.approx(1.0, abs=0.25)
    smooth = grid.whiten(np.ones(b))
    assert np.mean((white @ smooth) ** 2 / (smooth @ smooth)) == pytest.approx(1.0, abs=0.21)
    assert np.mean(z.sum(1) ** 2 / b) > 1.5


def test_the_held_out_threshold_passes_a_candidate_no_better_than_the_model_rarely():
    """The held-out check's null: on each of K independent traces the current model's χ² and a far
    candidate's are independent χ²(dof) draws (no rays shared), the candidate also paying the BIC's
    penalty for its 2 parameters. The mean ΔBIC over K traces has the spread the threshold assumes,
    √(4·dof/K), and exceeds the threshold with a chance ≤ Φ(−3) = 0.13 %; a candidate whose true
    gain is the threshold plus 2σ passes ≈ 98 % of the time."""
    rng = np.random.default_rng(5)
    dof, k, draws, penalty = 203, HELD_OUT_TRACES, 200_000, 2 * np.log(208)
    difference = rng.chisquare(dof, (draws, k)) - rng.chisquare(dof, (draws, k))
    sigma = np.sqrt(4 * dof / k)
    assert difference.mean(1).std() == pytest.approx(sigma, rel=0.01)
    needed = _held_out_threshold(dof, k)
    assert needed == pytest.approx(3 * sigma)
    null = (difference - penalty).mean(1)
    assert np.mean(null >= needed) < 0.0013
    real = (difference + needed + 2 * sigma).mean(1)  # its ΔBIC's mean: the threshold + 2σ
    assert np.mean(real >= needed) == pytest.approx(0.977, abs=0.01)
    assert _held_out_threshold(dof, 10_000) == 10.0  # never below the BIC's threshold


class _NoisyTemplates:
    """Two units' traced maps on B bins as Poisson counts of ``rays`` per unit of ``expected``
    (power per ray 1/rays), against ``data`` without noise (the camera's shot noise negligible)."""

    units = 2

    def __init__(self, expected: np.ndarray, rays: int, rng: np.random.Generator, data: np.ndarray):
        self.counts = rng.poisson(expected * rays)
        self.per_ray = 1.0 / rays
        self.measured = SimpleNamespace(
            values_at=lambda offset: data, pixels=np.full(data.size, 1e12), whiten=lambda x: x
        )  # independent bins

    def maps(self, geometry):
        return self.counts * self.per_ray, self.counts * self.per_ray**2


def test_the_linear_values_are_corrected_for_the_traced_maps_monte_carlo_noise():
    """Two nearly alike unit maps (1 ± 0.3 x), unit 1 at flux 0.5, each map traced with 100 rays per
    bin, 400 draws: plain least squares reads the flux high, as the first-order errors-in-variables
    closed form says, (XᵀWX + D)⁻¹XᵀWd with D the maps' Σ w·variance (0.553); corrected for that
    noise it reads 0.5."""
    x = np.linspace(-1, 1, 200)
    expected = np.stack([1 + 0.3 * x, 1 - 0.3 * x])
    data = 50 * (expected[0] + 0.5 * expected[1])
    flux = next(e for e in illumination_effects(2, False) if e.name == "led_flux" and e.unit == 1)
    slots = _nuisance_slots(0.05)[:1] + _effect_slots(flux)
    rng = np.random.default_rng(0)
    plain, corrected = [], []
    for _ in range(400):
        fit = _Fit(_NoisyTemplates(expected, 100, rng, data), np.ones(2), np.zeros((2, 4)), 1.0)
        plain.append(fit.profiled(slots, np.array([50.0, 1.0]))[0][1])
        corrected.append(fit.profiled(slots, np.array([50.0, 1.0]), template_noise=True)[0][1])
    w = 1 / (50**2 * expected.sum(0) / 100)  # the weights at flux 1: the maps' Monte Carlo variance
    maps = 50 * expected
    coef = np.linalg.solve((maps * w) @ maps.T + np.diag((w * 50**2 * expected / 100).sum(1)), (maps * w) @ data)
    sem = np.std(plain) / 20
    assert np.mean(plain) == pytest.approx(coef[1] / coef[0], abs=3 * sem) and coef[1] / coef[0] > 0.5 + 10 * sem
    assert np.mean(corrected) == pytest.approx(0.5, abs=3 * np.std(corrected) / 20)


@pytest.mark.slow  # 6 traces: ≈ 5 s of CPU after the tracer's compilation, 13 s with it
def test_the_traced_models_monte_carlo_variance_and_chi2_hold_on_independent_traces(v2):
    """cm2-v2 traced 6 times with independent rays (20 000 each) on the comparison grid: at every
    centre the variance across the traces is the code's Monte Carlo variance (Σ w² per ray), and two
    traces compared with that noise (scale fitted, generalised χ²) give χ²_red ≈ 1 — the noise model
    holds on the real tracer, beams' sharp edges and field edge included. (A clean map's χ²_red of
    1.29 against the model's seed 0 is that seed's draw of the model's noise, shared by every map
    compared with it, plus the synthetic truth's own ray noise: BENCHMARKS.md, session 13.)"""
    grid = bin_measured_map(np.ones((200, 200)), 50.0, 0.5, 4.0)
    traces = [TracedMaps(v2, grid, 20_000, seed).maps(np.zeros((4, 4))) for seed in range(6)]
    means = np.array([m.sum(0) for m, _ in traces])
    variances = np.array([v.sum(0) for _, v in traces])
    ratio = means.var(0, ddof=1) / variances.mean(0)
    assert ratio.mean() == pytest.approx(1.0, abs=3 * ratio.std() / np.sqrt(ratio.size))
    chi2 = []
    for a, b in zip(range(0, 6, 2), range(1, 6, 2), strict=True):
        k = means[a].sum() / means[b].sum()
        r = grid.whiten((means[a] - k * means[b]) / np.sqrt(variances[a] + k**2 * variances[b]))
        chi2.append(r @ r / (grid.values.size - 1))
    assert np.mean(chi2) == pytest.approx(1.0, abs=3 * np.sqrt(2 / (grid.values.size - 1) / len(chi2)))


def test_the_fit_traces_a_tilt_and_a_decentre_as_the_design_injects_them(v2):
    """The tool's geometry (tilt about x, y in degrees; collimator dx, dy in mm, per unit) traces
    exactly the rays that ``illumination_as_built`` does for the same values (same seed): the fit
    and the injection agree on units, axes and signs."""
    changes = {
        "led_tilt_deg": [[1.5, -2.0], [0, 0], [0, 0], [0, 0]],
        "collimator_decenter_mm": [[0, 0], [0, 0], [0.1, -0.2], [0, 0]],
    }
    built = v2.with_changes({f"illumination_as_built.{k}": v for k, v in changes.items()})
    units = unit_pixel_maps(built, rays=20_000, seed=3)
    grid = bin_measured_map(units.sum(0), 50.0, 0.5, 4.0)
    geometry = np.zeros((4, 4))
    geometry[0, :2], geometry[2, 2:] = (1.5, -2.0), (0.1, -0.2)
    hits, unit, _ = TracedMaps(v2, grid, 20_000, 3)._hits(geometry)
    half = units.shape[-1] * 0.05 / 2
    traced = np.stack(
        [
            np.histogram2d(hits[unit == u, 1], hits[unit == u, 0], bins=units.shape[-1], range=[[-half, half]] * 2)[0]
            for u in range(4)
        ]
    )
    assert units.sum() > 1000 and np.array_equal(traced, units)


@pytest.fixture(scope="module")
def v1_units(v1):
    return unit_pixel_maps(v1, rays=1_000_000, offset_mm=OFFSET_MM)


def test_a_dim_led_is_named_and_measured_a_clean_map_yields_nothing(v1, v1_units):
    """V1 (bare LEDs), the model traced with 200 000 rays, the flux candidates only (the tilts are
    the slow tests'): LED 2 at 50 % is named alone and measured; the same map at full flux yields
    no effect. Tolerance ± 0.19: 3× the spread measured over 15 runs of this case (truth traces and
    camera noise of seeds 7–16, model seeds 0–5: 0.531 ± 0.062, BENCHMARKS.md); uncorrected for the
    model's Monte Carlo noise the flux read ≈ 0.60 on average."""
    dim = calibrate_illumination(
        measured_map(v1_units, flux=(1, 1, 0.5, 1)), 50.0, v1, rays=200_000, effect_names=("led_flux",)
    )
    doc = dim.document
    assert [(e["name"], e["unit"]) for e in doc["effects"]] == [("led_flux", 2)]
    flux = doc["effects"][0]
    assert flux["parameters"]["flux"] == pytest.approx(0.5, abs=0.19)
    assert 0 < flux["uncertainties"]["flux"] < 0.1
    assert doc["setup"]["template_noise_corrected"]
    assert doc["chi2_after"] < doc["chi2_before"] and doc["nmse_after"] < doc["nmse_before"]
    # V1's bare LEDs light the whole image almost evenly: the map does not fix the offset (fitted
    # from 0.01 to its 0.5-mm bound in those 15 runs, truth +0.1 mm in x, BENCHMARKS.md): not checked
    assert dim.corrected_design.illumination_as_built.flux(2) == pytest.approx(flux["parameters"]["flux"], abs=1e-4)
    clean = calibrate_illumination(measured_map(v1_units), 50.0, v1, rays=200_000, effect_names=("led_flux",))
    assert clean.document["effects"] == [] and clean.document["unexplained"] == []
    assert clean.corrected_design.illumination_as_built.is_nominal


@pytest.fixture(scope="module")
def v2_tilted_units(v2):
    """cm2-v2 with unit 1 tilted 4° about its x axis, traced with 8 000 000 rays."""
    tilted = v2.with_changes({"illumination_as_built.led_tilt_deg": [[0, 0], [4, 0], [0, 0], [0, 0]]})
    return unit_pixel_maps(tilted, rays=8_000_000, offset_mm=OFFSET_MM)


@pytest.mark.slow
@pytest.mark.timeout(3000)  # ≈ 15 min at load 20 on 2 cores: 8 M truth rays, ≈ 20 traces of 1 M
def test_cli_names_a_tilted_unit_and_a_dim_led_and_writes_a_valid_corrected_design(v2_tilted_units, tmp_path):
    """cm2-v2 with unit 1 tilted 4° and LED 3 at 70 %, against the nominal design through the
    command (model traced with 1 000 000 rays): both effects named, measured within the
    tolerances, the corrected design valid. (A 2° tilt is below this map's noise: not named at
    400 000 rays, BENCHMARKS.md.)"""
    tifffile.imwrite(tmp_path / "map.tif", measured_map(v2_tilted_units, flux=(1, 1, 1, 0.7)))
    args = ["calibrate", "illumination", str(tmp_path / "map.tif"), "--pixel-um", "50", "--rays", "1000000"]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "rep"), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    found = {(e["name"], e["unit"]): e["parameters"] for e in doc["effects"]}
    assert ("led_tilt", 1) in found and ("led_flux", 3) in found, found
    assert found[("led_tilt", 1)]["tilt_x_deg"] == pytest.approx(4.0, abs=0.5)
    assert found[("led_tilt", 1)]["tilt_y_deg"] == pytest.approx(0.0, abs=0.5)
    assert found[("led_flux", 3)]["flux"] == pytest.approx(0.7, abs=0.1)
    assert doc["chi2_after"] < doc["chi2_before"]
    for key in ("nmse_before", "nmse_after", "unexplained", "registration", "uniformity_cv", "radial_profile"):
        assert key in doc
    corrected = design_from_dict(yaml.safe_load((tmp_path / "rep" / "corrected-design.yaml").read_text()))
    assert corrected.illumination_as_built.flux(3) == pytest.approx(found[("led_flux", 3)]["flux"], abs=1e-3)
    for name in ("maps.png", "profiles.png", "report.html", "calibration.json"):
        assert (tmp_path / "rep" / name).is_file()


# ----------------------------------------------------------------------------- the effect matrix
# Illumination effects alone (the tool not told which) on cm2-v2, the design as built traced with
# 20 000 000 rays (40× the model's 500 000, 10× the final refit's 2 000 000; chunks of 4 M, the first
# the earlier 4 M-ray truth), a camera frame of 2000 counts per pixel (Poisson): the map's noise is the
# truth trace's, ≈ 1/10 of the final refit's own Monte Carlo variance per bin, as on a real map, where
# the camera's shot noise is far below the model's. (With the earlier 4 M-ray truth that noise was half
# the final refit's, not in the noise model: decenter-0.25's refit read χ²_red 1.50 against the 1.30
# floor, 1.02 with the truth's variance counted — BENCHMARKS.md, session 14.) Only the cases with a verdict
# are here (BENCHMARKS.md, session 12, the generalised χ²: flux-0.7 passed, 363 s of CPU;
# decenter-0.25 passed, dy −0.200 mm, at the tolerance's edge, 551 s of CPU; decenter-0.15 failed;
# flux-1.4 and tilt-4x got no run; session 14: tilt-3x3y passes with the final refit at 4× the rays,
# (2.88 ± 0.13°, 3.02 ± 0.13°), 1001 s of CPU, 1971 s wall at load 6). Tolerances (module docstring):
# flux ± 0.1, tilt ± 1°, decentre ± 0.05 mm.

_BELOW_NOISE = pytest.mark.xfail(
    strict=True,
    reason="not met (BENCHMARKS.md, session 12): at 500 000 model rays with the generalised χ² a 0.15-mm "
    "decentre is at the detection limit — χ²_red 1.281 before, as on a clean map (1.286), each unit's "
    "decentre refitted and rejected by the one held-out trace then used (ΔBIC −25.8, −6.8, −15.3): no effect "
    "named. Session 14 (not re-run): a traced candidate now needs a mean ΔBIC ≥ 30.2 over 8 held-out "
    "traces; the true 0.25-mm decentre's held-out Δχ² averages 64.5 over 8 traces (measured), a 0.15-mm "
    "one's, ∝ its square, ≈ 23, a ΔBIC ≈ 12: below the threshold, so it stays unnamed at 500 000 rays",
)

#: case → (as-built changes, relative fluxes, the effect key expected, its parameters, tolerance)
SINGLE = {
    "flux-0.7": ({}, (0.7, 1, 1, 1), ("led_flux", 0), {"flux": 0.7}, 0.1),
    "tilt-3x3y": (
        {"led_tilt_deg": [[0, 0], [0, 0], [0, 0], [3, 3]]},
        None,
        ("led_tilt", 3),
        {"tilt_x_deg": 3.0, "tilt_y_deg": 3.0},
        1.0,
    ),
    "decenter-0.15": pytest.param(
        {"collimator_decenter_mm": [[0, 0], [0.15, 0], [0, 0], [0, 0]]},
        None,
        ("collimator_decenter", 1),
        {"dx_mm": 0.15, "dy_mm": 0.0},
        0.05,
        marks=_BELOW_NOISE,
    ),
    "decenter-0.25": (
        {"collimator_decenter_mm": [[0, -0.25], [0, 0], [0, 0], [0, 0]]},
        None,
        ("collimator_decenter", 0),
        {"dx_mm": 0.0, "dy_mm": -0.25},
        0.05,
    ),
}


@pytest.mark.slow
@pytest.mark.timeout(5400)  # flux-0.7: 3491 s wall, 363 s CPU at load 10–24 on 2 cores (2026-11-26)
@pytest.mark.parametrize(
    ("changes", "flux", "key", "truth", "tolerance"),
    list(SINGLE.values()),
    ids=list(SINGLE),
)
def test_each_illumination_effect_alone_is_named_and_measured(v2, changes, flux, key, truth, tolerance):
    built = v2.with_changes({f"illumination_as_built.{k}": v for k, v in changes.items()})
    units = unit_pixel_maps(built, rays=20_000_000, offset_mm=OFFSET_MM, chunk=4_000_000)
    doc = calibrate_illumination(measured_map(units, flux=flux, mean_counts=2000.0), 50.0, v2, rays=500_000).document
    found = {(e["name"], e["unit"]): e["parameters"] for e in doc["effects"]}
    assert list(found) == [key], found
    assert found[key] == pytest.approx(truth, abs=tolerance), found
    assert doc["unexplained"] == []
    reg = doc["registration"]
    assert (reg["offset_x_mm"], reg["offset_y_mm"]) == pytest.approx(OFFSET_MM, abs=0.08)


@pytest.mark.slow
@pytest.mark.timeout(7200)  # 100–160 s of CPU per seed at 200 000 model rays, 8 held-out traces (session 14)
def test_clean_maps_yield_no_effect_for_ten_seeds(v2):
    """The nominal cm2-v2 as the truth (20 000 000 rays: its own ray noise 1 % of the model's, as a
    real map has none), ten camera-noise seeds at 2000 counts per pixel, each calibrated with the
    model traced with its own seed (200 000 rays): the model's Monte Carlo noise, which dominates
    the comparison, is then a new draw for every map — with one model seed every map would share
    the same draw, ten repeats of one test. No effect named, nothing unexplained. (Session 13, one
    held-out trace: seeds 5, 6 and 9 kept a far collimator decentre, the decentred and nominal traces
    nearly independent draws; session 14, a mean over 8 held-out traces against 3σ of its noise: all
    ten name nothing, 96–331 s wall and 100–160 s CPU each at load 3–6 — BENCHMARKS.md.)"""
    units = unit_pixel_maps(v2, rays=20_000_000, offset_mm=OFFSET_MM, seed=100, chunk=4_000_000)
    for seed in range(10):
        image = measured_map(units, mean_counts=2000.0, seed=seed)
        doc = calibrate_illumination(image, 50.0, v2, rays=200_000, seed=seed).document
        assert doc["effects"] == [] and doc["unexplained"] == [], (seed, doc["effects"], doc["chi2_after"])
