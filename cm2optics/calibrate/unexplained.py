"""What the fitted effects leave unexplained: the signature of a structured residual.

After the attribution, every focus of every image is tested against the noise model: its patch
of the residual (2·half + 1 px square around the model focus) has χ² = Σ r²/σ² over n pixels;
a focus is *flagged* when that χ² exceeds n by more than :data:`Z_FLAG` standard deviations
(√(2n)) and its reduced χ² exceeds :data:`REDUCED_FLAG`; a lenslet counts when at least
:data:`MIN_FOCI` of its foci are flagged. Clean data flag nothing. A change of energy common to
the foci is no signature: the registration's one flux scale is a least-squares fit over every
pixel, and a few bright foci dimmed by a local loss (a scratch) pull it, so that every other
focus looks a few per cent too bright; the patches are compared with the model scaled by the
median data/model energy ratio of the bright foci (:data:`COMMON_FOCI` of their image's brightest).

Flagged foci are grouped: when most lenslets are flagged in most images the residual is common
to all foci (one entry); otherwise each flagged lenslet is one entry. Each entry says where
(``lenslets``, the field radius range ``field_mm`` and ``depths_mm`` of its flagged images),
how much (``energy_fraction``: Σ|residual| over its flagged patches / the model's signal in
those patches) and what shape (``description``), read from the entry's mean residual patch
relative to its foci's energy: a displaced copy of the foci (light outside the focus with its
own centroid, offset and width; light moved to both sides of the focus is a wider focus, an
aberration, instead), or foci dimmed by a share that changes with the position (a
transmission loss that no constant per-lenslet transmission explains), or neither.
"""

from __future__ import annotations

from typing import Any
from warnings import catch_warnings, simplefilter

import numpy as np

from cm2optics.calibrate.features import focus_patches
from cm2optics.calibrate.residual import ResidualAnalysis

__all__ = ["PATCH_HALF_PX", "describe_unexplained", "flagged_foci"]

#: Half-size of the residual patch around each focus, px (33 × 33 px: a focus defocused by
#: 0.5 mm spreads over ≈ 20 px at 8× binning; the lenslet pitch is ≈ 80 px there).
PATCH_HALF_PX = 16
#: A focus is flagged when its patch χ² exceeds its pixel count by this many standard deviations…
Z_FLAG = 8.0
#: …and its reduced χ² exceeds this.
REDUCED_FLAG = 1.5
#: A lenslet flagged in fewer foci than this is no signature: one focus at the field's edge can
#: hold the model's own local error (a corner focus after a fitted 0.5° rotation, traced scan).
MIN_FOCI = 2
#: Foci at least this share of their image's brightest (model) give the common energy ratio.
COMMON_FOCI = 0.1
#: Flagged foci whose energies all change less than this (relative) differ in shape or position,
#: not in energy: no loss is named then.
ENERGY_UNCHANGED = 0.02
#: A "copy" holding more than this share of the energy one pixel from the focus is the focus
#: itself displaced (sub-pixel shifts fit best as a copy at one pixel), not a ghost.
DISPLACED_SHARE = 0.3
#: Largest ghost offset sought, px: the patch's half less 2 px, so that a copy's core lies in it
#: (a ghost farther than this from its focus is not sought; session 10's 8 px missed one at 14 px).
GHOST_REACH_PX = PATCH_HALF_PX - 2
#: A displaced copy is named when it explains this share of the mean residual patch…
GHOST_EXPLAINS = 0.6
#: …and this much more than a change of the focus's energy alone.
GHOST_GAIN = 0.3


def flagged_foci(
    after: ResidualAnalysis, half: int = PATCH_HALF_PX, per_frame: bool = False, background: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, J) flagged foci (module docstring), and the residual (against the model at the foci's
    common energy ratio; with ``per_frame``, at each frame's own, for a scan whose source drifted;
    above ``background`` (N, J, 2·half + 1, 2·half + 1) counts on the same patches, a structure of
    the background described apart, :mod:`.background`) and model-signal patches (N, J, 2·half + 1, 2·half + 1) in counts."""
    model_signal = after.model_counts - after.registration.dark_level
    centres = after.model.centroid_px
    residual, inside = focus_patches(after.residual_counts, centres, half)
    if background is not None:
        residual = residual - background
    model, _ = focus_patches(model_signal, centres, half)
    variance = after.noise.variance(model)
    energy = model.sum(axis=(-2, -1))
    bright = after.used[:, None] & inside & (energy >= COMMON_FOCI * np.max(energy, axis=1, keepdims=True))
    if bright.any():  # the residual against the model at the foci's common energy ratio
        ratios = 1.0 + residual.sum(axis=(-2, -1)) / np.maximum(energy, 1e-30)
        ratio = np.median(ratios[bright])
        if per_frame:  # each frame's own ratio (its common ratio where it has no bright focus)
            with np.errstate(invalid="ignore"), catch_warnings():
                simplefilter("ignore", RuntimeWarning)
                own = np.nanmedian(np.where(bright, ratios, np.nan), axis=1)
            ratio = np.where(np.isfinite(own), own, ratio)[:, None, None, None]
        residual = residual - (ratio - 1.0) * model
    pixels = float((2 * half + 1) ** 2)
    chi2 = np.sum(residual**2 / variance, axis=(-2, -1))
    z = (chi2 - pixels) / np.sqrt(2.0 * pixels)
    flagged = after.used[:, None] & inside & (z > Z_FLAG) & (chi2 / pixels > REDUCED_FLAG)
    return flagged, residual, model


def describe_unexplained(
    after: ResidualAnalysis,
    pixel_um: float,
    half: int = PATCH_HALF_PX,
    per_frame: bool = False,
    background: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """The entries ``{lenslets, field_mm, depths_mm, energy_fraction, description}`` of what
    remains above the noise after the fit (empty when no focus is flagged); ``pixel_um`` is the
    binned pixel pitch, µm; ``per_frame``: each frame's flux is its own (a source that drifted
    during the scan, :mod:`.acquisition`), so that only what departs from it is described;
    ``background`` (N, J, 2·half + 1, 2·half + 1) counts: a background structure on the foci's
    patches, which they are read above."""
    flagged, residual, model = flagged_foci(after, half, per_frame, background)
    if not flagged.any():
        return []
    repeated = flagged.sum(axis=0) >= MIN_FOCI
    flagged = flagged & repeated[None, :]
    if not flagged.any():
        return []
    lenslets = np.flatnonzero(repeated)
    if len(lenslets) > flagged.shape[1] // 2:
        groups = [lenslets]
    else:
        groups = [np.array([j]) for j in np.flatnonzero(flagged.any(axis=0))]
    return [_entry(after, flagged, residual, model, group, pixel_um) for group in groups]


def _entry(
    after: ResidualAnalysis,
    flagged: np.ndarray,
    residual: np.ndarray,
    model: np.ndarray,
    lenslets: np.ndarray,
    pixel_um: float,
) -> dict[str, Any]:
    mask = np.zeros_like(flagged)
    mask[:, lenslets] = flagged[:, lenslets]
    where = np.flatnonzero(mask.any(axis=1))
    field = np.hypot(after.positions_mm[where, 0], after.positions_mm[where, 1])
    energy = model.sum(axis=(-2, -1))  # (N, J) model focus energy, counts
    fraction = float(np.abs(residual[mask]).sum() / max(float(np.abs(model[mask]).sum()), 1e-30))
    shape = _shape(residual[mask], energy[mask], model[mask], pixel_um)
    # per flagged focus: the relative change of its energy
    change = residual[mask].sum(axis=(-2, -1)) / np.maximum(energy[mask], 1e-30)
    misfit = np.where(mask, np.sum(residual**2, axis=(-2, -1)) / np.maximum(np.sum(model**2, axis=(-2, -1)), 1e-30), -1)
    worst = after.positions_mm[np.unravel_index(np.argmax(misfit), misfit.shape)[0]]
    count = (
        f"{int(mask.sum())} foci in {len(where)} of {int(after.used.sum())} images, largest at field "
        f"{np.hypot(worst[0], worst[1]):.2f} mm: x, y, z = {worst[0]:.3g}, {worst[1]:.3g}, {worst[2]:.3g} mm"
    )
    low, high = float(change.min()), float(change.max())
    if shape is None and max(abs(low), abs(high)) < ENERGY_UNCHANGED:
        dx, dy = _displacement_px(residual[mask], model[mask])
        description = (
            f"the foci of lenslet{'s' if len(lenslets) > 1 else ''} {[int(j) for j in lenslets]} differ from the "
            f"model in shape or position, not in energy ({low:+.1%} to {high:+.1%}; mean displacement "
            f"({dx:+.2f}, {dy:+.2f}) px) ({count}): a local aberration or focus position the design's "
            f"parameters do not reach"
        )
    elif shape is None:
        kind = "a loss" if high < 0 else "a gain" if low > 0 else "a gain or loss"
        description = (
            f"the foci of lenslet{'s' if len(lenslets) > 1 else ''} {[int(j) for j in lenslets]} change in "
            f"energy by {low:+.1%} to {high:+.1%} ({count}) while the other positions match: {kind} that "
            f"depends on the source position or on where the foci land on the sensor (e.g. a scratch or dust "
            f"on a filter in front of the array, a sensor gain that varies over the sensor), not a constant "
            f"lenslet transmission"
        )
    else:
        description = f"{shape} ({count})"
    return {
        "lenslets": [int(j) for j in lenslets],
        "field_mm": [round(float(field.min()), 3), round(float(field.max()), 3)],
        "depths_mm": sorted({round(float(z), 4) for z in after.positions_mm[where, 2]}),
        "energy_fraction": round(fraction, 5),
        "description": description,
    }


def _displacement_px(residual: np.ndarray, model: np.ndarray) -> tuple[float, float]:
    """Mean displacement (x, y) px of foci whose residual patches (M, P, P) against their model
    patches is a small shift d: residual ≈ −d·∇model, so its first moment over the model's total is d."""
    half = residual.shape[-1] // 2
    offsets = np.arange(-half, half + 1, dtype=float)
    total = max(float(model.sum()), 1e-30)
    return float((residual * offsets[None, None, :]).sum() / total), float(
        (residual * offsets[None, :, None]).sum() / total
    )


def _shape(residual: np.ndarray, energy: np.ndarray, model: np.ndarray, pixel_um: float) -> str | None:
    """A displaced copy of the foci read from the mean residual patch R relative to the foci's
    energy (residual, model: (F, w, w) counts; energy (F,)): R is fitted by a·M + b·M shifted
    by d (M the mean model focus) for every integer d within :data:`GHOST_REACH_PX`; the best d
    is named when it explains :data:`GHOST_EXPLAINS` of R and :data:`GHOST_GAIN` more than a·M
    alone (a change of energy), and when it is a copy rather than the focus itself displaced (a
    copy of more than :data:`DISPLACED_SHARE` of the energy within one pixel's offset is the
    focus moved). A pair of copies at ± d that explains more than the best single copy (and as
    much as a copy must) is light moved out to both sides: a wider focus. None otherwise."""
    relative = residual.sum(axis=0) / energy.sum()
    focus = model.sum(axis=0) / energy.sum()
    total = float(np.sum(relative**2))
    if total <= 0:
        return None
    alone = float(np.sum(relative * focus)) ** 2 / max(float(np.sum(focus**2)), 1e-30)
    best, wider = (0.0, 0.0, (0, 0)), (0.0, 0.0, (0, 0))
    reach = min(GHOST_REACH_PX, relative.shape[0] // 2)
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if (dr, dc) == (0, 0):
                continue
            moved = _moved(focus, dr, dc)
            for kind, shape in (("copy", moved), ("both", moved + _moved(focus, -dr, -dc))):
                basis = np.stack([focus.ravel(), shape.ravel()], axis=1)
                coefficients, *_ = np.linalg.lstsq(basis, relative.ravel(), rcond=None)
                explained = total - float(np.sum((relative.ravel() - basis @ coefficients) ** 2))
                found = (explained, float(coefficients[1]), (dr, dc))
                if kind == "copy" and coefficients[1] > 0 and explained > best[0]:
                    best = found
                if kind == "both" and coefficients[1] > 0 and explained > wider[0]:
                    wider = found
    if wider[0] > best[0] and wider[0] >= GHOST_EXPLAINS * total and wider[0] - alone >= GHOST_GAIN * total:
        explained, share, (dr, dc) = wider  # light moved out to both sides: a wider focus, not a copy
        return (
            f"foci wider than the model's along ({dr:+d}, {dc:+d}) px (row, col): {share:.1%} of each focus's "
            f"energy moved out to ± {np.hypot(dr, dc):.0f} px ({np.hypot(dr, dc) * pixel_um:.0f} µm) on both sides, "
            f"explaining {explained / total:.0%} of the mean residual: a blur or aberration of the lenslet "
            f"(astigmatism, defocus) that the design's parameters do not reach, not a ghost"
        )
    explained, share, (dr, dc) = best
    if (
        explained < GHOST_EXPLAINS * total
        or explained - alone < GHOST_GAIN * total
        or (share > DISPLACED_SHARE and max(abs(dr), abs(dc)) <= 1)
    ):
        return None
    return (
        f"a displaced copy of the foci (a ghost): {share:.1%} of each focus's energy at ({dr:+d}, {dc:+d}) px "
        f"(row, col; {np.hypot(dr, dc) * pixel_um:.0f} µm on the sensor) from it, explaining {explained / total:.0%} "
        f"of the mean residual around the foci"
    )


def _moved(patch: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """``patch`` moved by (dr, dc) px, zeros shifted in."""
    out = np.zeros_like(patch)
    h, w = patch.shape
    out[max(dr, 0) : h + min(dr, 0), max(dc, 0) : w + min(dc, 0)] = patch[
        max(-dr, 0) : h + min(-dr, 0), max(-dc, 0) : w + min(-dc, 0)
    ]
    return out
