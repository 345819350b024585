"""Monte Carlo of manufacturing and assembly errors (``cm2 illum robustness``)."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.illumination.compare import setup_from_options
from cm2optics.illumination.geometry import build_scene, collimator_from_design
from cm2optics.illumination.robustness import (
    Tolerances,
    UnitError,
    draw_errors,
    expected_figures,
    perturbed_scene,
    robustness_study,
    surface_error,
)


@pytest.fixture(scope="module")
def v2_scene(v2):
    return build_scene(v2, collimator_from_design(v2))


def test_surface_error_has_the_stated_rms_is_smooth_and_keeps_the_exit_face(v2_scene):
    mesh = v2_scene.collimator.mesh
    moved = surface_error(mesh, 2.0, np.random.default_rng(3))
    shift = np.asarray(moved.vertices) - np.asarray(mesh.vertices)
    along = np.einsum("ij,ij->i", shift, mesh.vertex_normals)
    assert np.allclose(np.linalg.norm(shift, axis=1), np.abs(along), atol=1e-12)  # along the normals only
    area = np.zeros(len(shift))
    np.add.at(area, mesh.faces.ravel(), np.repeat(mesh.area_faces / 3, 3))
    assert np.sqrt(np.sum(area * along**2) / area.sum()) == pytest.approx(2e-3, rel=1e-9)
    top = mesh.vertices[:, 2] >= mesh.vertices[:, 2].max() - 1e-6
    assert top.sum() >= 4 and np.all(shift[top] == 0)
    # Smooth: vertices joined by a short edge (< 50 µm) move alike (wavelengths ≥ 0.3 mm).
    short = mesh.edges_unique_length < 0.05
    a, b = mesh.edges_unique[short].T
    assert np.corrcoef(along[a], along[b])[0, 1] > 0.95
    assert moved.is_watertight


def test_errors_move_only_their_own_unit(v2_scene):
    errors = [UnitError(np.zeros(2), np.zeros(2), None) for _ in range(v2_scene.units)]
    errors[1] = UnitError(np.array([0.05, -0.02]), np.array([1.0, 0.0]), None)
    moved = perturbed_scene(v2_scene, errors)
    for before, after in zip(v2_scene.parts, moved.parts, strict=True):
        same = np.allclose(before.vertices_mm, after.vertices_mm, atol=1e-9)
        assert same == (before.unit != 1), before.name
    # The LED of unit 1: 50 µm / −20 µm in its own plane, and its axis turned by 1°.
    pose0, pose1 = v2_scene.poses[1], moved.poses[1]
    axis0, axis1 = pose0[:3, 2], pose1[:3, 2]
    assert np.degrees(np.arccos(np.clip(axis0 @ axis1, -1, 1))) == pytest.approx(1.0, abs=1e-9)
    offset = np.linalg.inv(pose0) @ pose1[:, 3]
    assert offset[:3] == pytest.approx(
        [0.05, -0.02 * np.cos(np.radians(1.0)), -0.02 * np.sin(np.radians(1.0))], abs=1e-9
    )


def test_zero_tolerances_give_the_nominal_figures_and_a_seed_repeats(v2, v2_scene):
    setup = setup_from_options(v2, rays=8000, seed=1)
    study = robustness_study(v2_scene, setup, Tolerances(0.0, 0.0, 0.0), samples=2, seed=4)
    for row in study["per_sample"]:
        assert row["delivered_fraction"] == pytest.approx(study["nominal"]["delivered_fraction"], abs=1e-3)
        assert row["uniformity_cv"] == pytest.approx(study["nominal"]["uniformity_cv"], abs=2e-3)
    errors = Tolerances(0.05, 1.0, 2.0)
    first = robustness_study(v2_scene, setup, errors, samples=2, seed=4)
    again = robustness_study(v2_scene, setup, errors, samples=2, seed=4)
    assert first["per_sample"] == again["per_sample"]
    assert first["per_sample"][0]["delivered_fraction"] != first["nominal"]["delivered_fraction"]
    other = draw_errors(v2_scene.collimator, v2_scene.units, errors, np.random.default_rng(5))
    assert not np.allclose(other[0].led_offset_mm, first["per_sample"][0]["led_offset_mm"][0])


def test_expected_figures_are_the_means_of_the_builds_and_score_the_mean_cv():
    rows = [
        {"delivered_fraction": 0.30, "uniformity_cv_corrected": 0.08},
        {"delivered_fraction": 0.26, "uniformity_cv_corrected": 0.11},
        {"delivered_fraction": 0.28, "uniformity_cv_corrected": 0.14},
    ]
    expected = expected_figures(rows, max_cv=0.10)
    assert expected["expected_delivered_fraction"] == pytest.approx(0.28)
    assert expected["expected_uniformity_cv_corrected"] == pytest.approx(0.11)
    assert expected["share_within_max_cv"] == pytest.approx(1 / 3)
    assert expected["expected_score"] == pytest.approx(0.28 - 2 * 0.01)
    assert expected_figures(rows[:1], max_cv=0.10)["expected_score"] == pytest.approx(0.30)  # no penalty


@pytest.mark.slow
def test_robust_scoring_of_a_sweep_candidate(v2):
    """``cm2 illum optimize --robust-samples``: with no errors the expected figures are the
    nominal ones (the builds trace the candidate's own rays); with errors the same seed draws the
    same builds (the same score) and another seed others."""
    from cm2optics.illumination.optimize import RobustScoring, evaluate_candidate

    def entry(tolerances, seed):
        return evaluate_candidate(v2.to_dict(), {}, 4000, 1, 0.10, threads=1, robust=RobustScoring(2, tolerances, seed))

    exact = entry(Tolerances(0.0, 0.0, 0.0), 4)
    assert exact["expected_delivered_fraction"] == pytest.approx(exact["delivered_fraction"], abs=1e-3)
    assert exact["expected_uniformity_cv_corrected"] == pytest.approx(exact["uniformity_cv_corrected"], abs=2e-3)
    penalty = 2 * max(0.0, exact["expected_uniformity_cv_corrected"] - 0.10)
    assert exact["score"] == exact["expected_score"] == pytest.approx(exact["expected_delivered_fraction"] - penalty)
    assert exact["nominal_score"] == pytest.approx(
        exact["delivered_fraction"] - 2 * max(0.0, exact["uniformity_cv_corrected"] - 0.10)
    )
    errors = Tolerances(0.05, 1.0, 2.0)
    first, again, other = entry(errors, 4), entry(errors, 4), entry(errors, 5)
    figures = ("expected_delivered_fraction", "expected_uniformity_cv_corrected", "score")
    assert [first[k] for k in figures] == [again[k] for k in figures]
    assert first["expected_delivered_fraction"] != other["expected_delivered_fraction"]
    assert first["delivered_fraction"] == other["delivered_fraction"]  # the nominal trace is the same
