"""LSV operators on small synthetic models: adjoint identity, the naive per-(k, z, lenslet)
reference, exact interpolation at the grid nodes, sparse vs dense, batching, files."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.interpolate import chief_ray_nodes
from cm2optics.lsv.lsi import lsi_model
from cm2optics.lsv.model import LSVModel, ModelError, load_model
from cm2optics.lsv.preprocess import Geometry
from cm2optics.lsv.reference import reference_forward

PIXEL_UM = 20.0
SENSOR = (64, 72)


def synthetic_model(
    kind: str = "diag", rank: int = 3, seed: int = 0, shear_px: float = 1.3, zoom: float = 0.03
) -> LSVModel:
    """A 2×2-lenslet model on a 4×3×3 grid with random smooth coefficients, shear, a
    magnification that changes with depth and (``kind``) the stage axes aligned with the
    sensor's ('diag'), swapped ('anti') or rotated by 5° ('general')."""
    rng = np.random.default_rng(seed)
    xs, ys, zs = np.array([-1.0, -0.3, 0.4, 1.0]), np.array([-0.8, 0.0, 0.9]), np.array([-0.2, 0.0, 0.2])
    m = 1000.0 / PIXEL_UM * 0.6  # px per mm
    base = {"diag": np.array([[0.0, -1.0], [-1.0, 0.0]]), "anti": np.array([[-1.0, 0.0], [0.0, 1.0]])}.get(kind)
    if base is None:
        angle = math.radians(5.0)
        base = np.array([[-math.sin(angle), -math.cos(angle)], [-math.cos(angle), math.sin(angle)]])
    A_poly = np.stack([m * base, m * zoom / 0.2 * base])  # A(z) = m·(1 + zoom·z/0.2)·base
    offsets = np.array([[-14.0, -15.0], [-14.0, 16.0], [13.0, -15.0], [13.0, 16.0]])
    shear_dir = np.sign(offsets)
    o_poly = np.stack([offsets, shear_px / 0.2 * shear_dir, 3.0 * shear_dir])
    r0_poly = np.array([[31.3, 35.6], [0.7, -0.4]])
    geometry = Geometry(r0_poly=r0_poly, A_poly=A_poly, o_poly=o_poly, rows=2, cols=2)
    basis = rng.normal(size=(rank, 4, 9, 11)).astype(np.float32)
    coefficients = rng.normal(size=(rank, len(zs), len(ys), len(xs))).astype(np.float32)
    native = 1000.0 / m
    return LSVModel(
        basis,
        coefficients,
        xs,
        ys,
        zs,
        geometry,
        SENSOR,
        PIXEL_UM,
        VolumeGrid((5, 22, 26), (100.0, native, native)),
        provenance={"geometry": {"axis_position_mm": [0.0, 0.0]}},
    )


def _inner(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sum(a.astype(np.float64) * b.astype(np.float64)))


def _check_adjoint_and_naive(model: LSVModel, op, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """⟨Ax, y⟩ = ⟨x, Aᵀy⟩ to float32 precision and the fast forward = the naive reference, for a
    seeded volume x; returns x and Ax."""
    rng = np.random.default_rng(seed)
    x = rng.random(op.grid.shape).astype(np.float32)
    y = rng.normal(size=SENSOR).astype(np.float32)
    Ax, ATy = op.forward(x), op.adjoint(y)
    assert abs(_inner(Ax, y) - _inner(x, ATy)) <= 1e-5 * np.linalg.norm(Ax) * np.linalg.norm(y)
    naive = reference_forward(model, op, x)
    assert np.linalg.norm(Ax - naive) / np.linalg.norm(naive) < 1e-5
    return x, Ax


GRIDS = {
    "native": None,
    "coarser": VolumeGrid((4, 17, 15), (130.0, 45.0, 52.0)),
    "beyond the calibrated volume": VolumeGrid((6, 24, 24), (150.0, 60.0, 60.0)),
}


@pytest.mark.parametrize("kind", ["diag", "anti", "general"])
@pytest.mark.parametrize("grid_name", list(GRIDS))
def test_adjoint_identity_to_float32_precision(kind, grid_name):
    model = synthetic_model(kind)
    op = model.operator(GRIDS[grid_name])
    rng = np.random.default_rng(1)
    x = rng.random(op.grid.shape).astype(np.float32)
    y = rng.normal(size=SENSOR).astype(np.float32)
    Ax, ATy = op.forward(x), op.adjoint(y)
    assert Ax.shape == SENSOR and ATy.shape == op.grid.shape
    lhs, rhs = _inner(Ax, y), _inner(x, ATy)
    assert abs(lhs - rhs) <= 1e-5 * np.linalg.norm(Ax) * np.linalg.norm(y)


@pytest.mark.parametrize("kind", ["diag", "anti", "general"])
def test_fast_operator_equals_naive_per_kz_convolution(kind):
    model = synthetic_model(kind)
    op = model.operator(GRIDS["coarser"])
    x = np.random.default_rng(2).random(op.grid.shape).astype(np.float32)
    fast = op.forward(x)
    naive = reference_forward(model, op, x)
    assert np.linalg.norm(fast - naive) / np.linalg.norm(naive) < 1e-5


def test_coefficients_interpolate_exactly_at_grid_points():
    model = synthetic_model("general")
    xs, ys, zs = model.axes
    z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
    expected = np.moveaxis(model.coefficients, 0, -1)
    np.testing.assert_allclose(model.coefficients_at(x, y, z), expected, atol=1e-6)
    for j in range(model.n_lenslets):
        np.testing.assert_allclose(model.coefficients_at(x, y, z, lenslet=j), expected, atol=1e-5)
    # between nodes, plain trilinear interpolation is linear along each axis
    mid = model.coefficients_at(0.5 * (xs[0] + xs[1]), ys[1], zs[1])
    np.testing.assert_allclose(mid, 0.5 * (model.coefficients[:, 1, 1, 0] + model.coefficients[:, 1, 1, 1]), atol=1e-6)


def test_chief_ray_weights_sum_to_one_and_follow_the_shear():
    model = synthetic_model("diag")
    xs, ys, zs = model.axes
    nodes, weights = chief_ray_nodes(model.geometry, model.axes, 0, 0.1, -0.2, 0.1)
    assert weights.sum() == pytest.approx(1.0)
    assert set(nodes[:, 0].tolist()) == {1, 2}
    # on a calibration depth the chief-ray weights are the plain trilinear ones
    for j in range(model.n_lenslets):
        c = model.coefficients_at(0.13, 0.21, zs[2], lenslet=j)
        np.testing.assert_allclose(c, model.coefficients_at(0.13, 0.21, zs[2]), atol=1e-5)


def test_a_single_voxel_images_like_a_point_source():
    model = synthetic_model("diag", zoom=0.0)
    op = model.operator()
    volume = np.zeros(op.grid.shape, np.float32)
    iz, iy, ix = 2, 9, 14
    volume[iz, iy, ix] = 1.0
    image = op.forward(volume)
    point = model.point_image(op.grid.axis_mm(2)[ix], op.grid.axis_mm(1)[iy], op.grid.axis_mm(0)[iz])
    assert np.linalg.norm(image - point) / np.linalg.norm(point) < 2e-2


def test_orientation_follows_the_geometry():
    """A source moved +x moves its image the way A(z) says (here: inverted, along columns)."""
    model = synthetic_model("diag", shear_px=0.0, zoom=0.0)
    a = model.point_image(0.0, 0.0, 0.0)
    b = model.point_image(0.2, 0.0, 0.0)

    def com(img):
        return (np.indices(img.shape) * img).reshape(2, -1).sum(1) / img.sum()

    shift = com(np.abs(b)) - com(np.abs(a))
    expected = model.geometry.A(0.0) @ np.array([0.2, 0.0])
    np.testing.assert_allclose(shift, expected, atol=0.5)


def test_per_lenslet_images_sum_to_the_measurement_and_batches_match():
    model = synthetic_model("diag")
    op = model.operator(VolumeGrid((3, 12, 14), (150.0, 60.0, 60.0)))
    rng = np.random.default_rng(3)
    volumes = rng.random((2,) + op.grid.shape).astype(np.float32)
    full = op.forward(volumes)
    views = op.forward(volumes, per_lenslet=True)
    assert views.shape == (2, 4) + SENSOR
    np.testing.assert_allclose(views.sum(1), full, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(full[1], op.forward(volumes[1]), rtol=1e-5, atol=1e-5)
    as_tensor = op.forward(torch.as_tensor(volumes[0]))
    assert isinstance(as_tensor, torch.Tensor)
    np.testing.assert_allclose(as_tensor.numpy(), full[0], rtol=1e-5, atol=1e-5)
    back = op.adjoint(rng.random((2,) + SENSOR).astype(np.float32))
    assert back.shape == (2,) + op.grid.shape


def test_wrong_shapes_are_refused():
    op = synthetic_model().operator()
    with pytest.raises(ValueError, match="does not match the grid"):
        op.forward(np.zeros((3, 4, 5), np.float32))
    with pytest.raises(ValueError, match="does not match the sensor"):
        op.adjoint(np.zeros((5, 5), np.float32))


def test_sparse_points_equal_exact_point_images():
    model = synthetic_model("general")
    emitters = Emitters(
        np.array([0.0, 300.0, -450.0]),
        np.array([0.0, -200.0, 500.0]),
        np.array([0.0, 80.0, -130.0]),
        np.zeros(3),
        np.array([1.0, 2.0, 0.5]),
    )
    image = model.forward_sparse(emitters, subpixel_steps=None)
    expected = sum(
        i * model.point_image(x / 1000, y / 1000, z / 1000)
        for x, y, z, i in zip(emitters.x_um, emitters.y_um, emitters.z_um, emitters.intensity, strict=True)
    )
    assert np.linalg.norm(image - expected) / np.linalg.norm(expected) < 1e-5
    rounded = model.forward_sparse(emitters)  # positions rounded to 1/4 px
    assert np.linalg.norm(rounded - expected) / np.linalg.norm(expected) < 0.3


def test_sparse_balls_match_the_dense_model_of_their_volume():
    model = synthetic_model("diag", rank=2, zoom=0.0)
    model = LSVModel(
        np.abs(model.basis),
        np.abs(model.coefficients) + 1,
        *model.axes,
        model.geometry,
        SENSOR,
        PIXEL_UM,
        model.default_grid,
    )
    grid = VolumeGrid((5, 66, 78), (100.0, model.default_grid.voxel_um[1] / 3, model.default_grid.voxel_um[2] / 3))
    op = model.operator(grid)
    # a ball of 6 native pixels' diameter in one depth plane, rasterised finely, against the sparse path
    diameter = 6 * model.default_grid.voxel_um[1]
    z, y, x = grid.axis_um(0), grid.axis_um(1), grid.axis_um(2)
    volume = np.zeros(grid.shape, np.float32)
    centre = (0.0, 40.0, -70.0)
    ry, rx = np.meshgrid(y - centre[1], x - centre[2], indexing="ij")
    disk = np.sqrt(np.clip((diameter / 2) ** 2 - ry**2 - rx**2, 0, None))
    volume[2] = disk / disk.sum()
    dense = op.forward(volume)
    sparse = model.forward_sparse(
        Emitters(np.array([centre[2]]), np.array([centre[1]]), np.array([z[2]]), np.array([diameter]), np.ones(1))
    )
    assert np.linalg.norm(sparse - dense) / np.linalg.norm(dense) < 0.05
    assert sparse.sum() == pytest.approx(dense.sum(), rel=0.02)


def test_lsi_baseline_is_shift_invariant_per_depth():
    model = synthetic_model("diag", shear_px=1.0, zoom=0.05)
    lsi = lsi_model(model)
    assert lsi.coefficients.shape[2:] == (1, 1)
    a = lsi.point_image(0.0, 0.0, 0.1)
    b = lsi.point_image(0.3, -0.2, 0.1)
    step = lsi.geometry.A(0.1) @ np.array([0.3, -0.2])  # the in-focus magnification at every depth
    np.testing.assert_allclose(step, [6.0, -9.0], atol=1e-9)
    shifted = np.roll(a, (6, -9), axis=(0, 1))
    np.testing.assert_allclose(b[12:-12, 12:-12], shifted[12:-12, 12:-12], atol=1e-5)
    lsv = model.point_image(0.3, -0.2, 0.1)
    assert np.linalg.norm(lsv - b) > 0.1 * np.linalg.norm(b)  # the LSV model is not shift invariant
    op = lsi.operator(GRIDS["coarser"])
    x = np.random.default_rng(4).random(op.grid.shape).astype(np.float32)
    y = np.random.default_rng(5).random(SENSOR).astype(np.float32)
    assert abs(_inner(op.forward(x), y) - _inner(x, op.adjoint(y))) <= 1e-5 * abs(_inner(x, op.adjoint(y)))


def test_model_file_round_trip_and_errors(tmp_path):
    model = synthetic_model("general")
    path = model.save(tmp_path / "model.h5")
    loaded = load_model(path)
    np.testing.assert_array_equal(loaded.basis, model.basis)
    np.testing.assert_array_equal(loaded.coefficients, model.coefficients)
    np.testing.assert_allclose(loaded.geometry.A_poly, model.geometry.A_poly)
    assert loaded.default_grid == model.default_grid and loaded.provenance == model.provenance
    x = np.random.default_rng(6).random(model.default_grid.shape).astype(np.float32)
    np.testing.assert_allclose(loaded.forward(x), model.forward(x), rtol=1e-6, atol=1e-6)
    (tmp_path / "junk.h5").write_bytes(b"junk")
    with pytest.raises(ModelError, match="not a readable LSV model"):
        load_model(tmp_path / "junk.h5")
    with pytest.raises(ModelError, match="no such model file"):
        load_model(tmp_path / "missing.h5")
    with pytest.raises(ModelError, match="rank = 9"):
        model.truncated(9)


def cross_coupled_model(cross_px: float = 0.13) -> LSVModel:
    """The 'diag' model with the small stage/sensor cross-coupling of a real fit: A's off-diagonal
    zeros replaced by terms that move a point at the edge of the calibrated field by ``cross_px``."""
    from dataclasses import replace

    model = synthetic_model("diag")
    A_poly = model.geometry.A_poly.copy()
    A_poly[0, 0, 0] = cross_px / 1.0  # px per mm of x (|x| ≤ 1 mm)
    A_poly[0, 1, 1] = -cross_px / 0.9  # px per mm of y (|y| ≤ 0.9 mm)
    return replace(model, geometry=replace(model.geometry, A_poly=A_poly))


@pytest.mark.parametrize("grid_name", ["native", "coarser"])
def test_a_sub_pixel_cross_coupling_stays_exact_and_keeps_no_per_voxel_data(grid_name):
    """A 0.13-px cross term sends the operator down the 'general' path (bilinear splat through the
    full 2×2 map, tents in the stage's x and y), which once stored a sparse matrix per plane and a
    weight image per node (> 22 GB at full size). It must stay exact (adjoint identity, the naive
    reference) while keeping no more than the aligned operator does."""
    model = cross_coupled_model()
    grid = GRIDS[grid_name]
    op = model.operator(grid)
    assert op._kind_all == "general"
    x, Ax = _check_adjoint_and_naive(model, op, seed=3)
    aligned = synthetic_model("diag").operator(grid)
    assert op.memory_bytes() <= aligned.memory_bytes()
    # and it differs from the aligned model's image by the sub-pixel amount only
    assert 0 < np.linalg.norm(Ax - aligned.forward(x)) / np.linalg.norm(Ax) < 0.2


def test_sparse_ball_is_the_point_image_blurred_by_its_ball():
    """A ball's image is the exact point image convolved with the ball's projection, also where
    the blurred focus runs over the sensor's edge (light from foci just off the sensor blurs in)."""
    from dataclasses import replace

    from scipy.signal import fftconvolve

    from cm2optics.lsv.sparse import SIZE_STEP_PX, ball_kernel

    model = synthetic_model("general")
    H, W = model.sensor_shape
    diameter_px = 24 * SIZE_STEP_PX  # a whole size bin: no rounding of the diameter
    kernel = ball_kernel(diameter_px)
    pad = kernel.shape[0]
    g = model.geometry
    r0 = np.array(g.r0_poly, float, copy=True)
    r0[0] += pad
    wider = replace(
        model, geometry=type(g)(r0, g.A_poly, g.o_poly, g.rows, g.cols), sensor_shape=(H + 2 * pad, W + 2 * pad)
    )
    scale = np.sqrt(abs(np.linalg.det(model.geometry.A(0.05)))) / 1000.0  # px per µm
    for x_um in (0.0, -900.0):  # the second set of foci straddles the sensor's left edge
        ball = Emitters(
            np.array([x_um]), np.array([120.0]), np.array([50.0]), np.array([diameter_px / scale]), np.ones(1)
        )
        image = model.forward_sparse(ball, subpixel_steps=None, per_lenslet=True)
        point = wider.point_image(x_um / 1000, 0.12, 0.05, per_lenslet=True)
        expected = np.stack([fftconvolve(p, kernel, mode="same") for p in point])[:, pad:-pad, pad:-pad]
        assert np.linalg.norm(image - expected) / np.linalg.norm(expected) < 1e-5


@pytest.mark.parametrize("how", [{"rotate_aberrations": True}, {"warp_shapes": True}], ids=["turned", "warped"])
def test_a_turned_or_warped_model_keeps_every_path_consistent(how):
    """Neighbours turned with the azimuth (cm2optics.lsv.rotation) or blended by displacement
    interpolation (cm2optics.lsv.warp): the adjoint identity, the naive reference, a single voxel
    against the point image and sparse points against point images."""
    model = replace(synthetic_model("general"), refine=2, **how)
    assert not model.shared_coefficients
    op = model.operator(GRIDS["coarser"])
    _check_adjoint_and_naive(model, op, seed=4)
    emitters = Emitters(
        np.array([120.0, -330.0]), np.array([250.0, 410.0]), np.array([60.0, -90.0]), np.zeros(2), np.ones(2)
    )
    sparse = model.forward_sparse(emitters, subpixel_steps=None)
    expected = sum(
        model.point_image(x / 1000, y / 1000, z / 1000)
        for x, y, z in zip(emitters.x_um, emitters.y_um, emitters.z_um, strict=True)
    )
    assert np.linalg.norm(sparse - expected) / np.linalg.norm(expected) < 1e-5
    # the turn (warp) changed the coefficients between the nodes (else this test would not test it)
    plain = replace(synthetic_model("general"), refine=1)
    assert not np.allclose(model.point_image(0.12, 0.25, 0.06), plain.point_image(0.12, 0.25, 0.06), atol=1e-3)
