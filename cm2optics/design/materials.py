"""Optical materials and their refractive index n(λ).

Dispersion formulas with their sources; wavelengths in nm at the API, µm inside the
formulas (as the catalogues write them).
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np


class Material(StrEnum):
    """Materials a CM² part can be made of (the YAML spells them by value)."""

    PMMA = "pmma"
    N_BK7 = "n-bk7"
    CLEAR_RESIN = "clear-resin"
    GELATIN = "gelatin"
    BLACK_RESIN = "black-resin"

    @property
    def is_transparent(self) -> bool:
        return self is not Material.BLACK_RESIN


# Sellmeier n² − 1 = Σ Bᵢ λ² / (λ² − Cᵢ), λ in µm.
_SELLMEIER = {
    # Schott N-BK7 catalogue.
    Material.N_BK7: ((1.03961212, 0.231792344, 1.01046945), (0.00600069867, 0.0200179144, 103.560653)),
    # Szczurowski (2013), PMMA at 20 °C, 0.4–1.6 µm (refractiveindex.info).
    Material.PMMA: ((0.99654, 0.18964, 0.00411), (0.00787, 0.02191, 3.85727)),
}

# Cauchy n = A + B / λ², λ in µm: for materials with no catalogue Sellmeier data.
_CAUCHY = {
    # Cured clear methacrylate SLA resin (Formlabs Clear class): published values span
    # n_D ≈ 1.50–1.54; A, B chosen for n(589 nm) = 1.510, n(470 nm) = 1.516.
    Material.CLEAR_RESIN: (1.5000, 0.00348),
    # Gelatin film (Wratten gel filters): n_D ≈ 1.53.
    Material.GELATIN: (1.5200, 0.0035),
}


def refractive_index(material: Material, wavelength_nm: float | np.ndarray) -> float | np.ndarray:
    """Refractive index of ``material`` at ``wavelength_nm`` (nm, 380–1000)."""
    material = Material(material)
    lam_um = np.asarray(wavelength_nm, dtype=float) / 1000.0
    if np.any(~np.isfinite(lam_um)) or np.any(lam_um < 0.35) or np.any(lam_um > 1.6):
        raise ValueError(f"wavelength_nm = {wavelength_nm}: must lie within 350–1600 nm")
    if material in _SELLMEIER:
        b, c = _SELLMEIER[material]
        lam2 = lam_um**2
        n2 = 1.0 + sum(bi * lam2 / (lam2 - ci) for bi, ci in zip(b, c, strict=True))
        n = np.sqrt(n2)
    elif material in _CAUCHY:
        a, b = _CAUCHY[material]
        n = a + b / lam_um**2
    else:
        raise ValueError(f"material = {material.value!r} is opaque: it has no refractive index")
    return float(n) if np.ndim(n) == 0 else n
