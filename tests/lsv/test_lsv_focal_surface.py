"""Best-focus surfaces and the interpolation that follows them: closed forms (the vertex of a
parabola, the effective area of a Gaussian), a toy system with a curved focal field (known
answer), every path of a model with a surface (adjoint identity, the naive reference, sparse and
dense against the exact point image), and model files with and without a surface."""

from __future__ import annotations

from dataclasses import replace

import h5py
import numpy as np
import pytest
from test_lsv_operators import GRIDS, SENSOR, _inner, synthetic_model

from cm2optics.design import load_preset
from cm2optics.formats.emitters import Emitters
from cm2optics.lsv.focal_surface import (
    FocalSurface,
    _robust_fit,
    effective_area,
    estimate_focal_surface,
    stack_best_focus,
)
from cm2optics.lsv.interpolate import defocus_nodes, refine_axis
from cm2optics.lsv.model import ModelError, load_model
from cm2optics.lsv.reference import reference_forward
from cm2optics.lsv.toy import AnalyticCM2, analytic_crops, analytic_geometry, analytic_lsv_model

KAPPA = 0.06  # the toy's field curvature: best focus at z = κ·ρ², mm


def test_stack_best_focus_is_the_vertex_of_a_parabola():
    z = np.array([-0.5, -0.3, -0.2, -0.1, 0.0, 0.15, 0.3, 0.5])  # irregular depths, mm
    vertices = np.array([0.137, -0.26, 0.36, -0.45, 0.55])
    area = 3.0 + 50.0 * (z[None, :] - vertices[:, None]) ** 2
    found = stack_best_focus(area, z)
    np.testing.assert_allclose(found[:3], vertices[:3], atol=1e-12)
    assert np.isnan(found[3]) and np.isnan(found[4])  # smallest at the first / last depth
    flat = stack_best_focus(np.full((2, len(z)), np.inf), z)
    assert np.all(np.isnan(flat))


def test_stacks_that_span_no_area_get_a_clear_error():
    """Stacks at one lateral point (a node and its sub-pixel dithers) cannot fix a surface."""
    x = np.array([3.0, 3.0 + 1e-6, 3.0, 3.0 + 1e-6, 3.0])
    y = np.array([0.0, 0.0, 1e-6, 1e-6, 0.0])
    terms = np.stack([np.ones_like(x), x, y, x * x + y * y], axis=-1)
    with pytest.raises(ValueError, match="span too little of the field"):
        _robust_fit(terms, np.full(5, 0.1), np.ones(5), resolution_mm=0.01)


def test_effective_area_of_a_gaussian_is_four_pi_sigma_squared():
    sigma = 2.5
    r, c = np.mgrid[-30:31, -30:31]
    g = np.exp(-(r**2 + c**2) / (2 * sigma**2))
    crops = np.stack([g, 0.0 * g])[None].astype(np.float32)  # (1, 2, h, w); the second is empty
    area = effective_area(crops)
    assert area[0, 0] == pytest.approx(4 * np.pi * sigma**2, rel=1e-4)
    assert area[0, 1] == np.inf


@pytest.fixture(scope="module")
def toy():
    """A CM² V2-like toy at 8× binning whose lenslets' best focus curves as κ·ρ² and whose PSFs
    depend only on that defocus: no off-axis widening, distortion or vignetting, and foci wide
    enough (σ₀ = 30 µm, 1.6 px) that their sub-pixel phase does not matter."""
    return AnalyticCM2.from_design(
        load_preset("cm2-v2"),
        binning=8,
        field_curvature_per_mm=KAPPA,
        aberration_per_mm2=0.0,
        distortion_um_per_mm3=0.0,
        vignetting_mm=100.0,
        sigma0_um=30.0,
        object_na=0.4,
    )


#: 1-mm lateral nodes, 50-µm depth nodes (the axial interpolation's own error stays below 1 %).
AXES = (np.linspace(-2.0, 2.0, 5), np.linspace(-2.0, 2.0, 5), np.linspace(-0.5, 0.5, 21))


def test_the_focal_surface_of_a_curved_toy_field_is_recovered(toy):
    xs, ys, zs = AXES
    geometry = analytic_geometry(toy, zs)
    positions = np.array([[x, y, z] for z in zs for y in ys for x in xs])
    grid_index = np.array([[ix, iy, iz] for iz in range(len(zs)) for iy in range(len(ys)) for ix in range(len(xs))])
    surface = estimate_focal_surface(analytic_crops(toy, geometry, positions, (20, 20)), grid_index, AXES)
    np.testing.assert_allclose(surface.coefficients[:, 3], KAPPA, rtol=0.01)
    np.testing.assert_allclose(surface.axes_mm(), np.asarray(toy.lenslet_centres_mm), atol=0.01)
    assert np.all(surface.rms_mm < 0.002)
    # the fit evaluates where the lenslets' own best focus is: κ·ρ² from each axis
    rho2 = np.sum((np.array([0.7, -1.2]) - np.asarray(toy.lenslet_centres_mm)) ** 2, axis=1)
    np.testing.assert_allclose(surface.z_best(0.7, -1.2), KAPPA * rho2, atol=0.002)


def _patch_error(model, toy, points) -> float:
    """Mean relative error of the model's focus patches against the toy's true crops (the model's
    units: the toy's scaled by ``model.scale``)."""
    errors = []
    for x, y, z in points:
        truth = analytic_crops(toy, model.geometry, np.array([[x, y, z]]), model.patch_shape)[0]
        patch = model.focus_patches(x, y, z) / model.scale
        errors.append(np.linalg.norm(patch - truth) / np.linalg.norm(truth))
    return float(np.mean(errors))


def test_interpolating_along_the_focal_surface_reproduces_off_node_psfs(toy):
    """Known answer: where the PSF depends only on the defocus from a curved best-focus surface,
    a lateral neighbour's PSF at the same defocus is the PSF; plain trilinear interpolation at
    fixed depth mixes two different defocus states."""
    xs, ys, zs = AXES
    full = len(xs) * len(ys) * len(zs)  # full rank: no low-rank error
    plain = analytic_lsv_model(toy, xs, ys, zs, rank=full, patch_px=20, trim=None)
    curved = analytic_lsv_model(toy, xs, ys, zs, rank=full, patch_px=20, trim=None, focal_surface=True, refine=8)
    assert curved.focal_surface is not None and plain.focal_surface is None
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-1.8, 1.8, 8), rng.uniform(-1.8, 1.8, 8), rng.uniform(-0.4, 0.4, 8)])
    error_plain, error_curved = _patch_error(plain, toy, points), _patch_error(curved, toy, points)
    assert error_curved < 0.015 and error_plain > 0.04  # measured: 0.0078 and 0.052
    # at the nodes both are the nodes' own PSFs
    nodes = [(xs[1], ys[3], zs[2]), (xs[4], ys[0], zs[7])]
    assert _patch_error(curved, toy, nodes) == pytest.approx(_patch_error(plain, toy, nodes), abs=1e-5)


def test_defocus_nodes_keep_the_defocus_and_sum_to_one():
    surface = FocalSurface(np.array([[0.05, 0.02, -0.01, 0.04]]), np.zeros(1))
    axes = (np.array([-1.0, 0.0, 1.0]), np.array([-1.0, 0.0, 1.0]), np.linspace(-0.5, 0.5, 11))
    x, y, z = 0.3, -0.6, 0.12
    nodes, weights = defocus_nodes(surface, axes, 0, x, y, z)
    assert weights.sum() == pytest.approx(1.0)
    defocus = z - surface.z_best(x, y, 0)
    # each lateral node's depth weights average to the depth of the same defocus there
    for ix in (1, 2):
        for iy in (0, 1):
            mine = (nodes[:, 1] == iy) & (nodes[:, 2] == ix)
            depth = np.sum(weights[mine] * axes[2][nodes[mine, 0]]) / np.sum(weights[mine])
            assert depth == pytest.approx(defocus + surface.z_best(axes[0][ix], axes[1][iy], 0), abs=1e-12)


def test_refine_axis_cuts_every_interval():
    np.testing.assert_allclose(refine_axis(np.array([-1.0, -0.3, 1.0]), 2), [-1.0, -0.65, -0.3, 0.35, 1.0])
    np.testing.assert_array_equal(refine_axis(np.array([0.4]), 4), [0.4])


def curved_model(kind: str = "diag", refine: int = 3):
    """The operator tests' synthetic model with a best-focus surface per lenslet."""
    model = synthetic_model(kind)
    rng = np.random.default_rng(7)
    c = np.column_stack(
        [rng.uniform(-0.1, 0.1, 4), rng.uniform(-0.1, 0.1, 4), rng.uniform(-0.1, 0.1, 4), rng.uniform(0.05, 0.2, 4)]
    )
    return replace(model, focal_surface=FocalSurface(c, np.zeros(4)), refine=refine)


@pytest.mark.parametrize("kind", ["diag", "general"])
@pytest.mark.parametrize("grid_name", ["native", "beyond the calibrated volume"])
def test_adjoint_identity_with_a_focal_surface(kind, grid_name):
    model = curved_model(kind)
    op = model.operator(GRIDS[grid_name])
    rng = np.random.default_rng(1)
    x = rng.random(op.grid.shape).astype(np.float32)
    y = rng.normal(size=SENSOR).astype(np.float32)
    Ax, ATy = op.forward(x), op.adjoint(y)
    assert abs(_inner(Ax, y) - _inner(x, ATy)) <= 1e-5 * np.linalg.norm(Ax) * np.linalg.norm(y)
    assert np.linalg.norm(Ax - synthetic_model(kind).operator(GRIDS[grid_name]).forward(x)) > 1e-3 * np.linalg.norm(Ax)


@pytest.mark.parametrize("kind", ["diag", "general"])
def test_fast_operator_equals_the_naive_reference_with_a_focal_surface(kind):
    model = curved_model(kind)
    op = model.operator(GRIDS["coarser"])
    x = np.random.default_rng(2).random(op.grid.shape).astype(np.float32)
    fast, naive = op.forward(x), reference_forward(model, op, x)
    assert np.linalg.norm(fast - naive) / np.linalg.norm(naive) < 1e-5


def test_every_path_images_a_point_alike_with_a_focal_surface():
    model = curved_model("diag")
    # sparse points = exact point images
    emitters = Emitters(
        np.array([0.0, 300.0, -450.0]),
        np.array([0.0, -200.0, 500.0]),
        np.array([0.0, 80.0, -130.0]),
        np.zeros(3),
        np.array([1.0, 2.0, 0.5]),
    )
    expected = sum(
        i * model.point_image(x / 1000, y / 1000, z / 1000)
        for x, y, z, i in zip(emitters.x_um, emitters.y_um, emitters.z_um, emitters.intensity, strict=True)
    )
    image = model.forward_sparse(emitters, subpixel_steps=None)
    assert np.linalg.norm(image - expected) / np.linalg.norm(expected) < 1e-5
    # a single voxel of the dense operator = the point image at the voxel
    op = replace(synthetic_model("diag", zoom=0.0), focal_surface=model.focal_surface, refine=3).operator()
    volume = np.zeros(op.grid.shape, np.float32)
    volume[2, 9, 14] = 1.0
    point = op.model.point_image(op.grid.axis_mm(2)[14], op.grid.axis_mm(1)[9], op.grid.axis_mm(0)[2])
    assert np.linalg.norm(op.forward(volume) - point) / np.linalg.norm(point) < 2e-2
    # at the calibration nodes the coefficients are the nodes' own
    xs, ys, zs = model.axes
    z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
    for j in range(model.n_lenslets):
        np.testing.assert_allclose(
            model.coefficients_at(x, y, z, lenslet=j), np.moveaxis(model.coefficients, 0, -1), atol=1e-5
        )


def test_model_files_with_and_without_a_focal_surface(tmp_path):
    plain = synthetic_model("diag")
    path = plain.save(tmp_path / "plain.h5")
    with h5py.File(path, "r") as f:
        assert int(f.attrs["version"]) == 1 and "focal_surface" not in f  # readable by earlier versions
    assert load_model(path).focal_surface is None
    # a file written before focal surfaces existed (no refine attribute) loads as plain interpolation
    with h5py.File(path, "a") as f:
        del f.attrs["refine"]
    old = load_model(path)
    assert old.focal_surface is None and old.refine == 1
    np.testing.assert_array_equal(old.lenslet_coefficients(2), plain.coefficients)
    curved = curved_model("general")
    for name in ("curved.h5", "curved.npz"):
        loaded = load_model(curved.save(tmp_path / name))
        np.testing.assert_array_equal(loaded.focal_surface.coefficients, curved.focal_surface.coefficients)
        assert loaded.refine == curved.refine
        np.testing.assert_array_equal(loaded.point_image(0.2, -0.1, 0.05), curved.point_image(0.2, -0.1, 0.05))
    with h5py.File(tmp_path / "curved.h5", "a") as f:
        del f["focal_surface/rms_mm"]
    with pytest.raises(ModelError, match="incomplete focal surface"):
        load_model(tmp_path / "curved.h5")


def test_bad_focal_surfaces_are_refused():
    model = synthetic_model("diag")
    with pytest.raises(ModelError, match="needs a focal surface"):
        replace(model, refine=2)
    with pytest.raises(ModelError, match="focal surface has 9 lenslets"):
        replace(model, focal_surface=FocalSurface(np.zeros((9, 4)), np.zeros(9)))
    with pytest.raises(ValueError, match="coefficients contain NaN"):
        FocalSurface(np.full((4, 4), np.nan), np.zeros(4))
    with pytest.raises(ValueError, match="need ≥ 5"):
        estimate_focal_surface(np.zeros((3, 4, 5, 5), np.float32), np.array([[0, 0, 0], [0, 0, 1], [0, 0, 2]]), AXES)


def test_build_and_validate_follow_the_focal_surface_of_a_curved_scan(toy, v2, tmp_path):
    """`cm2 lsv build` finds the toy's curved field from its frames, and `cm2 lsv validate`'s
    leave-one-out (which interpolates as the model does) is better along it than at fixed depth."""
    from cm2optics.lsv.build import build_model
    from cm2optics.lsv.toy import write_analytic_scan
    from cm2optics.lsv.validate import validate_model

    xs, ys, zs = AXES
    scan = write_analytic_scan(tmp_path / "scan", toy, xs, ys, zs[::2], binning=8)
    curved = build_model(scan, rank=64, patch_px=20, design=v2).model
    plain = build_model(scan, rank=64, patch_px=20, design=v2, focal_surface=False).model
    assert plain.focal_surface is None and curved.provenance["focal_surface"]["refine"] == 2
    np.testing.assert_allclose(curved.focal_surface.coefficients[:, 3], KAPPA, rtol=0.1)
    errors = [validate_model(m, scan, ranks=(64,), n_heldout=12)["nmse_heldout"] for m in (plain, curved)]
    assert errors[1] < 0.7 * errors[0]
