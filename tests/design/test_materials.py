"""Refractive indices against catalogue values."""

import numpy as np
import pytest

from cm2optics.design.materials import Material, refractive_index


@pytest.mark.parametrize(
    ("material", "wavelength_nm", "expected"),
    [
        (Material.N_BK7, 587.56, 1.5168),
        (Material.N_BK7, 486.13, 1.5224),
        (Material.PMMA, 589.3, 1.4906),
        (Material.CLEAR_RESIN, 589.0, 1.510),
    ],
)
def test_catalogue_values(material, wavelength_nm, expected):
    assert refractive_index(material, wavelength_nm) == pytest.approx(expected, abs=6e-4)


def test_normal_dispersion_and_arrays():
    lam = np.array([450.0, 550.0, 650.0])
    n = refractive_index(Material.PMMA, lam)
    assert n.shape == (3,) and np.all(np.diff(n) < 0)


@pytest.mark.parametrize("bad", [np.nan, 100.0, 5000.0])
def test_wavelength_out_of_range(bad):
    with pytest.raises(ValueError, match="wavelength_nm"):
        refractive_index(Material.N_BK7, bad)


def test_opaque_material_has_no_index():
    with pytest.raises(ValueError, match="opaque"):
        refractive_index(Material.BLACK_RESIN, 500.0)
