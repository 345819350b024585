"""The residual of a measured PSF scan against its model, image by image and focus by focus.

:func:`analyse_scan` registers the model to the data (:mod:`.register`), estimates the sensor's
noise (:mod:`.noise`) and measures every focus in both (:mod:`.features`). What it returns is the
evidence the attribution works from and the numbers a person reads:

- per image: NMSE ``‖d − µ‖²/‖d − dark‖²`` and the reduced χ² under the noise model;
- per focus: the energy ratio data/model, the centroid error (px) and the width ratio, with
  their summaries against field radius, depth and lenslet;
- the background the model lacks: its level against exposure (light that scales with the
  exposure is leakage or stray light; a constant is a dark-level error) and its spatial structure.

Bad data get one clear :class:`CalibrationError` (a frame of the wrong size, a scan whose
positions differ from the model's) or a flag in the analysis (saturated frames and frames
without light are left out of every fit; images whose foci sit far from where their
positions put them are named).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cm2optics.calibrate.features import (
    FocusFeatures,
    away_from_foci,
    focus_features,
    focus_windows,
    local_centroids,
)
from cm2optics.calibrate.noise import SensorNoise, estimate_noise, quantisation_step
from cm2optics.calibrate.register import Registration, register
from cm2optics.errors import UserError

#: A focus whose data centroid sits farther than this fraction of the lenslet pitch from the
#: model's marks its image as one whose position does not match its content.
MISPLACED_FRACTION = 0.25
#: A frame whose light above dark is below this fraction of the model's is "empty".
EMPTY_FRACTION = 0.05


class CalibrationError(UserError):
    """Data that cannot be compared with the model; the message says what and where."""


@dataclass(frozen=True)
class ScanData:
    """Frames to compare: raw counts (N, y, x), exposures (N,) ms, positions (N, 3) mm, names;
    ``defects`` (y, x): the sensor's defective pixels, left out of every fit (None: none known)."""

    counts: np.ndarray
    exposure_ms: np.ndarray
    positions_mm: np.ndarray
    files: tuple[str, ...]
    bit_depth: int
    defects: np.ndarray | None = None

    def good_pixels(self) -> np.ndarray:
        """(y, x) bool: the pixels that are not defects."""
        return np.ones(self.counts.shape[-2:], bool) if self.defects is None else ~self.defects

    def subset(self, index: np.ndarray) -> ScanData:
        """The frames ``index`` (same defects)."""
        return ScanData(
            self.counts[index],
            self.exposure_ms[index],
            self.positions_mm[index],
            tuple(self.files[i] for i in index),
            self.bit_depth,
            self.defects,
        )


@dataclass(frozen=True)
class ResidualAnalysis:
    """What :func:`analyse_scan` found (arrays over images N and lenslets J)."""

    registration: Registration
    noise: SensorNoise
    positions_mm: np.ndarray
    files: tuple[str, ...]
    used: np.ndarray
    nmse: np.ndarray
    chi2: np.ndarray
    data: FocusFeatures
    model: FocusFeatures
    background_counts: np.ndarray
    background_map: np.ndarray
    residual_counts: np.ndarray
    model_counts: np.ndarray
    flags: dict[str, list[str]] = field(default_factory=dict)

    @property
    def nmse_total(self) -> float:
        return _total_nmse(self)

    @property
    def chi2_total(self) -> float:
        return _total_chi2(self)

    @property
    def energy_ratio(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.data.energy / self.model.energy

    @property
    def centroid_error_px(self) -> np.ndarray:
        return self.data.centroid_px - self.model.centroid_px

    @property
    def width_ratio(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.data.width_px / self.model.width_px

    def to_dict(self) -> dict[str, object]:
        """The analysis as a JSON-ready document (summaries, not the pixel arrays)."""
        return residual_document(self)


def _total_nmse(a: ResidualAnalysis) -> float:
    used = a.used
    signal = a.model_counts[used] - a.registration.dark_level + a.residual_counts[used]
    return float(np.sum(a.residual_counts[used] ** 2) / max(np.sum(signal**2), 1e-30))


def _total_chi2(a: ResidualAnalysis) -> float:
    return float(np.nanmean(a.chi2[a.used])) if np.any(a.used) else float("nan")


def check_frames(data: ScanData) -> None:
    """A clear error for frames that cannot be analysed at all: not a stack, NaN or infinite pixels."""
    if data.counts.ndim != 3:
        raise CalibrationError(f"the measured frames must be a stack (N, y, x); got shape {data.counts.shape}")
    if not np.all(np.isfinite(data.counts)):
        bad = [data.files[i] for i in np.flatnonzero(~np.isfinite(data.counts).all(axis=(-2, -1)))]
        raise CalibrationError(f"frames with NaN or infinite pixels: {', '.join(bad[:5])}")


def _check_inputs(data: ScanData, model_rate: np.ndarray, model_positions_mm: np.ndarray) -> None:
    check_frames(data)
    if data.counts.shape[-2:] != model_rate.shape[-2:]:
        raise CalibrationError(
            f"wrong sensor size: the measured frames are {data.counts.shape[-2]} × {data.counts.shape[-1]} px, "
            f"the design's sensor at this binning gives {model_rate.shape[-2]} × {model_rate.shape[-1]} px"
        )
    if len(data.counts) != len(model_rate) or not np.allclose(data.positions_mm, model_positions_mm, atol=1e-6):
        raise CalibrationError("the model was simulated at other positions than the scan's positions.csv")


def analyse_scan(
    data: ScanData,
    model_rate: np.ndarray,
    model_positions_mm: np.ndarray,
    centres_px: np.ndarray,
    pitch_px: float,
    *,
    counts_per_electron: float | None = None,
) -> ResidualAnalysis:
    """Compare measured frames with the model's images of the same positions.

    data: the measured frames.
    model_rate: (N, y, x) the model's images, counts per ms for a unit source above dark.
    model_positions_mm: (N, 3) the positions the model was simulated at (must equal the data's).
    centres_px: (N, J, 2) predicted focus positions (row, col) px in the model's frame.
    pitch_px: distance between neighbouring foci, px (sets the largest window).
    counts_per_electron: the camera's gain when known; fitted from the data otherwise.
    """
    _check_inputs(data, model_rate, model_positions_mm)
    counts = data.counts.astype(np.float32)
    used, flags = _usable_frames(data, model_rate)
    valid = used[:, None, None] & np.isfinite(counts) & data.good_pixels()[None]
    registration, model_counts = register(counts, data.exposure_ms, model_rate, valid)
    model_counts = model_counts.astype(np.float32)
    if data.defects is not None:  # defective pixels hold no information: the model's value, a zero residual
        counts = np.where(data.defects[None], model_counts, counts)

    signal = counts - registration.dark_level
    model_signal = model_counts - registration.dark_level
    residual = counts - model_counts
    dark_mask = valid & (model_signal <= 1e-3 * float(model_signal.max()))
    noise = estimate_noise(
        residual[valid],
        model_signal[valid],
        dark_mask[valid],
        counts_per_electron,
        quantisation_step(data.counts[valid]),
    )
    nmse, chi2 = _per_image_misfit(residual, signal, noise.variance(model_signal), valid, used)

    centres, radii = focus_windows(model_signal, centres_px + np.asarray(registration.offset_px), pitch_px)
    data_features = _with_local_centroids(focus_features(signal, centres, radii), signal, centres, radii)
    model_features = _with_local_centroids(focus_features(model_signal, centres, radii), model_signal, centres, radii)

    error = np.linalg.norm(data_features.centroid_px - model_features.centroid_px, axis=-1)
    misplaced = used & (
        np.nanmedian(np.where(np.isfinite(error), error, np.nan), axis=1) > MISPLACED_FRACTION * pitch_px
    )
    if np.any(misplaced):
        flags["positions_do_not_match_images"] = [data.files[i] for i in np.flatnonzero(misplaced)]

    outside = valid & away_from_foci(counts.shape[-2:], centres, 2.0 * radii)  # the wings kept out
    with np.errstate(invalid="ignore"):
        background = np.array(
            [float(np.median(residual[i][outside[i]])) if outside[i].any() else np.nan for i in range(len(counts))]
        )
    background_map = _background_map(residual, outside, data.exposure_ms)
    return ResidualAnalysis(
        registration=registration,
        noise=noise,
        positions_mm=np.asarray(data.positions_mm, float),
        files=data.files,
        used=used,
        nmse=nmse,
        chi2=chi2,
        data=data_features,
        model=model_features,
        background_counts=background,
        background_map=background_map,
        residual_counts=residual,
        model_counts=model_counts,
        flags={k: v for k, v in flags.items() if v},
    )


def _with_local_centroids(
    features: FocusFeatures, signal: np.ndarray, centres: np.ndarray, radii: np.ndarray
) -> FocusFeatures:
    """``features`` with centroids measured above each window's own background
    (:func:`~cm2optics.calibrate.features.local_centroids`; energies and widths unchanged)."""
    return FocusFeatures(features.energy, local_centroids(signal, centres, radii), features.width_px)


def _usable_frames(data: ScanData, model_rate: np.ndarray) -> tuple[np.ndarray, dict[str, list[str]]]:
    """(N,) frames that take part, and the flags of those left out: saturated frames and frames
    without light; an error when none is left."""
    saturated = ((data.counts >= 2**data.bit_depth - 1) & data.good_pixels()[None]).any(axis=(-2, -1))
    flags: dict[str, list[str]] = {"saturated": [data.files[i] for i in np.flatnonzero(saturated)]}
    light = model_rate.reshape(len(model_rate), -1).max(axis=1) > 0
    used = ~saturated & light
    empty = used & _without_light(data, model_rate)
    if np.any(empty):
        flags["empty"] = [data.files[i] for i in np.flatnonzero(empty)]
        used = used & ~empty
    if not np.any(used):
        raise CalibrationError("no frame can be compared: every frame is saturated or the model puts no light on it")
    return used, flags


def _per_image_misfit(
    residual: np.ndarray, signal: np.ndarray, variance: np.ndarray, valid: np.ndarray, used: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) NMSE ‖d − µ‖²/‖d − dark‖² and reduced χ² of each frame (NaN where left out)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        chi2 = np.where(used, np.sum(np.where(valid, residual**2 / variance, 0.0), axis=(-2, -1)), np.nan)
        chi2 = chi2 / np.maximum(valid.sum(axis=(-2, -1)), 1)
        nmse = np.where(
            used, np.sum(residual**2, axis=(-2, -1)) / np.maximum(np.sum(signal**2, axis=(-2, -1)), 1e-30), np.nan
        )
    return nmse, chi2


def _without_light(data: ScanData, model_rate: np.ndarray) -> np.ndarray:
    """(N,) frames whose light per ms, relative to the model's, is below ``EMPTY_FRACTION`` of the
    scan's median ratio (a shutter that stayed shut, a source that went out)."""
    counts = data.counts.reshape(len(data.counts), -1).astype(np.float64)
    dark = np.median(counts, axis=1, keepdims=True)  # most pixels of a PSF frame are dark
    light = np.clip(counts - dark, 0.0, None).sum(axis=1) / np.asarray(data.exposure_ms, float)
    expected = model_rate.reshape(len(model_rate), -1).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = light / expected
    return ratio < EMPTY_FRACTION * np.nanmedian(ratio[expected > 0])


def _background_map(residual: np.ndarray, outside: np.ndarray, exposure_ms: np.ndarray, blocks: int = 16) -> np.ndarray:
    """The residual outside the foci in counts per ms, averaged over images on a coarse grid
    (``blocks`` × ``blocks``; NaN where no pixel is outside)."""
    n, h, w = residual.shape
    rate = np.where(outside, residual / np.asarray(exposure_ms, np.float32)[:, None, None], 0.0)
    by, bx = h // blocks, w // blocks
    crop = (slice(None), slice(0, by * blocks), slice(0, bx * blocks))
    sums = rate[crop].reshape(n, blocks, by, blocks, bx).sum(axis=(0, 2, 4))
    counts = outside[crop].reshape(n, blocks, by, blocks, bx).sum(axis=(0, 2, 4))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / counts, np.nan)


def _binned(values: np.ndarray, keys: np.ndarray, edges: np.ndarray) -> list[float | None]:
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (keys >= lo) & (keys < hi) & np.isfinite(values)
        out.append(round(float(np.mean(values[inside])), 5) if inside.any() else None)
    return out


def residual_document(a: ResidualAnalysis) -> dict[str, object]:
    """Summaries of an analysis against field radius, depth and lenslet (JSON-ready)."""
    radius = np.hypot(a.positions_mm[:, 0], a.positions_mm[:, 1])
    depths = np.unique(np.round(a.positions_mm[:, 2], 6))
    field_edges = np.linspace(0.0, float(radius.max()) + 1e-9, 6)
    used = a.used[:, None] & np.isfinite(a.energy_ratio)
    ratio = np.where(used, a.energy_ratio, np.nan)
    shift = np.where(used[..., None], a.centroid_error_px, np.nan)
    widths = np.where(used, a.width_ratio, np.nan)
    per_focus_field = np.broadcast_to(radius[:, None], ratio.shape)
    per_focus_depth = np.broadcast_to(a.positions_mm[:, 2, None], ratio.shape)
    depth_edges = np.concatenate([depths - 1e-6, [depths[-1] + 1e-6]]) if len(depths) else np.array([0.0, 1.0])
    exposure_free = np.isfinite(a.background_counts) & a.used
    return {
        "images": int(len(a.files)),
        "images_used": int(a.used.sum()),
        "nmse": round(a.nmse_total, 6),
        "chi2": round(a.chi2_total, 4),
        "registration": a.registration.to_dict(),
        "noise": a.noise.to_dict(),
        "per_image": [
            {
                "file": a.files[i],
                "x_mm": round(float(a.positions_mm[i, 0]), 6),
                "y_mm": round(float(a.positions_mm[i, 1]), 6),
                "z_mm": round(float(a.positions_mm[i, 2]), 6),
                "used": bool(a.used[i]),
                "nmse": None if not np.isfinite(a.nmse[i]) else round(float(a.nmse[i]), 6),
                "chi2": None if not np.isfinite(a.chi2[i]) else round(float(a.chi2[i]), 4),
            }
            for i in range(len(a.files))
        ],
        "against_field": {
            "field_mm_edges": [round(float(e), 4) for e in field_edges],
            "energy_ratio": _binned(ratio, per_focus_field, field_edges),
            "centroid_error_px": _binned(np.linalg.norm(shift, axis=-1), per_focus_field, field_edges),
            "width_ratio": _binned(widths, per_focus_field, field_edges),
        },
        "against_depth": {
            "z_mm": [round(float(z), 6) for z in depths],
            "energy_ratio": _binned(ratio, per_focus_depth, depth_edges),
            "centroid_error_px": _binned(np.linalg.norm(shift, axis=-1), per_focus_depth, depth_edges),
            "width_ratio": _binned(widths, per_focus_depth, depth_edges),
        },
        "per_lenslet": {
            "energy_ratio": [round(float(v), 5) for v in np.nanmean(ratio, axis=0)],
            "centroid_error_px": [[round(float(v), 4) for v in row] for row in np.nanmean(shift, axis=0)],
            "width_ratio": [round(float(v), 5) for v in np.nanmean(widths, axis=0)],
        },
        "background": {
            "median_counts": round(float(np.nanmedian(a.background_counts[exposure_free])), 4)
            if exposure_free.any()
            else None,
            "map_counts_per_ms": [
                [None if not np.isfinite(v) else round(float(v), 6) for v in row] for row in a.background_map
            ],
        },
        "flags": a.flags,
    }
