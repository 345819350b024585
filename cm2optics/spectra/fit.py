"""Fit the angle-shifted band-pass model to a vendor's transmittance curves.

Input: a CSV with columns ``wavelength_nm``, ``aoi_deg`` and either ``T`` (unpolarised) or
``Ts``, ``Tp`` (other columns, such as ``Rs``/``Rp``, are ignored), one block of rows per
angle of incidence, wavelengths increasing within a block, transmittance in 0–1.

The fitter is the first, small instance of this toolkit's loop (measure → residual → missing
effect → before/after): it fits the textbook model on some angles, predicts the 50 % band
edges at the angles it did not see, and then adds one physical effect at a time:

1. ``single-n_eff``: one effective index for both edges and both polarisations;
2. ``n_eff-per-edge``: each edge its own index — the passband may narrow with angle;
3. ``n_eff-per-edge-and-polarisation``: s and p their own indices too — the edges split and
   the unpolarised curve grows a shelf at each edge where only one polarisation passes.

For every model it reports the residual on the fitted curves and the edge errors at the
held-out angles; the model with the smallest held-out error is selected (with no held-out
angle, the one with the smallest Bayesian information criterion).

A table whose ``Ts`` and ``Tp`` columns are identical carries no polarisation information
(a real coating always splits s and p at oblique incidence; someone averaged them): it is
fitted as unpolarised data, and the s/p labels of model 3 follow the physical convention
that the s passband is the narrower one.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from cm2optics.spectra.interference import InterferenceBandpass, Polarisation

__all__ = [
    "AngleCurve",
    "FilterFitReport",
    "FilterModelKind",
    "FilterTable",
    "HeldOutEdges",
    "ModelFit",
    "band_edges_nm",
    "fit_bandpass",
    "fit_filter_models",
    "predict_edges_nm",
    "read_filter_table",
]


class FilterModelKind(StrEnum):
    """The models the fitter tries, from the textbook law to the refinements."""

    SINGLE = "single-n_eff"
    PER_EDGE = "n_eff-per-edge"
    PER_EDGE_POLARISATION = "n_eff-per-edge-and-polarisation"

    @property
    def effect(self) -> str:
        """The physical effect this model adds to the previous one."""
        return {
            FilterModelKind.SINGLE: "one effective index for the whole filter: λ(θ) = λ₀√(1 − (sin θ/n_eff)²)",
            FilterModelKind.PER_EDGE: "each edge its own effective index: the passband narrows (or widens) with angle",
            FilterModelKind.PER_EDGE_POLARISATION: "s and p their own indices per edge: the edges split by polarisation",
        }[self]


# ----------------------------------------------------------------------------- the table


@dataclass(frozen=True, eq=False)
class AngleCurve:
    """Transmittance at one angle of incidence.

    aoi_deg: angle of incidence in air, degrees.
    wavelength_nm: increasing wavelengths, nm.
    transmittance: unpolarised transmittance (T, or (Ts + Tp)/2), 0–1.
    transmittance_s, transmittance_p: per polarisation, or None for unpolarised data.
    """

    aoi_deg: float
    wavelength_nm: np.ndarray
    transmittance: np.ndarray
    transmittance_s: np.ndarray | None = None
    transmittance_p: np.ndarray | None = None


@dataclass(frozen=True)
class FilterTable:
    """A vendor's curves at several angles: ``curves`` sorted by angle; ``polarised`` when they
    carry distinct s and p data; ``note`` says how the file was read."""

    curves: tuple[AngleCurve, ...]
    polarised: bool
    note: str

    @property
    def aoi_deg(self) -> tuple[float, ...]:
        return tuple(c.aoi_deg for c in self.curves)

    def curve(self, aoi_deg: float) -> AngleCurve:
        for c in self.curves:
            if math.isclose(c.aoi_deg, aoi_deg, abs_tol=1e-9):
                return c
        raise ValueError(f"aoi_deg = {aoi_deg:g}: not in the table (angles: {_angles_text(self.aoi_deg)})")


def _angles_text(angles: Sequence[float]) -> str:
    return ", ".join(f"{a:g}" for a in angles)


def read_filter_table(path: str | Path) -> FilterTable:
    """Read and validate a vendor table (see the module docstring); one clear ValueError if malformed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such filter table")
    lines = [line for line in path.read_text(encoding="utf-8").splitlines() if not line.lstrip().startswith("#")]
    reader = csv.reader(lines)
    header = [h.strip() for h in next(reader, [])]
    if "wavelength_nm" not in header or "aoi_deg" not in header:
        raise ValueError(f"{path}: needs columns wavelength_nm, aoi_deg and T (or Ts, Tp); found {header}")
    if "Ts" in header and "Tp" in header:
        columns = ["Ts", "Tp"]
    elif "T" in header:
        columns = ["T"]
    else:
        raise ValueError(f"{path}: needs a transmittance column T, or both Ts and Tp; found {header}")
    index = {name: header.index(name) for name in ["wavelength_nm", "aoi_deg", *columns]}
    blocks: dict[float, list[list[float]]] = {}
    for number, row in enumerate(reader, start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) != len(header):
            raise ValueError(f"{path}: row {number}: {len(row)} values for {len(header)} columns")
        try:
            values = {name: float(row[i]) for name, i in index.items()}
        except ValueError:
            raise ValueError(f"{path}: row {number}: not a number in {row}") from None
        bad = [name for name, v in values.items() if not math.isfinite(v)]
        if bad:
            raise ValueError(f"{path}: row {number}: NaN or infinity in {', '.join(bad)}")
        wavelength, aoi = values["wavelength_nm"], values["aoi_deg"]
        if wavelength <= 0:
            raise ValueError(f"{path}: row {number}: wavelength_nm = {wavelength:g}: must be > 0")
        if not 0 <= aoi < 90:
            raise ValueError(f"{path}: row {number}: aoi_deg = {aoi:g}: must lie within 0–90°")
        for name in columns:
            if values[name] < 0:
                raise ValueError(f"{path}: row {number}: {name} = {values[name]:g} is negative: must lie within 0–1")
            if values[name] > 1.0 + 1e-6:
                hint = " (percent? divide by 100)" if values[name] <= 100 else ""
                raise ValueError(f"{path}: row {number}: {name} = {values[name]:g}: must lie within 0–1{hint}")
        block = blocks.setdefault(aoi, [])
        if block and wavelength <= block[-1][0]:
            raise ValueError(
                f"{path}: row {number}: wavelength_nm = {wavelength:g} after {block[-1][0]:g} at aoi_deg = {aoi:g}: "
                "wavelengths must increase within each angle (sort the file)"
            )
        block.append([wavelength] + [values[name] for name in columns])
    if not blocks:
        raise ValueError(f"{path}: no data rows")
    short = [a for a, rows in blocks.items() if len(rows) < 10]
    if short:
        raise ValueError(f"{path}: aoi_deg = {_angles_text(short)}: fewer than 10 wavelengths (too few to fit)")
    arrays = {a: np.array(rows) for a, rows in sorted(blocks.items())}
    polarised = len(columns) == 2 and any(not np.array_equal(r[:, 1], r[:, 2]) for r in arrays.values())
    if len(columns) == 1:
        note = "unpolarised T"
    elif polarised:
        note = "Ts and Tp fitted separately"
    else:
        note = "Ts and Tp are identical everywhere: no polarisation information; fitted as unpolarised (Ts+Tp)/2"
    curves = []
    for aoi, r in arrays.items():
        if len(columns) == 1:
            curves.append(AngleCurve(aoi, r[:, 0], r[:, 1]))
        else:
            mean = 0.5 * (r[:, 1] + r[:, 2])
            curves.append(
                AngleCurve(aoi, r[:, 0], mean, r[:, 1] if polarised else None, r[:, 2] if polarised else None)
            )
    return FilterTable(tuple(curves), polarised, note)


# ----------------------------------------------------------------------------- edges


def band_edges_nm(wavelength_nm: np.ndarray, transmittance: np.ndarray, level: float = 0.5) -> np.ndarray:
    """The band edges [short, long], nm: where ``transmittance`` first rises through ``level`` and
    last falls through it (linear interpolation between samples). A side with no crossing (the
    band never reaches ``level``, or runs off the sampled range) is NaN."""
    wavelength = np.asarray(wavelength_nm, dtype=float)
    t = np.asarray(transmittance, dtype=float)
    if wavelength.shape != t.shape or wavelength.ndim != 1:
        raise ValueError(f"wavelength_nm {wavelength.shape} and transmittance {t.shape} must be 1-D of equal length")
    above = t >= level
    edges = np.full(2, np.nan)
    up = np.flatnonzero(~above[:-1] & above[1:])
    down = np.flatnonzero(above[:-1] & ~above[1:])
    if up.size and not above[0]:
        i = up[0]
        edges[0] = wavelength[i] + (level - t[i]) / (t[i + 1] - t[i]) * (wavelength[i + 1] - wavelength[i])
    if down.size and not above[-1]:
        j = down[-1]
        edges[1] = wavelength[j] + (level - t[j]) / (t[j + 1] - t[j]) * (wavelength[j + 1] - wavelength[j])
    return edges


def predict_edges_nm(
    model: InterferenceBandpass, aoi_deg: float, wavelength_range_nm: tuple[float, float] = (300.0, 1100.0)
) -> np.ndarray:
    """50 % edges [short, long] of the model's unpolarised transmittance at ``aoi_deg`` (degrees), nm.

    Evaluated on a 0.01-nm grid over ``wavelength_range_nm``; NaN for a side with no crossing.
    """
    if not (math.isfinite(aoi_deg) and 0 <= aoi_deg < 90):
        raise ValueError(f"aoi_deg = {aoi_deg!r}: must lie within 0–90°")
    grid = np.arange(wavelength_range_nm[0], wavelength_range_nm[1] + 0.005, 0.01)
    return band_edges_nm(grid, model.transmittance(grid, math.radians(aoi_deg)))


# ----------------------------------------------------------------------------- fitting


@dataclass(frozen=True)
class HeldOutEdges:
    """Measured and predicted 50 % edges [short, long] at an angle the fit did not see, nm.

    scored: whether the measured curve is still a band-pass (both edges defined, no wider than
    1.5× the band at the lowest fitted angle); a curve whose blocking broke down (a 50 % "band"
    hundreds of nm wide) or whose band vanished is shown but not scored: no edge-shift law
    describes it.
    """

    aoi_deg: float
    measured_nm: tuple[float, float]
    predicted_nm: tuple[float, float]
    scored: bool

    @property
    def error_nm(self) -> tuple[float, float]:
        """Predicted minus measured, nm (NaN where either is undefined)."""
        return (self.predicted_nm[0] - self.measured_nm[0], self.predicted_nm[1] - self.measured_nm[1])


@dataclass(frozen=True)
class ModelFit:
    """One model fitted on ``fit_aoi_deg``: its filter, residual and held-out edge errors.

    rms_residual: RMS of (model − measured) transmittance over the fitted curves.
    bic: Bayesian information criterion of the fit (lower is better).
    blocking_od_is_lower_bound: the table rounds the out-of-band values to 0, so the
        filter's ``blocking_od`` is only the bound that resolution allows.
    """

    kind: FilterModelKind
    filter: InterferenceBandpass
    fit_aoi_deg: tuple[float, ...]
    rms_residual: float
    bic: float
    blocking_od_is_lower_bound: bool
    held_out: tuple[HeldOutEdges, ...] = ()

    @property
    def held_out_rms_nm(self) -> float:
        """RMS of the scored held-out edge errors, nm (NaN with none)."""
        errors = np.array([e for h in self.held_out if h.scored for e in h.error_nm], dtype=float)
        errors = errors[np.isfinite(errors)]
        return float(np.sqrt(np.mean(errors**2))) if errors.size else math.nan


def _unpack(kind: FilterModelKind, p: np.ndarray, blocking_od: float) -> InterferenceBandpass:
    short, long, width, peak = p[:4]
    n = p[4:]
    if kind is FilterModelKind.SINGLE:
        indices = (n[0], n[0], n[0], n[0])
    elif kind is FilterModelKind.PER_EDGE:
        indices = (n[0], n[0], n[1], n[1])
    else:
        indices = (n[0], n[1], n[2], n[3])
    return InterferenceBandpass(
        float(short),
        float(long),
        *map(float, indices),
        edge_width_nm=float(width),
        peak_transmittance=float(peak),
        blocking_od=blocking_od,
    )


def _starts(kind: FilterModelKind, base: np.ndarray, previous: InterferenceBandpass | None) -> list[np.ndarray]:
    """Deterministic starting points (a few, so that split indices find the right basin)."""
    if kind is FilterModelKind.SINGLE:
        return [np.r_[base, 1.9]]
    if kind is FilterModelKind.PER_EDGE:
        n = previous.n_eff_short_s if previous else 1.9
        return [np.r_[base, n, n]]
    ns = previous.n_eff_short_s if previous else 1.9
    nl = previous.n_eff_long_s if previous else 1.9
    starts = []
    for split in (0.1, 0.2, 0.3):
        starts.append(np.r_[base, ns + split, ns - split, nl - split, nl + split])
        starts.append(np.r_[base, ns - split, ns + split, nl + split, nl - split])
    return starts


def _residuals(model: InterferenceBandpass, curves: Sequence[AngleCurve], polarised: bool) -> np.ndarray:
    parts = []
    for c in curves:
        theta = math.radians(c.aoi_deg)
        if polarised:
            parts.append(model.transmittance(c.wavelength_nm, theta, Polarisation.S) - c.transmittance_s)
            parts.append(model.transmittance(c.wavelength_nm, theta, Polarisation.P) - c.transmittance_p)
        else:
            parts.append(model.transmittance(c.wavelength_nm, theta) - c.transmittance)
    return np.concatenate(parts)


def _blocking(model: InterferenceBandpass, curves: Sequence[AngleCurve]) -> tuple[float, bool]:
    """Out-of-band floor from the data: mean measured T where the model's band is < 1e-4 of its peak."""
    outside, smallest = [], math.inf
    for c in curves:
        band = model.transmittance(c.wavelength_nm, math.radians(c.aoi_deg)) / model.peak_transmittance
        outside.append(c.transmittance[band < 1e-4])
        positive = c.transmittance[c.transmittance > 0]
        if positive.size:
            smallest = min(smallest, float(positive.min()))
    values = np.concatenate(outside)
    mean = float(values.mean()) if values.size else 0.0
    if mean > 0:
        return min(10.0, -math.log10(mean)), False
    resolution = smallest / 2 if math.isfinite(smallest) else 1e-4
    return min(10.0, -math.log10(resolution)), True


def _swap_polarisations(model: InterferenceBandpass) -> InterferenceBandpass:
    return InterferenceBandpass(
        model.short_edge_nm,
        model.long_edge_nm,
        model.n_eff_short_p,
        model.n_eff_short_s,
        model.n_eff_long_p,
        model.n_eff_long_s,
        edge_width_nm=model.edge_width_nm,
        peak_transmittance=model.peak_transmittance,
        blocking_od=model.blocking_od,
    )


def fit_bandpass(
    table: FilterTable,
    kind: FilterModelKind | str,
    fit_aoi_deg: Sequence[float],
    previous: InterferenceBandpass | None = None,
) -> ModelFit:
    """Least-squares fit of one model to the curves at ``fit_aoi_deg`` (degrees).

    ``previous`` (the fit of the simpler model) seeds the starting point. Held-out errors are
    filled in by :func:`fit_filter_models`.
    """
    kind = FilterModelKind(kind)
    curves = [table.curve(a) for a in fit_aoi_deg]
    if len({c.aoi_deg for c in curves}) < 2:
        raise ValueError(
            f"fit_aoi_deg = {_angles_text(fit_aoi_deg)}: needs at least two different angles "
            "(one angle cannot tell a band's position from its shift)"
        )
    lowest = min(curves, key=lambda c: c.aoi_deg)
    edges = band_edges_nm(lowest.wavelength_nm, lowest.transmittance)
    if not np.all(np.isfinite(edges)):
        raise ValueError(f"no band-pass at aoi_deg = {lowest.aoi_deg:g}: the curve does not cross 50 % on both sides")
    base = np.array([edges[0], edges[1], 2.0, min(0.999, float(lowest.transmittance.max()))])
    w_min = min(float(c.wavelength_nm.min()) for c in curves)
    w_max = max(float(c.wavelength_nm.max()) for c in curves)
    n_count = {FilterModelKind.SINGLE: 1, FilterModelKind.PER_EDGE: 2, FilterModelKind.PER_EDGE_POLARISATION: 4}[kind]
    lower = np.r_[w_min, w_min, 0.05, 0.05, [1.0] * n_count]
    upper = np.r_[w_max, w_max, 50.0, 1.0, [4.0] * n_count]
    blocking = 6.0  # the floor barely moves the edges; it is estimated from the data after the fit

    def residual(p: np.ndarray) -> np.ndarray:
        if p[1] <= p[0]:
            return np.full(sum(c.wavelength_nm.size for c in curves) * (2 if table.polarised else 1), 1.0)
        return _residuals(_unpack(kind, p, blocking), curves, table.polarised)

    best = None
    for start in _starts(kind, base, previous):
        result = least_squares(residual, np.clip(start, lower, upper), bounds=(lower, upper), x_scale="jac")
        if best is None or result.cost < best.cost:
            best = result
    model = _unpack(kind, best.x, blocking)
    od, bound = _blocking(model, curves)
    model = _unpack(kind, best.x, od)
    if kind is FilterModelKind.PER_EDGE_POLARISATION and not table.polarised:
        widest = math.radians(max(c.aoi_deg for c in curves))
        s_short, s_long = model.edges_nm(widest, Polarisation.S)
        p_short, p_long = model.edges_nm(widest, Polarisation.P)
        if s_long - s_short > p_long - p_short:
            model = _swap_polarisations(model)
    r = _residuals(model, curves, table.polarised)
    n_points = r.size
    rss = float(np.sum(r**2))
    bic = n_points * math.log(max(rss, 1e-300) / n_points) + best.x.size * math.log(n_points)
    return ModelFit(kind, model, tuple(c.aoi_deg for c in curves), math.sqrt(rss / n_points), bic, bound)


@dataclass(frozen=True)
class FilterFitReport:
    """Every model tried, in order, and the one selected.

    note: how the table was read (polarised or not). selection: why ``selected`` was chosen.
    """

    note: str
    fit_aoi_deg: tuple[float, ...]
    held_out_aoi_deg: tuple[float, ...]
    fits: tuple[ModelFit, ...]
    selected: FilterModelKind
    selection: str

    @property
    def best(self) -> ModelFit:
        return next(f for f in self.fits if f.kind is self.selected)

    def to_dict(self, predict_aoi_deg: float | None = None) -> dict[str, Any]:
        """JSON-able summary; with ``predict_aoi_deg`` (degrees) adds ``edges_nm`` of the selected model."""

        def number(x: float, digits: int = 3) -> float | None:
            return round(float(x), digits) if math.isfinite(x) else None

        def model_dict(fit: ModelFit) -> dict[str, Any]:
            f = fit.filter
            return {
                "model": fit.kind.value,
                "adds": fit.kind.effect,
                "parameters": _parameters(f, fit.blocking_od_is_lower_bound),
                "rms_residual": number(fit.rms_residual, 5),
                "bic": number(fit.bic, 1),
                "held_out": [
                    {
                        "aoi_deg": h.aoi_deg,
                        "measured_edges_nm": [number(v, 2) for v in h.measured_nm],
                        "predicted_edges_nm": [number(v, 2) for v in h.predicted_nm],
                        "error_nm": [number(v, 2) for v in h.error_nm],
                        "scored": h.scored,
                    }
                    for h in fit.held_out
                ],
                "held_out_rms_nm": number(fit.held_out_rms_nm, 2),
            }

        data: dict[str, Any] = {
            "table": self.note,
            "fit_aoi_deg": list(self.fit_aoi_deg),
            "held_out_aoi_deg": list(self.held_out_aoi_deg),
            "models": [model_dict(f) for f in self.fits],
            "selected_model": self.selected.value,
            "selection": self.selection,
            "parameters": _parameters(self.best.filter, self.best.blocking_od_is_lower_bound),
        }
        if predict_aoi_deg is not None:
            edges = predict_edges_nm(self.best.filter, predict_aoi_deg)
            data["predict_aoi_deg"] = predict_aoi_deg
            data["edges_nm"] = [number(v, 2) for v in edges]
        return data


def _parameters(f: InterferenceBandpass, od_bound: bool) -> dict[str, Any]:
    return {
        "short_edge_nm": round(f.short_edge_nm, 3),
        "long_edge_nm": round(f.long_edge_nm, 3),
        "n_eff_short_s": round(f.n_eff_short_s, 4),
        "n_eff_short_p": round(f.n_eff_short_p, 4),
        "n_eff_long_s": round(f.n_eff_long_s, 4),
        "n_eff_long_p": round(f.n_eff_long_p, 4),
        "edge_width_nm": round(f.edge_width_nm, 3),
        "peak_transmittance": round(f.peak_transmittance, 4),
        "blocking_od": round(f.blocking_od, 2),
        "blocking_od_is_lower_bound": od_bound,
    }


def fit_filter_models(table: FilterTable, fit_aoi_deg: Sequence[float] | None = None) -> FilterFitReport:
    """Fit every model on ``fit_aoi_deg`` (default: 0° and 20° when present, else every angle)
    and score each on the other angles' 50 % edges."""
    angles = table.aoi_deg
    if fit_aoi_deg is None:
        has = [any(math.isclose(a, target, abs_tol=1e-9) for a in angles) for target in (0.0, 20.0)]
        fit_aoi_deg = (0.0, 20.0) if all(has) else angles
    fit_aoi_deg = tuple(table.curve(a).aoi_deg for a in fit_aoi_deg)
    held = tuple(a for a in angles if a not in fit_aoi_deg)
    reference = table.curve(min(fit_aoi_deg))
    reference_width = float(np.diff(band_edges_nm(reference.wavelength_nm, reference.transmittance))[0])
    fits: list[ModelFit] = []
    previous = None
    for kind in FilterModelKind:
        fit = fit_bandpass(table, kind, fit_aoi_deg, previous)
        previous = fit.filter
        held_out = []
        for a in held:
            curve = table.curve(a)
            measured = band_edges_nm(curve.wavelength_nm, curve.transmittance)
            predicted = predict_edges_nm(fit.filter, a, (float(curve.wavelength_nm[0]), float(curve.wavelength_nm[-1])))
            width = measured[1] - measured[0]
            scored = bool(np.all(np.isfinite(measured)) and width <= 1.5 * reference_width)
            held_out.append(HeldOutEdges(a, tuple(measured), tuple(predicted), scored))
        fits.append(ModelFit(**{**fit.__dict__, "held_out": tuple(held_out)}))
    scored = [f for f in fits if math.isfinite(f.held_out_rms_nm)]
    if scored:
        best = min(scored, key=lambda f: f.held_out_rms_nm)
        angles = sorted({h.aoi_deg for h in best.held_out if h.scored})
        selection = f"smallest held-out edge error ({best.held_out_rms_nm:.2f} nm RMS at {_angles_text(angles)}°)"
    else:
        best = min(fits, key=lambda f: f.bic)
        selection = "no held-out angle with defined edges: smallest Bayesian information criterion on the fit"
    return FilterFitReport(table.note, fit_aoi_deg, held, tuple(fits), best.kind, selection)
