"""The :class:`Spectrum` type: a non-negative spectral quantity on a wavelength grid (nm).

Built on :class:`colour.SpectralDistribution` (linear interpolation: filter edges are steep,
and Sprague interpolation rings below zero there). A spectrum is defined on its sampled
range only: evaluating it outside raises :class:`ValueError` rather than inventing values, and
the product of two spectra lives on the overlap of their ranges.

CSV format (:func:`read_spectrum_csv`, :func:`write_spectrum_csv`)::

    # source: where the numbers come from (a datasheet, a model and its parameters, a paper)
    wavelength_nm,transmittance
    380,0.0
    381,1.2e-05
    ...

Two columns, the first ``wavelength_nm`` (strictly increasing, > 0), the second named after
the quantity (``relative_power``, ``transmittance``, ``quantum_efficiency`` ...), finite and
≥ 0. Lines starting with ``#`` are comments; the ``# source:`` line is the provenance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import colour
import numpy as np

from cm2optics.formats.atomic import write_text_atomic

__all__ = [
    "DEFAULT_WAVELENGTH_NM",
    "Normalisation",
    "Spectrum",
    "read_spectrum_csv",
    "write_spectrum_csv",
]

#: The grid of the shipped curves and of the filter chain: 380–780 nm in 1-nm steps.
DEFAULT_WAVELENGTH_NM = colour.SpectralShape(380, 780, 1).wavelengths

_SOURCE_PREFIX = "# source:"


class Normalisation(StrEnum):
    """How :meth:`Spectrum.normalise` scales a spectrum: to a peak of 1 or to an area of 1 (per nm)."""

    PEAK = "peak"
    AREA = "area"


def _check_quantity(quantity: str) -> None:
    ok = (
        isinstance(quantity, str)
        and quantity.strip() == quantity
        and quantity != ""
        and quantity != "wavelength_nm"
        and not any(c in quantity for c in ',\n\r"#')
    )
    if not ok:
        raise ValueError(
            f"quantity = {quantity!r}: must be a non-empty CSV column name other than 'wavelength_nm' "
            "(no commas, quotes, '#' or line breaks)"
        )


@dataclass(frozen=True, eq=False)
class Spectrum:
    """A spectral quantity sampled at ``wavelength_nm``.

    wavelength_nm: sample wavelengths, nm: 1-D, ≥ 2 values, finite, > 0, strictly increasing.
    values: the quantity at each wavelength (dimensionless or as ``quantity`` says): finite, ≥ 0.
    quantity: what the values are; the CSV column name (``transmittance``, ``relative_power``).
    source: provenance, one line (written as the CSV's ``# source:`` line).

    Arrays are copied and made read-only; operations return new spectra.
    """

    wavelength_nm: np.ndarray
    values: np.ndarray
    quantity: str = "value"
    source: str = ""

    def __post_init__(self) -> None:
        wavelength = np.array(self.wavelength_nm, dtype=float)
        values = np.array(self.values, dtype=float)
        if wavelength.ndim != 1 or wavelength.size < 2:
            raise ValueError(f"wavelength_nm has shape {wavelength.shape}: must be 1-D with ≥ 2 samples")
        if values.shape != wavelength.shape:
            raise ValueError(f"values has shape {values.shape}: must match wavelength_nm {wavelength.shape}")
        if not np.all(np.isfinite(wavelength)):
            raise ValueError("wavelength_nm contains NaN or infinity: must be finite")
        if np.any(wavelength <= 0):
            raise ValueError(f"wavelength_nm = {wavelength.min():g}: must be > 0 nm")
        steps = np.diff(wavelength)
        if np.any(steps <= 0):
            i = int(np.argmax(steps <= 0))
            raise ValueError(
                f"wavelength_nm must increase strictly: {wavelength[i + 1]:g} nm follows {wavelength[i]:g} nm"
            )
        if not np.all(np.isfinite(values)):
            i = int(np.argmax(~np.isfinite(values)))
            raise ValueError(f"values[{i}] = {values[i]} at {wavelength[i]:g} nm: must be finite (no NaN)")
        if np.any(values < 0):
            i = int(np.argmax(values < 0))
            raise ValueError(f"values[{i}] = {values[i]:g} at {wavelength[i]:g} nm: a spectrum must be ≥ 0")
        _check_quantity(self.quantity)
        if "\n" in self.source or "\r" in self.source:
            raise ValueError("source must be a single line")
        wavelength.flags.writeable = False
        values.flags.writeable = False
        object.__setattr__(self, "wavelength_nm", wavelength)
        object.__setattr__(self, "values", values)
        sd = colour.SpectralDistribution(
            values,
            wavelength,
            name=self.quantity,
            interpolator=colour.LinearInterpolator,
            extrapolator=colour.Extrapolator,
            extrapolator_kwargs={"method": "Constant", "left": np.nan, "right": np.nan},
        )
        object.__setattr__(self, "_sd", sd)

    # -- construction from colour ---------------------------------------------------------
    @classmethod
    def from_sd(cls, sd: colour.SpectralDistribution, quantity: str = "value", source: str = "") -> Spectrum:
        """A spectrum from a colour-science spectral distribution (wavelengths in nm)."""
        return cls(sd.wavelengths, sd.values, quantity=quantity, source=source)

    @property
    def sd(self) -> colour.SpectralDistribution:
        """A copy of the underlying :class:`colour.SpectralDistribution`, for colour-science's API."""
        return self._sd.copy()

    # -- evaluation ---------------------------------------------------------------------------
    @property
    def domain_nm(self) -> tuple[float, float]:
        """First and last sampled wavelength, nm."""
        return float(self.wavelength_nm[0]), float(self.wavelength_nm[-1])

    @property
    def peak_wavelength_nm(self) -> float:
        """Wavelength of the largest sample, nm (the first one if several are equal)."""
        return float(self.wavelength_nm[int(np.argmax(self.values))])

    def __len__(self) -> int:
        return self.wavelength_nm.size

    def __call__(self, wavelength_nm: float | np.ndarray) -> float | np.ndarray:
        """Values at ``wavelength_nm`` (nm, any shape), linearly interpolated; NaN in gives NaN out.

        Raises ValueError for a finite wavelength outside :attr:`domain_nm`.
        """
        wavelength = np.asarray(wavelength_nm, dtype=float)
        low, high = self.domain_nm
        finite = wavelength[np.isfinite(wavelength)]
        if finite.size and (finite.min() < low - 1e-9 or finite.max() > high + 1e-9):
            raise ValueError(
                f"wavelength_nm spans {finite.min():g}–{finite.max():g} nm: outside this {self.quantity} "
                f"spectrum's range {low:g}–{high:g} nm"
            )
        values = np.full(wavelength.shape, np.nan)
        finite_mask = np.isfinite(wavelength)
        values[finite_mask] = np.asarray(self._sd[np.clip(wavelength[finite_mask], low, high)], dtype=float)
        return float(values) if values.ndim == 0 else values

    def resample(self, wavelength_nm: np.ndarray | colour.SpectralShape) -> Spectrum:
        """The spectrum on a new grid (nm array or :class:`colour.SpectralShape`) inside its range."""
        if isinstance(wavelength_nm, colour.SpectralShape):
            wavelength_nm = wavelength_nm.wavelengths
        grid = np.asarray(wavelength_nm, dtype=float)
        return Spectrum(grid, self(grid), quantity=self.quantity, source=self.source)

    # -- arithmetic -----------------------------------------------------------------------------
    def __mul__(self, other: Spectrum | float) -> Spectrum:
        """Product with a number, or with a spectrum on the union of both grids within their overlap."""
        if isinstance(other, Spectrum):
            low = max(self.domain_nm[0], other.domain_nm[0])
            high = min(self.domain_nm[1], other.domain_nm[1])
            if high <= low:
                raise ValueError(
                    f"spectra do not overlap: {self.domain_nm[0]:g}–{self.domain_nm[1]:g} nm and "
                    f"{other.domain_nm[0]:g}–{other.domain_nm[1]:g} nm"
                )
            grid = np.union1d(self.wavelength_nm, other.wavelength_nm)
            grid = grid[(grid >= low) & (grid <= high)]
            return Spectrum(
                grid,
                self(grid) * other(grid),
                quantity=f"{self.quantity}*{other.quantity}",
                source=f"product of [{self.source}] and [{other.source}]",
            )
        factor = float(other)
        if not (math.isfinite(factor) and factor >= 0):
            raise ValueError(f"factor = {other!r}: must be a finite number ≥ 0")
        return Spectrum(self.wavelength_nm, self.values * factor, quantity=self.quantity, source=self.source)

    __rmul__ = __mul__

    def integrate(self) -> float:
        """∫ values dλ over the sampled range (trapezoidal rule), in units of the values × nm."""
        return float(np.trapezoid(self.values, self.wavelength_nm))

    def normalise(self, to: Normalisation | str = Normalisation.PEAK) -> Spectrum:
        """Scaled copy: peak value 1 (``peak``) or integral 1 per nm (``area``)."""
        to = Normalisation(to)
        scale = float(self.values.max()) if to is Normalisation.PEAK else self.integrate()
        if scale <= 0:
            raise ValueError(f"cannot normalise a {self.quantity} spectrum that is zero everywhere")
        return Spectrum(self.wavelength_nm, self.values / scale, quantity=self.quantity, source=self.source)

    # -- pictures -------------------------------------------------------------------------------
    def plot(self, ax: Any = None, **kwargs: Any) -> Any:
        """Draw the spectrum on matplotlib axes (new axes when ``ax`` is None); return the axes.

        Keyword arguments go to ``ax.plot`` (``label`` defaults to the quantity).
        """
        if ax is None:
            import matplotlib.pyplot as plt

            _, ax = plt.subplots()
        kwargs.setdefault("label", self.quantity)
        ax.plot(self.wavelength_nm, self.values, **kwargs)
        ax.set_xlabel("wavelength (nm)")
        return ax


# ----------------------------------------------------------------------------- CSV


def write_spectrum_csv(spectrum: Spectrum, path: str | Path) -> Path:
    """Write ``spectrum`` as CSV with its ``# source:`` line (atomically); return the path."""
    lines = [f"{_SOURCE_PREFIX} {spectrum.source or 'unspecified'}", f"wavelength_nm,{spectrum.quantity}"]
    lines += [f"{w:.6g},{v:.6g}" for w, v in zip(spectrum.wavelength_nm, spectrum.values, strict=True)]
    return write_text_atomic(Path(path), "\n".join(lines) + "\n")


def read_spectrum_csv(path: str | Path) -> Spectrum:
    """Read a spectrum CSV (see the module docstring); a malformed file raises one clear ValueError.

    A file without a ``# source:`` line gets ``source = "unspecified (<file name>)"``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such spectrum file")
    source = f"unspecified ({path.name})"
    header: list[str] | None = None
    wavelength, values = [], []
    for number, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            if line.lower().startswith(_SOURCE_PREFIX) and header is None:
                source = line[len(_SOURCE_PREFIX) :].strip() or source
            continue
        cells = [c.strip() for c in line.split(",")]
        if header is None:
            header = cells
            if len(cells) != 2 or cells[0] != "wavelength_nm":
                raise ValueError(
                    f"{path}: line {number}: expected the header 'wavelength_nm,<quantity>' (2 columns), got {cells}"
                )
            continue
        if len(cells) != 2:
            raise ValueError(f"{path}: line {number}: expected 2 values, got {len(cells)}: {line!r}")
        try:
            w, v = float(cells[0]), float(cells[1])
        except ValueError:
            raise ValueError(f"{path}: line {number}: not a number: {line!r}") from None
        if not (math.isfinite(w) and math.isfinite(v)):
            raise ValueError(f"{path}: line {number}: NaN or infinity ({line!r}): values must be finite")
        if w <= 0:
            raise ValueError(f"{path}: line {number}: wavelength_nm = {w:g}: must be > 0")
        if v < 0:
            raise ValueError(f"{path}: line {number}: {header[1]} = {v:g} is negative: a spectrum must be ≥ 0")
        if wavelength and w <= wavelength[-1]:
            raise ValueError(
                f"{path}: line {number}: wavelength_nm = {w:g} after {wavelength[-1]:g}: "
                "wavelengths must increase strictly (sort the file)"
            )
        wavelength.append(w)
        values.append(v)
    if header is None or len(wavelength) < 2:
        raise ValueError(f"{path}: needs a 'wavelength_nm,<quantity>' header and at least 2 data rows")
    try:
        return Spectrum(np.array(wavelength), np.array(values), quantity=header[1], source=source)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
