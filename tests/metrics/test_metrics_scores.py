"""Metrics on hand-made cases whose answers are known by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.metrics import (
    MatchOptions,
    breakdown,
    density_breakdown,
    detect_emitters,
    detection_maps,
    evaluate_volume,
    f1_optimal_threshold,
    match_emitters,
    pooled_scores,
    scores,
    volume_emitters,
)

GRID = VolumeGrid((21, 41, 41), (10.0, 4.0, 4.0))


def emitters(rows) -> Emitters:
    rows = np.asarray(rows, float).reshape(-1, 5)
    return Emitters(*rows.T)


def position_um(grid: VolumeGrid, iz: int, iy: int, ix: int) -> tuple[float, float, float]:
    return tuple(float(grid.axis_um(a)[i]) for a, i in zip((2, 1, 0), (ix, iy, iz), strict=True))


def blob(volume: np.ndarray, iz: int, iy: int, ix: int, value: float = 1.0, half: int = 1) -> None:
    """A 3×3×3 (half = 1) block of voxels centred on (iz, iy, ix), its centre brighter."""
    volume[max(iz - half, 0) : iz + half + 1, iy - half : iy + half + 1, ix - half : ix + half + 1] += 0.5 * value
    volume[iz, iy, ix] += 0.5 * value


CENTRES = [(10, 20, 20), (5, 8, 30), (15, 32, 9)]


def truth_at(centres, grid=GRID, diameter=12.0) -> Emitters:
    return emitters([[*position_um(grid, *c), diameter, 1.0] for c in centres])


def test_perfect_match():
    volume = np.zeros(GRID.shape, np.float32)
    for c in CENTRES:
        blob(volume, *c)
    result = evaluate_volume(volume, GRID, truth_at(CENTRES), threshold=0.25)
    m = result.metrics
    assert (m["recall"], m["precision"], m["f1"], m["jaccard"]) == (1.0, 1.0, 1.0, 1.0)
    assert m["n_true"] == m["n_detected"] == 3
    assert m["rmse_lateral_um"] == pytest.approx(0.0, abs=1e-9)
    assert m["rmse_axial_um"] == pytest.approx(0.0, abs=1e-9)


def test_one_false_positive():
    volume = np.zeros(GRID.shape, np.float32)
    for c in CENTRES + [(3, 35, 35)]:
        blob(volume, *c)
    m = evaluate_volume(volume, GRID, truth_at(CENTRES), threshold=0.25).metrics
    assert (m["n_tp"], m["n_fp"], m["n_fn"]) == (3, 1, 0)
    assert m["recall"] == 1.0
    assert m["precision"] == pytest.approx(3 / 4)
    assert m["f1"] == pytest.approx(2 * 3 / (2 * 3 + 1))
    assert m["jaccard"] == pytest.approx(3 / 4)


def test_one_miss():
    volume = np.zeros(GRID.shape, np.float32)
    for c in CENTRES[:2]:
        blob(volume, *c)
    m = evaluate_volume(volume, GRID, truth_at(CENTRES), threshold=0.25).metrics
    assert (m["n_tp"], m["n_fp"], m["n_fn"]) == (2, 0, 1)
    assert m["recall"] == pytest.approx(2 / 3)
    assert m["precision"] == 1.0
    assert m["f1"] == pytest.approx(4 / 5)
    assert m["jaccard"] == pytest.approx(2 / 3)


@pytest.mark.parametrize(("offset", "matched"), [(19.99, True), (20.0, True), (20.01, False), (25.0, False)])
def test_pair_at_the_gate(offset, matched):
    truth = emitters([0, 0, 0, 10.0, 1])  # gate 2 × 10 µm
    detected = emitters([offset * 0.6, 0, offset * 0.8, 0, 1])  # 3-D distance = offset
    m = match_emitters(truth, detected, gate_factor=2.0)
    assert m.n_tp == int(matched)
    s = scores(m.n_tp, m.n_fp, m.n_fn, m.offset_um)
    if matched:
        assert s["rmse_lateral_um"] == pytest.approx(offset * 0.6)
        assert s["rmse_axial_um"] == pytest.approx(offset * 0.8)
    else:
        assert (s["recall"], s["precision"], s["f1"], s["jaccard"]) == (0.0, 0.0, 0.0, 0.0)
        assert s["rmse_lateral_um"] is None and s["rmse_axial_um"] is None


def test_gate_scales_with_each_emitters_diameter():
    truth = emitters([[0, 0, 0, 4.0, 1], [100, 0, 0, 20.0, 1]])
    detected = emitters([[9, 0, 0, 0, 1], [109, 0, 0, 0, 1]])  # both 9 µm away: only the big one matches
    m = match_emitters(truth, detected)
    assert m.true_index.tolist() == [1] and m.detected_index.tolist() == [1]


def test_hungarian_beats_greedy_nearest_neighbour():
    # greedy would pair the detection at x = 9 with B (1 µm) and leave the one at 19 unmatched
    truth = emitters([[0, 0, 0, 6.0, 1], [10, 0, 0, 6.0, 1]])
    detected = emitters([[9, 0, 0, 0, 1], [19, 0, 0, 0, 1]])
    m = match_emitters(truth, detected)
    assert m.n_tp == 2
    assert sorted(zip(m.true_index.tolist(), m.detected_index.tolist(), strict=True)) == [(0, 0), (1, 1)]
    assert m.distance_um.tolist() == pytest.approx([9.0, 9.0])


def test_matching_prefers_the_closer_assignment_when_counts_tie():
    truth = emitters([[0, 0, 0, 10.0, 1], [30, 0, 0, 10.0, 1]])
    detected = emitters([[28, 0, 0, 0, 1], [2, 0, 0, 0, 1]])
    m = match_emitters(truth, detected)
    assert m.true_index.tolist() == [0, 1] and m.detected_index.tolist() == [1, 0]


def test_many_emitters_match_like_one_dense_assignment():
    from scipy.optimize import linear_sum_assignment

    rng = np.random.default_rng(3)
    n = 300
    t = rng.uniform(0, 600, (n, 3))
    d = t[rng.permutation(n)[:250]] + rng.normal(0, 6, (250, 3))
    d = np.vstack([d, rng.uniform(0, 600, (40, 3))])
    truth = emitters(np.c_[t, np.full(n, 8.0), np.ones(n)])
    detected = emitters(np.c_[d, np.zeros(len(d)), np.ones(len(d))])
    m = match_emitters(truth, detected)
    dist = np.linalg.norm(t[:, None] - d[None], axis=2)
    big = dist[dist <= 16].sum() + 1e6
    cost = np.where(dist <= 16, dist, big)
    r, c = linear_sum_assignment(cost)
    ok = cost[r, c] < big
    assert m.n_tp == int(ok.sum())
    assert m.distance_um.sum() == pytest.approx(cost[r, c][ok].sum())


def test_anisotropic_voxels_measure_errors_in_micrometres():
    grid = VolumeGrid((11, 31, 31), (10.0, 2.0, 4.0))  # z 10 µm, y 2 µm, x 4 µm
    volume = np.zeros(grid.shape, np.float32)
    blob(volume, 6, 15, 16, half=0)  # one voxel +z, one voxel +x from the true centre (5, 15, 15)
    truth = truth_at([(5, 15, 15)], grid, diameter=12.0)
    det = detect_emitters(volume, grid, 0.1)
    assert (det.x_um[0], det.y_um[0], det.z_um[0]) == pytest.approx((4.0, 0.0, 10.0))
    m = evaluate_volume(volume, grid, truth, 0.1).metrics
    assert m["n_tp"] == 1
    assert m["rmse_lateral_um"] == pytest.approx(4.0)
    assert m["rmse_axial_um"] == pytest.approx(10.0)
    # the same voxel offset along y is only 2 µm
    volume[:] = 0
    blob(volume, 5, 16, 15, half=0)
    m = evaluate_volume(volume, grid, truth, 0.1).metrics
    assert (m["rmse_lateral_um"], m["rmse_axial_um"]) == pytest.approx((2.0, 0.0))


def test_physical_coordinates_follow_the_design_convention():
    grid = VolumeGrid((3, 5, 7), (10.0, 4.0, 4.0))
    volume = np.zeros(grid.shape, np.float32)
    volume[2, 4, 6] = 1  # last voxel on every axis: +z (towards the device), +y, +x
    det = detect_emitters(volume, grid, 0.5)
    assert (det.x_um[0], det.y_um[0], det.z_um[0]) == pytest.approx((12.0, 8.0, 10.0))


@pytest.mark.parametrize(
    ("tp", "fp", "fn", "expected"),
    [
        (0, 0, 0, (1.0, 1.0, 1.0, 1.0)),  # nothing to find, nothing found
        (0, 0, 4, (0.0, 1.0, 0.0, 0.0)),  # all missed, nothing false claimed
        (0, 3, 0, (1.0, 0.0, 0.0, 0.0)),  # nothing to find, only false positives
        (2, 2, 2, (0.5, 0.5, 0.5, 1 / 3)),
    ],
)
def test_empty_and_degenerate_sets_are_defined(tp, fp, fn, expected):
    s = scores(tp, fp, fn, np.zeros((tp, 3)))
    assert (s["recall"], s["precision"], s["f1"], s["jaccard"]) == pytest.approx(expected)
    assert all(v is None or math.isfinite(v) for v in s.values())
    if tp == 0:
        assert s["rmse_lateral_um"] is None and s["rmse_axial_um"] is None


def test_empty_volume_and_empty_truth():
    empty = np.zeros(GRID.shape, np.float32)
    m = evaluate_volume(empty, GRID, emitters(np.zeros((0, 5))), threshold=0.5).metrics
    assert (m["recall"], m["precision"], m["f1"], m["n_true"], m["n_detected"]) == (1.0, 1.0, 1.0, 0, 0)
    assert volume_emitters(empty, GRID).x_um.shape == (0,)
    threshold, _ = f1_optimal_threshold([(empty, GRID, truth_at(CENTRES))])
    assert math.isfinite(threshold)


def test_ground_truth_from_a_volume_recovers_centres_and_sizes():
    from cm2optics.synth.raster import rasterize_balls

    grid = VolumeGrid((21, 61, 61), (10.0, 4.15, 4.15))
    truth = emitters([[0, 0, 0, 16.0, 3.0], [-80, 60, 50, 12.0, 1.0]])
    volume = rasterize_balls(truth, grid)
    found = volume_emitters(volume, grid)
    m = match_emitters(truth, found)
    assert m.n_tp == 2
    assert np.max(m.distance_um) < 1.0
    assert found.diameter_um[m.detected_index] == pytest.approx(truth.diameter_um[m.true_index], rel=0.25)
    assert found.intensity[m.detected_index] == pytest.approx(truth.intensity[m.true_index], rel=1e-4)


def test_f1_optimal_threshold_separates_emitters_from_dim_clutter():
    volume = np.zeros(GRID.shape, np.float32)
    for c in CENTRES:
        blob(volume, *c, value=1.0)
    for c in [(3, 35, 35), (18, 5, 5)]:
        blob(volume, *c, value=0.1)
    threshold, sweep = f1_optimal_threshold([(volume, GRID, truth_at(CENTRES))])
    assert 0.1 <= threshold < 0.5
    assert max(sweep["f1"]) == 1.0
    assert evaluate_volume(volume, GRID, truth_at(CENTRES), threshold).metrics["f1"] == 1.0


def test_pooled_scores_sum_counts_over_volumes():
    a = np.zeros(GRID.shape, np.float32)
    b = np.zeros(GRID.shape, np.float32)
    for c in CENTRES:
        blob(a, *c)
    blob(b, *CENTRES[0])
    evals = [evaluate_volume(v, GRID, truth_at(CENTRES), 0.25) for v in (a, b)]
    pooled = pooled_scores(evals)
    assert (pooled["n_tp"], pooled["n_fn"], pooled["recall"]) == (4, 2, pytest.approx(4 / 6))


def test_breakdowns_bin_true_emitters_and_detections():
    truth = emitters([[100, 0, -380, 8.0, 1], [1200, 0, 0, 14.0, 1], [3000, 0, 380, 20.0, 1]])
    detected = emitters([[102, 0, -378, 9.0, 1], [3001, 0, 379, 18.0, 1], [2600, 0, 0, 30.0, 1]])
    grid = VolumeGrid((81, 1700, 1700), (10.0, 4.15, 4.15))
    from cm2optics.metrics.scores import Evaluation

    m = match_emitters(truth, detected)
    e = Evaluation(0.5, truth, detected, m, grid, scores(m.n_tp, m.n_fp, m.n_fn, m.offset_um))
    lateral = breakdown(e, "lateral_mm")
    assert [r["n_true"] for r in lateral] == [1, 0, 1, 0, 0, 0, 1]
    assert [r["n_tp"] for r in lateral] == [1, 0, 0, 0, 0, 0, 1]
    assert lateral[5]["n_fp"] == 1 and lateral[5]["precision"] == 0.0  # the false positive at 2.6 mm
    assert lateral[2]["recall"] == 0.0 and lateral[2]["precision"] == 1.0
    depth = breakdown(e, "depth_um")
    assert depth[0]["n_true"] == 1 and depth[-1]["n_true"] == 1 and depth[4]["n_true"] == 1
    size = breakdown(e, "size_um")
    assert [r["n_true"] for r in size] == [1, 0, 0, 1, 0, 0, 1]
    # a true positive is binned by its true size, so recall and precision share the TP
    assert size[0]["n_tp"] == 1 and size[0]["precision"] == 1.0
    assert size[-1]["n_fp"] == 1  # the 30-µm false positive counts in the outermost bin


def test_density_breakdown_groups_volumes():
    evals = []
    volume = np.zeros(GRID.shape, np.float32)
    for c in CENTRES:
        blob(volume, *c)
    for n in (3, 2):
        evals.append(
            evaluate_volume(
                volume if n == 3 else volume * (np.arange(41) < 25)[None, None, :], GRID, truth_at(CENTRES), 0.25
            )
        )
    rows = density_breakdown(evals, [15.0, 17.0])
    assert rows[0]["n_volumes"] == 2
    assert rows[0]["recall_mean"] == pytest.approx((1.0 + 2 / 3) / 2)
    assert rows[0]["recall"] == pytest.approx(5 / 6)
    assert all(r["n_volumes"] == 0 and r["recall"] == 1.0 for r in rows[1:])


def test_maps_count_per_patch():
    grid = VolumeGrid((3, 100, 100), (10.0, 5.0, 5.0))  # 500 × 500 µm field
    truth = emitters([[-100, -100, 0, 10, 1], [100, 100, 0, 10, 1], [110, 110, 0, 10, 1]])
    detected = emitters([[-101, -100, 0, 0, 1], [100, 101, 0, 0, 1], [-150, 150, 0, 0, 1]])
    m = match_emitters(truth, detected)
    from cm2optics.metrics.scores import Evaluation

    e = Evaluation(0.5, truth, detected, m, grid, {})
    maps = detection_maps(e, patch_um=250.0)
    assert maps["recall"].shape == (2, 2)
    assert maps["recall"][0, 0] == 1.0 and maps["recall"][1, 1] == 0.5
    assert np.isnan(maps["recall"][1, 0]) and np.isnan(maps["recall"][0, 1])
    assert maps["precision"][1, 0] == 0.0 and maps["precision"][1, 1] == 1.0


def test_match_options_floor_the_gate_for_points():
    truth = emitters([0, 0, 0, 0.0, 1])
    detected = emitters([3, 0, 0, 0, 1])
    assert match_emitters(truth, detected).n_tp == 0
    assert match_emitters(truth, detected, min_gate_um=4.0).n_tp == 1
    assert MatchOptions().floor_um(GRID) == 10.0


def test_bad_inputs_raise_value_errors():
    with pytest.raises(ValueError, match="gate_factor"):
        match_emitters(truth_at(CENTRES), truth_at(CENTRES), gate_factor=0)
    with pytest.raises(ValueError, match="connectivity"):
        detect_emitters(np.zeros(GRID.shape), GRID, 0.5, connectivity=7)
    with pytest.raises(ValueError, match="does not match"):
        detect_emitters(np.zeros((2, 2, 2)), GRID, 0.5)
    with pytest.raises(ValueError, match="edges"):
        breakdown(evaluate_volume(np.zeros(GRID.shape), GRID, truth_at(CENTRES), 0.5), "depth_um", [0, 0])


def test_merged_evaluations_pool_like_pooled_scores():
    from cm2optics.metrics import merge_evaluations

    a = np.zeros(GRID.shape, np.float32)
    b = np.zeros(GRID.shape, np.float32)
    for c in CENTRES:
        blob(a, *c)
    blob(b, *CENTRES[1])
    blob(b, 3, 35, 35)
    evals = [evaluate_volume(v, GRID, truth_at(CENTRES), 0.25) for v in (a, b)]
    merged = merge_evaluations(evals)
    pooled = pooled_scores(evals)
    for key in ("n_tp", "n_fp", "n_fn", "recall", "precision", "f1"):
        assert merged.metrics[key] == pooled[key], key
    assert merged.matching.true_matched().sum() == 4 and len(merged.truth) == 6
    assert detection_maps(merged)["n_true"].sum() == 6


def test_depth_coded_mip_colours_each_pixel_by_the_plane_of_its_maximum(tmp_path):
    """Known answer: a voxel at plane k of nz takes the colour map's colour at k / (nz − 1),
    scaled by its value ÷ vmax; the brighter of two voxels in a column wins; empty pixels are
    black; the figure of three panels is written."""
    from matplotlib import colormaps

    from cm2optics.metrics.plots import depth_coded_mip, plot_depth_mips

    volume = np.zeros((5, 4, 6))
    volume[0, 1, 2] = 1.0
    volume[4, 2, 3] = 0.5
    volume[1, 3, 5], volume[3, 3, 5] = 0.2, 0.8  # the brighter one, at plane 3, wins
    rgb = depth_coded_mip(volume, vmax=1.0, cmap="viridis")
    colours = colormaps["viridis"](np.linspace(0, 1, 5))[:, :3]
    assert rgb.shape == (4, 6, 3)
    np.testing.assert_allclose(rgb[1, 2], colours[0])
    np.testing.assert_allclose(rgb[2, 3], 0.5 * colours[4])
    np.testing.assert_allclose(rgb[3, 5], 0.8 * colours[3])
    lit = np.zeros((4, 6), bool)
    lit[1, 2] = lit[2, 3] = lit[3, 5] = True
    assert np.all(rgb[~lit] == 0)
    np.testing.assert_allclose(depth_coded_mip(volume, cmap="viridis"), rgb)  # own maximum is 1 here
    np.testing.assert_allclose(depth_coded_mip(2 * volume, vmax=1.0, cmap="viridis")[2, 3], colours[4])  # clipped
    assert np.all(depth_coded_mip(np.zeros((3, 2, 2))) == 0)
    with pytest.raises(ValueError, match="z, y, x"):
        depth_coded_mip(np.zeros((4, 4)))
    grid = VolumeGrid((5, 4, 6), (10.0, 2.0, 2.0))
    path = plot_depth_mips(
        [("a", volume, grid, 1.0), ("b", volume, grid, None), ("c", volume, grid, None)], tmp_path / "m.png"
    )
    assert path.stat().st_size > 1000
    with pytest.raises(ValueError, match="planes"):
        plot_depth_mips([("a", volume, grid, 1.0), ("b", volume, VolumeGrid((5, 4, 6), (20.0, 2, 2)), 1.0)], path)
