"""Interpolation that turns each neighbour's PSF with the field azimuth (cm2optics.lsv.rotation):
the lenslet's axis from the geometry, the rotation's sense on the sensor, and a toy whose PSF is
exactly a rotated function of the field angle."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from cm2optics.lsv import model as model_module
from cm2optics.lsv.epsf_validate import turn_check
from cm2optics.lsv.lsi import lsi_model
from cm2optics.lsv.model import ModelError, load_model
from cm2optics.lsv.preprocess import Geometry
from cm2optics.lsv.rotation import AzimuthTurn, lenslet_axes, rotate_patches, sensor_azimuth

S = 4  # oversample
PATCH = 16  # px
AXIS_MM = np.array([0.05, -0.45])  # the lenslet's axis in object space (off every node)
MIRROR = np.array([[0.0, -1.0], [-1.0, 0.0]])  # (row, col) ← (−y, −x): a mirror image, as CM² V2


def _geometry() -> Geometry:
    """One lenslet with its axis at AXIS_MM; magnification 60 px/mm at z = 0 that changes by
    10 %/mm with depth (so the axis is the one source whose focus stays put)."""
    A_poly = np.stack([60.0 * MIRROR, 6.0 * MIRROR])
    r0 = np.array([200.0, 210.0]) - 60.0 * MIRROR @ AXIS_MM  # the axis's focus at (200, 210)
    r0_poly = np.stack([r0, -6.0 * MIRROR @ AXIS_MM])
    return Geometry(r0_poly=r0_poly, A_poly=A_poly, o_poly=np.zeros((1, 1, 2)), rows=1, cols=1)


def _psf(geometry: Geometry, x: float, y: float, z: float) -> np.ndarray:
    """(1, h·S, w·S) fine PSF: a Gaussian 2.5 × 1 px long along the focus's sensor azimuth about
    the axis's image, wider with |z|: exactly the on-axis-turned PSF of a symmetric lens."""
    phi = float(sensor_azimuth(geometry, AXIS_MM, x, y, z))
    n = PATCH * S
    r, c = np.mgrid[0:n, 0:n] - S * (PATCH // 2)
    along = (r * math.cos(phi) + c * math.sin(phi)) / S
    across = (-r * math.sin(phi) + c * math.cos(phi)) / S
    grow = 1.0 + 3.0 * z * z
    return np.exp(-0.5 * ((along / (2.5 * grow)) ** 2 + (across / grow) ** 2))[None].astype(np.float32)


@pytest.fixture(scope="module")
def toy(grid_toy):
    geometry = _geometry()
    axes = (np.linspace(-1.7, 2.3, 5), np.linspace(-2.2, 1.8, 5), np.array([-0.2, 0.0, 0.2]))
    model, crops, grid_index = grid_toy(lambda x, y, z: _psf(geometry, x, y, z), axes, geometry, S)
    return geometry, model, crops, grid_index


def test_the_lenslet_axis_is_the_source_whose_focus_stays_put():
    np.testing.assert_allclose(lenslet_axes(_geometry(), np.array([-0.2, 0.0, 0.3])), [AXIS_MM], atol=1e-9)
    with pytest.raises(ValueError, match="2 calibration depths"):
        lenslet_axes(_geometry(), np.array([0.0]))


def test_rotate_patches_turns_a_displacement_by_its_angle():
    """A dot at azimuth 0 (one row down from the centre) turned by +90° lands at azimuth 90°
    (one column right): the sense of ``atan2(col, row)``."""
    patch = torch.zeros((1, 21, 21))
    patch[0, 13, 10] = 1.0  # centre (10, 10), displacement (+3, 0)
    turned = rotate_patches(patch, np.array([math.pi / 2]), np.array([10.0, 10.0]))[0].numpy()
    assert np.unravel_index(turned.argmax(), turned.shape) == (10, 13)
    assert math.degrees(float(sensor_azimuth(_geometry(), AXIS_MM, AXIS_MM[0], AXIS_MM[1] - 1.0, 0.0))) == (
        pytest.approx(0.0, abs=1e-9)
    )


def _error(model, geometry, points) -> float:
    errors = []
    for x, y, z in points:
        truth = _psf(geometry, x, y, z)
        patch = model.focus_patches(x, y, z) / model.scale
        errors.append(np.linalg.norm(patch - truth) / np.linalg.norm(truth))
    return float(np.mean(errors))


def test_turning_the_neighbours_reproduces_a_psf_that_turns_with_the_field(toy):
    """Known answer: where the PSF is the on-axis-turned one, each neighbour turned to the source's
    azimuth is the source's PSF; a plain blend of differently oriented neighbours is not."""
    geometry, plain, _, _ = toy
    turned = replace(plain, refine=2, rotate_aberrations=True)
    xs, ys, zs = plain.axes
    # the refined grid's own nodes between the calibration nodes, at and between depths
    points = [(xs[1] + 0.5, ys[2], 0.0), (xs[3], ys[1] + 0.5, 0.2), (xs[0] + 0.5, ys[3] + 0.5, -0.1)]
    error_plain, error_turned = _error(plain, geometry, points), _error(turned, geometry, points)
    assert error_plain > 0.25 and error_turned < 0.03, (error_plain, error_turned)
    # at the calibration nodes both are the nodes' own PSFs
    nodes = [(xs[1], ys[3], zs[2]), (xs[4], ys[0], zs[0])]
    assert _error(turned, geometry, nodes) == pytest.approx(_error(plain, geometry, nodes), abs=1e-4)


def test_the_choice_is_kept_in_the_model_file(toy, tmp_path, monkeypatch):
    _, plain, _, _ = toy
    turned = replace(plain, refine=2, rotate_aberrations=True)
    path = turned.save(tmp_path / "turned.h5")

    def refuse(*args, **kwargs):
        raise AssertionError("the saved turned coefficients were computed again")

    monkeypatch.setattr(model_module, "rotated_lenslet_coefficients", refuse)
    loaded = load_model(path)
    assert loaded.rotate_aberrations and loaded.refine == 2
    np.testing.assert_allclose(loaded.lenslet_coefficients(0), turned.lenslet_coefficients(0), atol=1e-6)
    assert not load_model(plain.save(tmp_path / "plain.h5")).rotate_aberrations
    assert not lsi_model(loaded).rotate_aberrations  # the shift-invariant baseline has no lateral neighbours
    with pytest.raises(ModelError, match="refine ≥ 2"):
        replace(plain, rotate_aberrations=True)
    assert loaded.truncated(5).lenslet_coefficients(0).shape[0] == 5  # the saved turn, first 5 terms
    with pytest.raises(AssertionError, match="computed again"):  # other coefficients: not the saved turn
        replace(loaded, coefficients=loaded.coefficients * 2)


def test_the_scan_decides_for_the_turn_where_the_psf_turns(toy):
    """turn_check (what `cm2 lsv build --rotate auto` decides by): nodes left out, predicted from
    their lateral neighbours, are far better predicted turned on this toy."""
    _, model, crops, grid_index = toy
    check = turn_check(crops, grid_index, model.axes, None, AzimuthTurn.of_model(model), n_heldout=6)
    assert check["n_heldout"] == 6
    assert check["nmse_turned"] < 0.1 * check["nmse_fixed_orientation"], check
