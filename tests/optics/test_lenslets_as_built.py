"""lens_cells places the array as built: nominal by default, rotated, decentred, scaled, single
lenslets displaced."""

from __future__ import annotations

import math

import numpy as np

from cm2optics.design import AsBuilt, SystemDesign
from cm2optics.optics.lenslets import lens_cells


def _vertices(cells) -> np.ndarray:
    return np.array([(c.vertex_x, c.vertex_y) for c in cells])


def test_default_as_built_leaves_the_cells_unchanged(design: SystemDesign):
    assert lens_cells(design.mla, design.as_built) == lens_cells(design.mla) == lens_cells(design.mla, AsBuilt())
    full = [c for c in lens_cells(design.mla) if not c.partial]
    assert [(c.vertex_x, c.vertex_y) for c in full] == design.mla.lenslet_centres_mm()
    assert [c.row * design.mla.cols + c.col for c in full] == list(range(design.mla.rows * design.mla.cols))


def test_rotation_rotates_the_lattice(v2: SystemDesign):
    nominal = _vertices(lens_cells(v2.mla))
    rotated = _vertices(lens_cells(v2.mla, AsBuilt(mla_rotation_deg=2.0)))
    a = math.radians(2.0)
    expected = nominal @ np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]).T
    np.testing.assert_allclose(rotated, expected, atol=1e-12)
    assert np.allclose(np.hypot(*rotated.T), np.hypot(*nominal.T))


def test_decentre_pitch_and_single_lenslet(v2: SystemDesign):
    nominal_cells = lens_cells(v2.mla)
    nominal = _vertices(nominal_cells)
    moved = lens_cells(v2.mla, AsBuilt(mla_decenter_x_mm=0.05, mla_decenter_y_mm=-0.02))
    np.testing.assert_allclose(_vertices(moved) - nominal, [[0.05, -0.02]] * len(nominal), atol=1e-12)
    assert math.isclose(moved[0].x_min - nominal_cells[0].x_min, 0.05)  # the footprints move with the array
    scaled = _vertices(lens_cells(v2.mla, AsBuilt(lenslet_pitch_delta_mm=0.02)))
    np.testing.assert_allclose(scaled, nominal * (v2.mla.pitch_mm + 0.02) / v2.mla.pitch_mm, atol=1e-12)
    offsets = [[0.0, 0.0]] * 9
    offsets[2] = [0.03, 0.01]
    one = lens_cells(v2.mla, AsBuilt(lenslet_decenter_mm=tuple(map(tuple, offsets))))
    j = next(i for i, c in enumerate(one) if not c.partial and (c.row, c.col) == (0, 2))
    shift = _vertices(one) - nominal
    np.testing.assert_allclose(shift[j], [0.03, 0.01], atol=1e-12)
    assert np.allclose(np.delete(shift, j, axis=0), 0.0)
    assert (one[j].x_min, one[j].x_max) == (nominal_cells[j].x_min, nominal_cells[j].x_max)  # its cell stays
