"""View registration (:mod:`cm2optics.recon.net.register`) against closed forms: a model whose
lenslets' foci sit a known number of pixels from the affine geometry, different on the two
halves of the field, one lenslet dark on one half; the config flag stays out of the hash."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tiny_net import tiny

from cm2optics.lsv.preprocess import Geometry
from cm2optics.recon.net.config import ConfigError, load_config
from cm2optics.recon.net.register import focus_displacements, register_views, registration_map

PX_PER_MM = 100.0
PATCH = 21
#: (J, 2) displacement (row, col) px of each lenslet's focus for sources at x < 0 and at x ≥ 0
LEFT = np.array([[0, 0], [2, -1], [-3, 0], [1, 1]], float)
RIGHT = np.array([[0, 0], [-2, 3], [0, 4], [1, 1]], float)
DARK_LEFT = 3  # this lenslet gets no light from sources at x < 0


def _blob(shift: np.ndarray) -> np.ndarray:
    r = np.arange(PATCH) - PATCH // 2
    rr, cc = np.meshgrid(r, r, indexing="ij")
    return np.exp(-((rr - shift[0]) ** 2 + (cc - shift[1]) ** 2) / (2 * 1.5**2))


class DisplacedFoci:
    """A duck-typed 3D-LSV model: two basis patches per lenslet (its focus at LEFT and at RIGHT),
    the first weighting sources at x < 0, the second those at x ≥ 0."""

    oversample = 1

    def __init__(self):
        J = len(LEFT)
        self.basis = np.zeros((2, J, PATCH, PATCH), np.float32)
        for j in range(J):
            self.basis[0, j] = 0.0 if j == DARK_LEFT else _blob(LEFT[j])
            self.basis[1, j] = _blob(RIGHT[j])
        offsets = np.array([[-20, -20], [-20, 20], [20, -20], [20, 20]], float)
        A = np.array([[0.0, PX_PER_MM], [PX_PER_MM, 0.0]])  # row = a·y, col = a·x
        self.geometry = Geometry(np.array([[100.25, 100.0]]), A[None], offsets[None], 2, 2)

    def coefficients_at(self, x_mm, y_mm, z_mm, lenslet=None):
        left = np.asarray(x_mm, float) < 0
        return np.stack([left, ~left], axis=-1).astype(np.float32)


def test_focus_displacements_are_the_foci_offsets_and_dark_lenslets_carry_no_light():
    model = DisplacedFoci()
    shift, light = focus_displacements(model, np.array([-0.5, 0.5]), np.array([0.1, -0.1]))
    np.testing.assert_allclose(shift[0, :DARK_LEFT], LEFT[:DARK_LEFT], atol=1e-6)
    np.testing.assert_allclose(shift[1], RIGHT, atol=1e-6)
    assert light[0, DARK_LEFT] == 0.0 and light[1, DARK_LEFT] > 1.0


class PerLensletFoci(DisplacedFoci):
    """The same foci on a per-lenslet basis: lenslet j's two patches are terms 2j, 2j + 1, dark in
    every other lenslet (``lenslet_terms``), as ``cm2 lsv build --per-lenslet-basis`` stores them."""

    def __init__(self):
        super().__init__()
        K, J = self.basis.shape[:2]
        block = np.zeros((K * J, J, PATCH, PATCH), np.float32)
        for j in range(J):
            block[K * j : K * (j + 1), j] = self.basis[:, j]
        self.basis, self.K = block, K

    def lenslet_terms(self, j):
        return np.arange(self.K * j, self.K * (j + 1))

    def coefficients_at(self, x_mm, y_mm, z_mm, lenslet=None):
        return np.tile(super().coefficients_at(x_mm, y_mm, z_mm), len(LEFT))


def test_a_per_lenslet_basis_gives_the_same_displacements_from_each_lenslets_own_terms():
    x, y = np.array([-0.5, 0.5, 0.2]), np.array([0.1, -0.1, 0.3])
    shared, per_lenslet = focus_displacements(DisplacedFoci(), x, y), focus_displacements(PerLensletFoci(), x, y)
    for a, b in zip(shared, per_lenslet, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_registration_map_reads_each_view_where_its_focus_landed():
    model = DisplacedFoci()
    V = 40
    positions = registration_map(model, V, step_mm=0.02)
    assert positions.shape == (len(LEFT), 2, V, V)
    p = np.arange(V) - V // 2
    identity = np.stack(np.meshgrid(p, p, indexing="ij")) + V // 2 + np.array([0.25, 0.0])[:, None, None]
    far_left, far_right = (slice(None), slice(0, 15)), (slice(None), slice(25, V))  # x < −0.05 mm / x > 0.05 mm
    for j in range(len(LEFT)):
        expected_left = RIGHT[j] if j == DARK_LEFT else LEFT[j]  # dark: its nearest lit place's
        np.testing.assert_allclose(
            positions[j][:, far_left[0], far_left[1]],
            identity[:, far_left[0], far_left[1]] + expected_left[:, None, None],
            atol=1e-4,
        )
        np.testing.assert_allclose(
            positions[j][:, far_right[0], far_right[1]],
            identity[:, far_right[0], far_right[1]] + RIGHT[j][:, None, None],
            atol=1e-4,
        )


def test_registered_views_bring_one_source_to_the_same_pixel_in_every_view():
    model = DisplacedFoci()
    V = 40
    positions = registration_map(model, V, step_mm=0.02)
    source = np.array([V // 2 + 3, V // 2 + 10])  # on the right half: every lenslet lit
    views = np.zeros((len(RIGHT), V, V), np.float32)
    for j, d in enumerate(RIGHT):
        views[j, source[0] + int(d[0]), source[1] + int(d[1])] = 1.0
    registered = register_views(views, np.round(positions))  # whole pixels: the 0.25-px crop fraction aside
    for j in range(len(RIGHT)):
        assert np.unravel_index(np.argmax(registered[j]), (V, V)) == tuple(source)
        assert registered[j].sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="registration map"):
        register_views(views[:2], positions)
    with pytest.raises(ValueError, match="needs a 3D-LSV model"):
        registration_map(object(), V)


def test_register_views_stays_out_of_the_hash_when_false():
    plain = tiny()
    assert plain.with_changes(register_views=True).hash() != plain.hash()
    with pytest.raises(ConfigError, match="register_views"):
        plain.with_changes(register_views="yes")
    shipped = load_config(
        Path(__file__).parents[2] / "reconstruction/cm2net-cpu-traced/config.yaml"
    )  # written before the flag existed
    assert not shipped.register_views
    assert shipped.hash() == "12a5863d093d55ff311ec769b50c170ea9cbd6089691e1057b0f923e7cb3ba3c"  # its model card's
