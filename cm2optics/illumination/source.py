"""The LED as a ray source: a square emitter with an angular profile and a spectrum.

Pure NumPy, so that the Mitsuba tracer and the NumPy reference tracer start from the very
same rays. LED frame (:mod:`cm2optics.optics.layout`): origin at the centre of the emitting surface,
``+z`` the unit's axis; the emitter is the square ``|x|, |y| ≤ emitter_mm / 2`` at ``z = 0``.

Every point of the emitter radiates with the same relative radiant intensity ``I(θ)``
(W/sr, relative; θ from ``+z``, independent of azimuth), so a ray's direction has the density
``p(θ, φ) ∝ I(θ) sin θ`` and its position is uniform on the square: positions, directions and
wavelengths are independent. A Lambertian emitter has ``I(θ) = cos θ``.

Each ray carries the same power ``radiant_flux_mw / rays``: the figures of merit are plain
Monte Carlo means, and their standard errors follow from the binomial law.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cm2optics.design import SystemDesign

__all__ = [
    "AngularProfile",
    "EmittedRays",
    "LEDSource",
    "SourceSpectrum",
    "lambertian_profile",
    "led_source",
    "read_angular_profile",
    "read_source_spectrum",
    "sample_led_rays",
]

_GRID = 4097  # points of the tabulated angular density
_TABLE = 1 << 16  # nodes of the tabulated inverse CDFs


@dataclass(frozen=True, eq=False)
class AngularProfile:
    """Relative radiant intensity of the LED versus the emission angle from its axis.

    angle_rad: strictly increasing angles from 0 to ≤ π/2, rad.
    relative_intensity: I(θ) at those angles (any scale, ≥ 0, not all 0); linear in between.
    source: provenance, one line.
    """

    angle_rad: np.ndarray
    relative_intensity: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        angle = np.asarray(self.angle_rad, dtype=float)
        value = np.asarray(self.relative_intensity, dtype=float)
        if angle.ndim != 1 or angle.shape != value.shape or angle.size < 2:
            raise ValueError(
                f"angular profile: angle_rad and relative_intensity must be 1-D of the same length ≥ 2, got {angle.shape} and {value.shape}"
            )
        if not (
            np.all(np.isfinite(angle))
            and np.all(np.diff(angle) > 0)
            and angle[0] >= 0
            and angle[-1] <= math.pi / 2 + 1e-9
        ):
            raise ValueError("angular profile: angle_deg must increase strictly within 0–90°")
        if not (np.all(np.isfinite(value)) and np.all(value >= 0) and value.max() > 0):
            raise ValueError("angular profile: relative_intensity must be finite, ≥ 0 and not all 0")
        object.__setattr__(self, "angle_rad", angle)
        object.__setattr__(self, "relative_intensity", value)

    def intensity(self, angle_rad: np.ndarray | float) -> np.ndarray:
        """I(θ) at ``angle_rad`` (rad), linear between samples, 0 beyond the last one."""
        return np.interp(angle_rad, self.angle_rad, self.relative_intensity, right=0.0)

    def fraction_within(self, half_angle_rad: float) -> float:
        """Fraction of the emitted power inside the cone of half-angle ``half_angle_rad`` (rad)."""
        theta = np.linspace(0.0, math.pi / 2, _GRID)
        density = self.intensity(theta) * np.sin(theta)
        cdf = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * np.diff(theta))])
        return float(np.interp(half_angle_rad, theta, cdf / cdf[-1]))


def lambertian_profile() -> AngularProfile:
    """I(θ) = cos θ, the default when no measured profile is given."""
    theta = np.linspace(0.0, math.pi / 2, 91)
    return AngularProfile(theta, np.cos(theta), "Lambertian, I(θ) = cos θ")


def read_angular_profile(path: str | Path) -> AngularProfile:
    """Read a CSV with columns ``angle_deg,relative_intensity`` (degrees from the LED's axis)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"LED angular profile not found: {path}")
    with path.open(newline="") as handle:
        rows = [row for row in csv.reader(line for line in handle if not line.startswith("#")) if row]
    if not rows or [c.strip() for c in rows[0][:2]] != ["angle_deg", "relative_intensity"]:
        raise ValueError(f"{path}: the first line must be 'angle_deg,relative_intensity'")
    try:
        data = np.array([[float(c) for c in row[:2]] for row in rows[1:]])
    except ValueError as error:
        raise ValueError(f"{path}: not a number ({error})") from None
    if data.ndim != 2 or len(data) < 2:
        raise ValueError(f"{path}: needs at least two rows of angle_deg,relative_intensity")
    return AngularProfile(np.radians(data[:, 0]), data[:, 1], f"{path.name}")


@dataclass(frozen=True, eq=False)
class SourceSpectrum:
    """Relative spectral power of the LED, linear between samples.

    wavelength_nm: strictly increasing wavelengths, nm.
    relative_power: power per nm at those wavelengths (any scale, ≥ 0, not all 0).
    source: provenance, one line.
    """

    wavelength_nm: np.ndarray
    relative_power: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        wl = np.asarray(self.wavelength_nm, dtype=float)
        power = np.asarray(self.relative_power, dtype=float)
        if wl.ndim != 1 or wl.shape != power.shape or wl.size < 2 or not np.all(np.diff(wl) > 0):
            raise ValueError("LED spectrum: wavelength_nm must increase strictly and match relative_power")
        if not (np.all(np.isfinite(power)) and np.all(power >= 0) and power.max() > 0):
            raise ValueError("LED spectrum: relative_power must be finite, ≥ 0 and not all 0")
        object.__setattr__(self, "wavelength_nm", wl)
        object.__setattr__(self, "relative_power", power)

    def support_nm(self, tail: float = 0.0) -> tuple[float, float]:
        """Wavelength range outside which the power is ≤ ``tail`` × peak, nm."""
        above = np.flatnonzero(self.relative_power > tail * self.relative_power.max())
        lo, hi = max(above[0] - 1, 0), min(above[-1] + 1, len(self.wavelength_nm) - 1)
        return float(self.wavelength_nm[lo]), float(self.wavelength_nm[hi])

    def weighted_mean(self, values: np.ndarray) -> float:
        """Power-weighted mean of ``values`` sampled on ``wavelength_nm``."""
        return float(
            np.trapezoid(self.relative_power * values, self.wavelength_nm)
            / np.trapezoid(self.relative_power, self.wavelength_nm)
        )


@dataclass(frozen=True, eq=False)
class LEDSource:
    """One LED: emitter size, angular profile, spectrum and radiant flux.

    emitter_mm: side of the square emitting surface, mm.
    profile: relative radiant intensity versus angle.
    spectrum: relative spectral power.
    radiant_flux_mw: total radiant flux into the forward hemisphere, mW.
    """

    emitter_mm: float
    profile: AngularProfile
    spectrum: SourceSpectrum
    radiant_flux_mw: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.emitter_mm) and self.emitter_mm > 0):
            raise ValueError(f"emitter_mm = {self.emitter_mm!r}: must be a finite number > 0")
        if not (math.isfinite(self.radiant_flux_mw) and self.radiant_flux_mw > 0):
            raise ValueError(f"radiant_flux_mw = {self.radiant_flux_mw!r}: must be a finite number > 0")


def read_source_spectrum(path: str | Path) -> SourceSpectrum:
    """An LED spectrum from a spectrum CSV (``wavelength_nm,relative_power``; the format of
    :mod:`cm2optics.spectra.spectrum`)."""
    from cm2optics.spectra.spectrum import read_spectrum_csv

    spectrum = read_spectrum_csv(path)
    return SourceSpectrum(np.asarray(spectrum.wavelength_nm), np.asarray(spectrum.values), spectrum.source)


def _design_spectrum(design: SystemDesign) -> SourceSpectrum:
    """The spectra library's LED model at the design's peak wavelength (Ohno model, 25-nm FWHM)."""
    from cm2optics.spectra.library import led_spectrum

    spectrum = led_spectrum(design.led.peak_nm)
    return SourceSpectrum(np.asarray(spectrum.wavelength_nm), np.asarray(spectrum.values), spectrum.source)


def led_source(
    design: SystemDesign,
    profile: AngularProfile | None = None,
    spectrum: SourceSpectrum | None = None,
    radiant_flux_mw: float | None = None,
) -> LEDSource:
    """The design's LED; ``profile`` defaults to Lambertian, ``spectrum`` to the spectra
    library's LED model at ``design.led.peak_nm``, ``radiant_flux_mw`` (mW) to the design's."""
    return LEDSource(
        emitter_mm=design.led.emitter_mm,
        profile=profile if profile is not None else lambertian_profile(),
        spectrum=spectrum if spectrum is not None else _design_spectrum(design),
        radiant_flux_mw=design.led.radiant_flux_mw if radiant_flux_mw is None else float(radiant_flux_mw),
    )


def _inverse_cdf(x: np.ndarray, density: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Samples of a piecewise-linear density on the grid ``x`` for uniform variates ``u``:
    the CDF is integrated exactly (trapezoids) and inverted by solving its quadratic per cell."""
    cell = (density[1:] + density[:-1]) / 2 * np.diff(x)
    cdf = np.concatenate([[0.0], np.cumsum(cell)])
    target = u * cdf[-1]
    i = np.clip(np.searchsorted(cdf, target, side="right") - 1, 0, len(cell) - 1)
    width = x[i + 1] - x[i]
    f0, f1 = density[i], density[i + 1]
    slope = (f1 - f0) / width
    need = target - cdf[i]
    # Solve f0 t + slope t² / 2 = need for t in [0, width].
    with np.errstate(divide="ignore", invalid="ignore"):
        quadratic = (-f0 + np.sqrt(np.maximum(f0 * f0 + 2.0 * slope * need, 0.0))) / slope
        linear = need / f0
    t = np.where(np.abs(slope) * width > 1e-12 * np.maximum(f0, 1e-300), quadratic, linear)
    t = np.where(np.isfinite(t), t, 0.0)
    return x[i] + np.clip(t, 0.0, width)


class _InverseTable:
    """The inverse CDF of a piecewise-linear density tabulated on :data:`_TABLE` equal steps of
    u and interpolated linearly: O(1) per sample (the exact inverse at the table's nodes;
    between them the error is below 10⁻⁶ of the range for these smooth densities)."""

    def __init__(self, x: np.ndarray, density: np.ndarray):
        self.values = _inverse_cdf(x, density, np.linspace(0.0, 1.0, _TABLE))

    def __call__(self, u: np.ndarray) -> np.ndarray:
        f = u * (_TABLE - 1)
        i = np.minimum(f.astype(np.int64), _TABLE - 2)
        t = f - i
        return self.values[i] * (1.0 - t) + self.values[i + 1] * t


@dataclass(frozen=True, eq=False)
class EmittedRays:
    """Rays leaving one LED, in its LED frame.

    origin_mm: (N, 3) points on the emitter, mm.
    direction: (N, 3) unit vectors, z > 0.
    wavelength_nm: (N,) wavelengths, nm.
    """

    origin_mm: np.ndarray
    direction: np.ndarray
    wavelength_nm: np.ndarray


def sample_led_rays(source: LEDSource, count: int, rng: np.random.Generator) -> EmittedRays:
    """``count`` independent rays of ``source`` (positions, directions, wavelengths)."""
    if count < 1:
        raise ValueError(f"rays = {count}: must be ≥ 1")
    u = rng.random((count, 5))
    half = source.emitter_mm / 2
    origin = np.column_stack([(2 * u[:, 0] - 1) * half, (2 * u[:, 1] - 1) * half, np.zeros(count)])
    theta_table, wl_table = _tables(source)
    theta = theta_table(u[:, 2])
    phi = 2 * math.pi * u[:, 3]
    sin_t = np.sin(theta)
    direction = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), np.cos(theta)])
    return EmittedRays(origin, direction, wl_table(u[:, 4]))


def _tables(source: LEDSource) -> tuple[_InverseTable, _InverseTable]:
    """Inverse CDFs of the emission angle and of the wavelength (cached on the source)."""
    cached = getattr(source, "_cm2_tables", None)
    if cached is None:
        theta_grid = np.linspace(0.0, min(source.profile.angle_rad[-1], math.pi / 2), _GRID)
        cached = (
            _InverseTable(theta_grid, source.profile.intensity(theta_grid) * np.sin(theta_grid)),
            _InverseTable(source.spectrum.wavelength_nm, source.spectrum.relative_power),
        )
        object.__setattr__(source, "_cm2_tables", cached)
    return cached
