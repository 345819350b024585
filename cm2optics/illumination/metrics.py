"""Figures of merit of an illumination trace, each with its Monte Carlo standard error.

Every LED ray carries the same power ``w = Φ / N`` (Φ the LED's radiant flux, N the rays
per LED), so a power ratio is the fraction ``p̂`` of rays with some fate and its standard
error is the binomial ``√(p̂ (1 − p̂) / N)``. Figures that are not plain fractions
(uniformity) get a delete-a-group jackknife error over :data:`JACKKNIFE_GROUPS`
interleaved groups of rays; beam angles (quantiles) the asymptotic error of a sample quantile.

Definitions (P_emit: power emitted by the LEDs considered):

throughput
    power that leaves the excitation filter's back face into the air (with no filter: that
    crosses the unit's exit plane outwards), each ray counted once, / P_emit.
delivered_fraction
    power landing on the sample plane (z = object_plane_z_mm) inside the field circle
    (diameter volume.field_mm, centred on the optical axis) / P_emit.
power_mw
    delivered_fraction × led_array.count × LED radiant flux (each LED scaled by the design's
    ``illumination_as_built.led_flux``): mW into the circle from the array.
uniformity_min_max, uniformity_cv
    over the square bins (side ``bin_mm``) of the array's irradiance map whose centres lie in
    the circle: min / max, and standard deviation / mean. Monte Carlo noise adds to the
    spread: ``uniformity_cv_noise`` = 1 / √(mean rays per bin) is the CV a perfectly uniform
    field would show with these rays.
fraction_within_30deg
    power that passed (as for throughput) travelling within 30° of its unit's axis / P_emit.
beam_half_angle_50_deg, beam_half_angle_90_deg
    half-angles about the unit's axis of the cones holding 50 % and 90 % of the power that
    passed, degrees.
ledger
    where the emitted power went: delivered + absorbed (housing, LED board, filter edges,
    imaging tower, trapped: still bouncing after the last traced surface, in reality absorbed
    by the material) + escaped (landed on the sample plane outside the circle, or left the
    scene) = 1, as fractions of P_emit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.illumination.geometry import Absorber, IlluminationScene
from cm2optics.illumination.tracer import RayRecord, Status

__all__ = [
    "DEFINITIONS",
    "JACKKNIFE_GROUPS",
    "Estimate",
    "IlluminationFigures",
    "figures_of_merit",
    "write_maps_png",
]

JACKKNIFE_GROUPS = 16

#: One-line definitions of the JSON figures (for ``--help``, the docs and the reports).
DEFINITIONS = {
    "throughput": "power leaving the excitation filter's back face (no filter: the unit's exit plane) / power emitted by the LEDs",
    "delivered_fraction": "power landing inside the field circle (volume.field_mm) on the sample plane / power emitted",
    "power_mw": "delivered_fraction × led_array.count × LED radiant flux (each LED scaled by "
    "illumination_as_built.led_flux): mW into the circle from the array",
    "uniformity_min_max": "min / max of the array's irradiance over the bin_mm bins centred inside the circle",
    "uniformity_cv": "standard deviation / mean of the same bins (includes Monte Carlo noise, see uniformity_cv_noise)",
    "uniformity_cv_noise": "CV that Monte Carlo noise alone gives a uniform field with these rays: 1/√(rays per bin)",
    "fraction_within_30deg": "power passing (as throughput) within 30° of its unit's axis / power emitted",
    "beam_half_angle_50_deg": "half-angle about the unit's axis holding 50 % of the passing power, degrees",
    "beam_half_angle_90_deg": "half-angle about the unit's axis holding 90 % of the passing power, degrees",
    "ledger": "delivered + absorbed (housing, LED board, filter edges, imaging tower, trapped) + escaped (outside the circle, left the scene) = emitted",
}


@dataclass(frozen=True)
class Estimate:
    """A Monte Carlo estimate: value and standard error (same unit)."""

    value: float
    stderr: float

    def __format__(self, spec: str) -> str:
        spec = spec or ".4g"
        return f"{self.value:{spec}} ± {self.stderr:{spec}}"


def _fraction(mask: np.ndarray) -> Estimate:
    n = mask.size
    p = float(mask.mean()) if n else math.nan
    return Estimate(p, math.sqrt(max(p * (1 - p), 0.0) / n) if n else math.nan)


def _jackknife_bins(total: np.ndarray, per_group: np.ndarray, statistic) -> Estimate:
    """statistic(bin counts of all rays) and its delete-a-group jackknife standard error,
    from the bin counts of each group of rays (``per_group``: groups × bins)."""
    full = float(statistic(total))
    leave = np.array([statistic(total - counts) for counts in per_group], dtype=float)
    leave = leave[np.isfinite(leave)]
    if leave.size < 2 or not math.isfinite(full):
        return Estimate(full, math.nan)
    return Estimate(full, float(math.sqrt((leave.size - 1) / leave.size * np.sum((leave - leave.mean()) ** 2))))


def _quantile(values: np.ndarray, q: float, h: float = 0.02) -> Estimate:
    """The q-quantile of a sample and its asymptotic standard error √(q(1−q)/n) / f(Q(q)), the
    density f estimated from the quantiles at q ± h (Siddiqui–Bloch–Gastwirth)."""
    n = values.size
    if n < 10:
        return Estimate(math.nan, math.nan)
    lo, value, hi = np.quantile(values, [max(q - h, 0.0), q, min(q + h, 1.0)])
    density = (min(q + h, 1.0) - max(q - h, 0.0)) / (hi - lo) if hi > lo else math.inf
    return Estimate(float(value), math.sqrt(q * (1 - q) / n) / density)


@dataclass(frozen=True, eq=False)
class IlluminationFigures:
    """The figures of merit of one traced configuration (see the module docstring).

    label: configuration name. rays: rays traced (all LEDs). rays_per_led: rays per LED.
    units: LEDs. led_flux_mw: radiant flux of each LED, mW. field_radius_mm: circle radius, mm.
    bin_mm: uniformity bins, mm. map_bin_mm, map_half_mm: irradiance map pixels and half-width, mm.
    unit_map, array_map: irradiance on the sample plane (y, x), mW/mm², for LED 0 alone and
    for the whole array.
    """

    label: str
    rays: int
    rays_per_led: int
    units: int
    led_flux_mw: float
    field_radius_mm: float
    throughput: Estimate
    delivered_fraction: Estimate
    power_mw: Estimate
    uniformity_min_max: Estimate
    uniformity_cv: Estimate
    uniformity_cv_noise: float
    fraction_within_30deg: Estimate
    beam_half_angle_50_deg: Estimate
    beam_half_angle_90_deg: Estimate
    ledger: dict[str, Estimate]
    per_led: list[dict[str, float]]
    bin_mm: float
    map_bin_mm: float
    map_half_mm: float
    unit_map: np.ndarray = field(repr=False)
    array_map: np.ndarray = field(repr=False)
    seconds: float = 0.0
    variant: str = ""

    def summary(self) -> dict[str, Any]:
        """The JSON figures: ``name`` and ``name_stderr`` for every estimate."""
        out: dict[str, Any] = {"rays": self.rays, "rays_per_led": self.rays_per_led}
        for name in (
            "throughput",
            "delivered_fraction",
            "power_mw",
            "uniformity_cv",
            "uniformity_min_max",
            "fraction_within_30deg",
            "beam_half_angle_50_deg",
            "beam_half_angle_90_deg",
        ):
            estimate: Estimate = getattr(self, name)
            out[name] = _round(estimate.value)
            out[f"{name}_stderr"] = _round(estimate.stderr)
        out["uniformity_cv_noise"] = _round(self.uniformity_cv_noise)
        out["ledger"] = {k: _round(v.value) for k, v in self.ledger.items()}
        out["ledger_stderr"] = {k: _round(v.stderr) for k, v in self.ledger.items()}
        return out

    def to_json(self) -> dict[str, Any]:
        """Everything machine-readable: the summary, the per-LED figures and the setup."""
        out = self.summary()
        out.update(
            {
                "design": self.label,
                "led_radiant_flux_mw": self.led_flux_mw,
                "leds": self.units,
                "field_diameter_mm": 2 * self.field_radius_mm,
                "bin_mm": self.bin_mm,
                "per_led": self.per_led,
                "seconds": round(self.seconds, 3),
                "backend": self.variant,
            }
        )
        return out


def _round(value: float) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return float(f"{value:.6g}")


def _histogram(xy: np.ndarray, weight: float, half: float, bin_mm: float) -> np.ndarray:
    """Power per area (weight per ray / bin area) on a (y, x) grid over ±half, mm."""
    n = int(round(2 * half / bin_mm))
    ij = np.floor((xy + half) / bin_mm).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < n), axis=1)
    counts = np.bincount(ij[ok, 1] * n + ij[ok, 0], minlength=n * n).reshape(n, n)
    return counts * (weight / bin_mm**2)


def _bins_in_circle(half: float, bin_mm: float, radius: float) -> np.ndarray:
    n = int(round(2 * half / bin_mm))
    centres = -half + bin_mm * (np.arange(n) + 0.5)
    return np.hypot(centres[None, :], centres[:, None]) <= radius


def _uniformity(
    record: RayRecord, on_sample: np.ndarray, bin_mm: float, radius: float
) -> tuple[Estimate, Estimate, float]:
    """Uniformity over the field's circle (radius, mm) on bin_mm bins: the CV and min/max of the
    rays per bin (every ray carries the same power) with jackknife errors, and the mean count."""
    groups = np.arange(record.rays) % JACKKNIFE_GROUPS
    half_u = bin_mm * math.ceil(radius / bin_mm)
    inside_bins = _bins_in_circle(half_u, bin_mm, radius)
    hits = record.hit_mm
    n_side = int(round(2 * half_u / bin_mm))
    ij = np.floor((hits[on_sample] + half_u) / bin_mm).astype(np.int64)
    ok = np.all((ij >= 0) & (ij < n_side), axis=1)
    flat = ij[ok, 1] * n_side + ij[ok, 0]
    group_of = groups[on_sample][ok]
    per_group = np.bincount(group_of * n_side * n_side + flat, minlength=JACKKNIFE_GROUPS * n_side * n_side)
    per_group = per_group.reshape(JACKKNIFE_GROUPS, n_side * n_side)[:, inside_bins.ravel()].astype(float)
    counts = per_group.sum(axis=0)
    uniformity_cv = _jackknife_bins(counts, per_group, lambda c: c.std() / c.mean() if c.mean() > 0 else math.nan)
    uniformity_min_max = _jackknife_bins(counts, per_group, lambda c: c.min() / c.max() if c.max() > 0 else math.nan)
    mean_count = float(counts.mean()) if counts.size else 0.0
    return uniformity_cv, uniformity_min_max, mean_count


def _ledger(status: np.ndarray, on_sample: np.ndarray, delivered: np.ndarray) -> dict[str, Estimate]:
    """Where the rays went, as fractions of all rays: delivered, absorbed (by absorber, trapped),
    escaped (outside the field, out of the scene), unaccounted, and the closure of the sum."""
    ledger = {"delivered": _fraction(delivered)}
    absorbed_total = np.zeros(status.size, dtype=bool)
    for group in Absorber:
        mask = status == int(Status.ABSORBED) + int(group)
        absorbed_total |= mask
        ledger[f"absorbed_{group.name.lower()}"] = _fraction(mask)
    trapped = status == int(Status.TRUNCATED)
    absorbed_total |= trapped
    ledger["absorbed_trapped"] = _fraction(trapped)
    ledger["absorbed"] = _fraction(absorbed_total)
    outside = on_sample & ~delivered
    left = status == int(Status.ESCAPED)
    ledger["escaped_outside_field"] = _fraction(outside)
    ledger["escaped_left_scene"] = _fraction(left)
    ledger["escaped"] = _fraction(outside | left)
    accounted = delivered | absorbed_total | outside | left
    ledger["unaccounted"] = _fraction(~accounted)
    total = ledger["delivered"].value + ledger["absorbed"].value + ledger["escaped"].value
    ledger["closure"] = Estimate(total - 1.0, 0.0)

    return ledger


def _per_led(record: RayRecord, delivered: np.ndarray) -> list[dict[str, Any]]:
    """Each LED's throughput, delivered fraction and power (mW) with their errors."""
    units = record.units
    per_led = []
    for unit in range(units):
        mine = record.unit == unit
        flux = float(np.count_nonzero(mine) * record.power_mw)  # this LED's emitted power, mW
        t = _fraction(record.passed[mine])
        f = _fraction(delivered[mine])
        per_led.append(
            {
                "led": unit,
                "throughput": _round(t.value),
                "throughput_stderr": _round(t.stderr),
                "delivered_fraction": _round(f.value),
                "delivered_fraction_stderr": _round(f.stderr),
                "power_mw": _round(f.value * flux),
                "power_mw_stderr": _round(f.stderr * flux),
            }
        )
    return per_led


def figures_of_merit(
    record: RayRecord,
    scene: IlluminationScene,
    *,
    bin_mm: float = 0.5,
    map_bin_mm: float = 0.1,
    map_margin_mm: float = 2.0,
) -> IlluminationFigures:
    """The figures of merit of a trace (definitions in the module docstring).

    bin_mm: side of the uniformity bins, mm. map_bin_mm: pixel of the irradiance maps, mm.
    map_margin_mm: how far the maps reach beyond the circle, mm.
    """
    if not (0 < bin_mm <= scene.field_radius_mm):
        raise ValueError(f"bin_mm = {bin_mm}: must lie within 0–{scene.field_radius_mm} mm (the field's radius)")
    radius = scene.field_radius_mm
    status = record.status
    r = np.hypot(record.hit_mm[:, 0], record.hit_mm[:, 1])
    on_sample = status == int(Status.SAMPLE)
    delivered = on_sample & (r <= radius)
    axes = scene.unit_axes[record.unit]
    cos_axis = np.einsum("ij,ij->i", np.nan_to_num(record.exit_direction), axes)
    angle = np.degrees(np.arccos(np.clip(cos_axis, -1.0, 1.0)))
    within30 = record.passed & (angle <= 30.0)

    flux = float(record.power_mw * record.rays_per_unit)
    units = record.units
    throughput = _fraction(record.passed)
    delivered_fraction = _fraction(delivered)
    emitted_mw = record.rays * record.power_mw  # units × flux, less or more where LEDs differ
    power = Estimate(delivered_fraction.value * emitted_mw, delivered_fraction.stderr * emitted_mw)

    uniformity_cv, uniformity_min_max, mean_count = _uniformity(record, on_sample, bin_mm, radius)
    passed_angles = angle[record.passed]

    ledger = _ledger(status, on_sample, delivered)

    per_led = _per_led(record, delivered)

    map_half = map_bin_mm * math.ceil((radius + map_margin_mm) / map_bin_mm)
    hits = record.hit_mm
    unit_map = _histogram(hits[on_sample & (record.unit == 0)], record.power_mw, map_half, map_bin_mm)
    array_map = _histogram(hits[on_sample], record.power_mw, map_half, map_bin_mm)
    return IlluminationFigures(
        label=scene.label,
        rays=record.rays,
        rays_per_led=record.rays_per_unit,
        units=units,
        led_flux_mw=flux,
        field_radius_mm=radius,
        throughput=throughput,
        delivered_fraction=delivered_fraction,
        power_mw=power,
        uniformity_min_max=uniformity_min_max,
        uniformity_cv=uniformity_cv,
        uniformity_cv_noise=1.0 / math.sqrt(mean_count) if mean_count > 0 else math.inf,
        fraction_within_30deg=_fraction(within30),
        beam_half_angle_50_deg=_quantile(passed_angles, 0.5),
        beam_half_angle_90_deg=_quantile(passed_angles, 0.9),
        ledger=ledger,
        per_led=per_led,
        bin_mm=bin_mm,
        map_bin_mm=map_bin_mm,
        map_half_mm=map_half,
        unit_map=unit_map,
        array_map=array_map,
        seconds=record.seconds,
        variant=record.variant,
    )


def write_maps_png(figures: IlluminationFigures, path: str | Path) -> Path:
    """One PNG with the irradiance of one LED and of the array (mW/mm²), the field circle drawn."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    from cm2optics.formats.atomic import write_atomic

    half = figures.map_half_mm
    fig = Figure(figsize=(10, 4.4), constrained_layout=True)  # no pyplot: a notebook's backend stays as it is
    axes = fig.subplots(1, 2)
    for ax, image, title in (
        (axes[0], figures.unit_map, "one LED"),
        (axes[1], figures.array_map, f"{figures.units} LEDs"),
    ):
        shown = ax.imshow(image, origin="lower", extent=(-half, half, -half, half), cmap="inferno")
        ax.add_patch(Circle((0, 0), figures.field_radius_mm, fill=False, color="cyan", lw=1.0, ls="--"))
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(title)
        fig.colorbar(shown, ax=ax, label="irradiance (mW/mm²)")
    fig.suptitle(
        f"{figures.label}: delivered {figures.delivered_fraction.value:.1%} → {figures.power_mw.value:.1f} mW "
        f"in Ø{2 * figures.field_radius_mm:g} mm, CV {figures.uniformity_cv.value:.1%}"
    )
    path = Path(path)
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    return path
