"""A small synthetic scan for the checks read after the fit (acquisition, sensor gain): a 3 × 3
lattice of Gaussian foci (σ 1.2 px) that moves with the source, on a 180 × 180-px sensor with
Poisson shot noise (0.25 counts/e⁻), 2-count read noise, a 100-count dark level and 12 bits,
analysed against the model (the same lattice, undisturbed) by `calibrate.residual.analyse_scan`."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cm2optics.calibrate.noise import raw_frames
from cm2optics.calibrate.residual import ResidualAnalysis, ScanData, analyse_scan

GAIN = 0.25  # counts per electron
SHAPE = (180, 180)
LATTICE = np.array([[r, c] for r in (-36.0, 0.0, 36.0) for c in (-36.0, 0.0, 36.0)])  # foci about the centre, px
#: The lattice's points below the lenslets' vertices (where a source in front of each lands).
VERTICES = 90.0 + LATTICE
DEPTHS = np.array([[x, y, z] for x in (-1.0, 0.0, 1.0) for y in (-1.0, 1.0) for z in (-0.5, 0.5)])
FIELD = np.array([[x, y, 0.0] for x in np.linspace(-1, 1, 4) for y in np.linspace(-1, 1, 4)])


def lattice_analysis(
    peak: float,
    background: float,
    seed: int,
    *,
    positions: np.ndarray = DEPTHS,
    travel_px: float = 8.0,
    shift_px: np.ndarray | None = None,
    spread: np.ndarray | None = None,
    spread_centre_px: np.ndarray | None = None,
    gain: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    energy: np.ndarray | None = None,
    exposure_ms: np.ndarray | None = None,
    source_error_mm: np.ndarray | None = None,
) -> ResidualAnalysis:
    """Frames of the lattice at ``positions`` (N, 3) mm, moving ``travel_px`` per mm of source x, y
    (rows follow y), with foci of ``peak`` counts above a ramp of 0 → ``background`` counts
    across the columns. The data depart from the model by: a displacement of frame i by
    ``shift_px[i]`` columns, a spread ``spread[i]`` × the model's (about ``spread_centre_px[i]``
    (row, col) px; default the frame's lattice centre), a sensor gain ``gain(rows,
    cols)``, each focus's energy × ``energy`` (N, 9), the source's x, y off by ``source_error_mm``
    (N, 2) mm. Foci and ramp scale with ``exposure_ms`` (N,) (default 1 ms each)."""
    n = len(positions)
    exposure = np.ones(n) if exposure_ms is None else np.asarray(exposure_ms, float)
    centres = VERTICES[None] + travel_px * positions[:, None, 1::-1]  # (N, 9, 2) (row, col)
    factor = (np.ones(n) if spread is None else spread)[:, None, None]
    about = centres.mean(axis=1, keepdims=True) if spread_centre_px is None else spread_centre_px[:, None, :]
    moved = about + factor * (centres - about)
    moved[..., 1] += 0.0 if shift_px is None else shift_px[:, None]
    if source_error_mm is not None:
        moved = moved + travel_px * np.asarray(source_error_mm, float)[:, None, ::-1]
    rows, cols = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]

    def image(c: np.ndarray, weight: np.ndarray) -> np.ndarray:
        d2 = (rows[None, None] - c[:, :, None, None, 0]) ** 2 + (cols[None, None] - c[:, :, None, None, 1]) ** 2
        return np.einsum("nj,njyx->nyx", weight, np.exp(-d2 / 2.88))

    ones = np.ones((n, len(LATTICE)))
    signal = peak * image(moved, ones if energy is None else energy)
    if gain is not None:
        signal = signal * gain(rows, cols)[None]
    ramp = np.linspace(0.0, background, SHAPE[1])[None, None, :]
    expected = 100.0 + (signal + ramp) * exposure[:, None, None]
    counts = raw_frames(expected, 100.0, GAIN, 2.0, 12, np.random.default_rng(seed))
    data = ScanData(counts, exposure, positions, tuple(f"{i}.tif" for i in range(n)), 12)
    return analyse_scan(
        data, image(centres, ones).astype(np.float32), positions, centres, 36.0, counts_per_electron=GAIN
    )
