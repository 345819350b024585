"""Each lenslet's best-focus surface, estimated from a calibration scan (field curvature).

A lenslet images a source sharply at one depth ``z_best,j(x, y)`` that changes across the field
(field curvature: ``z_best ≈ a + b·r²`` with ``r`` the distance from lenslet j's own axis in
object space). A PSF then depends mostly on the *defocus* ``z − z_best,j(x, y)`` and only
slowly on (x, y) otherwise; the interpolation between calibration nodes can follow it
(:mod:`cm2optics.lsv.interpolate`).

Estimate (frames only, so it works on measured scans as on synthetic ones): per node and
lenslet the effective area ``(Σp)² / Σp²`` of the registered crop (far less sensitive to a
sub-pixel phase than the peak; for a blur that grows linearly with defocus it is a parabola in
depth), the depth of its minimum along each axial stack by a parabola through the three nodes
around the smallest (a stack whose smallest node is its first or last has no estimate, nor has
one whose focus hardly changes there (< ``MIN_CONTRAST``), nor a vignetted one, whose brightest node holds < ``VIGNETTED_BELOW`` of its lenslet's brightest),
then per lenslet a robust fit (least median of squares, then least squares on its inliers
weighted by the stack's brightness squared; a flat surface where the curved one does not
explain the inliers better by the Bayesian information criterion) of
``z_best,j = c0 + c1·x + c2·y + c3·(x² + y²)``: a paraboloid of revolution about a free axis
``(−c1, −c2)/(2·c3)`` (the lenslet's axis in object space). Units: x, y, z in mm.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from cm2optics.lsv.crop_store import CropStore, position_chunks

__all__ = ["FocalSurface", "effective_area", "estimate_focal_surface", "stack_best_focus"]

#: A stack whose focus grows by less than this share (both neighbours of its smallest node
#: together) has no measurable best focus: the depth of field is longer than the depth steps.
MIN_CONTRAST = 0.05
#: Robust fit: minimal subsets tried by the least median of squares (all of them if fewer).
LMEDS_SUBSETS = 5000
#: Robust fit: stacks within this many robust standard deviations of the LMedS fit are inliers.
INLIER_SIGMA = 2.5
#: A best focus found by a parabola through three depth nodes is good to about this share of the
#: depth step (the least robust standard deviation the inlier test assumes).
RESOLUTION_OF_STEP = 0.25
#: A stack whose brightest node holds less than this share of its lenslet's brightest focus is
#: vignetted (the housing cuts the pupil, which changes the focus's shape): not used in the fit.
VIGNETTED_BELOW = 0.3


@dataclass(frozen=True)
class FocalSurface:
    """Best-focus depth ``z_best,j(x, y) = c0 + c1·x + c2·y + c3·(x² + y²)`` (mm) per lenslet.

    coefficients: (J, 4) float64 [c0 (mm), c1, c2 (mm/mm), c3 (1/mm)].
    rms_mm: (J,) RMS residual of the fit (mm) on the stacks it kept.
    """

    coefficients: np.ndarray
    rms_mm: np.ndarray

    def __post_init__(self) -> None:
        c = np.asarray(self.coefficients, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 4:
            raise ValueError(f"coefficients: shape {c.shape}, expected (J, 4)")
        if not np.all(np.isfinite(c)):
            raise ValueError("coefficients contain NaN or infinite values")
        rms = np.asarray(self.rms_mm, dtype=np.float64).reshape(-1)
        if rms.shape != (c.shape[0],):
            raise ValueError(f"rms_mm: shape {rms.shape}, expected ({c.shape[0]},)")
        object.__setattr__(self, "coefficients", c)
        object.__setattr__(self, "rms_mm", rms)

    @property
    def n_lenslets(self) -> int:
        return self.coefficients.shape[0]

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The fields as arrays (the model file's ``focal_surface/`` group)."""
        return {"coefficients": self.coefficients, "rms_mm": self.rms_mm}

    def z_best(self, x_mm, y_mm, lenslet: int | None = None) -> np.ndarray:
        """Best-focus depth (mm) at field points (x, y) mm: (…, J), or (…) for one ``lenslet``."""
        x, y = np.broadcast_arrays(np.asarray(x_mm, float), np.asarray(y_mm, float))
        terms = np.stack([np.ones_like(x), x, y, x * x + y * y], axis=-1)  # (…, 4)
        c = self.coefficients if lenslet is None else self.coefficients[lenslet]
        return terms @ c.T

    def axes_mm(self) -> np.ndarray:
        """(J, 2) the lenslets' axes in object space (x, y) mm: the surfaces' vertices."""
        c = self.coefficients
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.stack([-c[:, 1], -c[:, 2]], axis=-1) / (2.0 * c[:, 3:4])


def effective_area(crops: np.ndarray) -> np.ndarray:
    """(N, J) effective area ``(Σp)² / Σp²`` of registered crops (N, J, h, w), in crop samples²
    (negative values clipped; ``inf`` for an empty crop). For a Gaussian focus of width σ it is
    4πσ², and under defocus d it grows as σ₀² + (NA·d)²: a parabola in depth."""
    p = np.clip(np.asarray(crops, dtype=np.float32), 0.0, None).reshape(crops.shape[0], crops.shape[1], -1)
    total = p.sum(axis=-1, dtype=np.float64)
    energy = np.einsum("njp,njp->nj", p, p, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(energy > 0, total**2 / np.maximum(energy, 1e-300), np.inf)


def stack_best_focus(area: np.ndarray, z_mm: np.ndarray, min_contrast: float = 0.0) -> np.ndarray:
    """Depth (mm) of the minimum of ``area`` (…, nz) along depths ``z_mm`` (nz,, increasing), by
    the parabola through the smallest node and its two neighbours; NaN where the smallest is
    the first or last node (the best focus lies outside the scanned depth) or is not finite, or
    where the two neighbours together exceed it by less than ``min_contrast`` of it (a depth of
    field longer than the depth steps: no measurable best focus)."""
    a = np.asarray(area, dtype=np.float64)
    z = np.asarray(z_mm, dtype=np.float64)
    nz = len(z)
    best = np.argmin(np.where(np.isfinite(a), a, np.inf), axis=-1)
    k = np.clip(best, 1, nz - 2)
    z0, z1, z2 = z[k - 1], z[k], z[k + 1]
    a0, a1, a2 = (np.take_along_axis(a, (k + d)[..., None], axis=-1)[..., 0] for d in (-1, 0, 1))
    # vertex of the parabola through (z0, a0), (z1, a1), (z2, a2)
    with np.errstate(divide="ignore", invalid="ignore"):
        d01, d12 = (a1 - a0) / (z1 - z0), (a2 - a1) / (z2 - z1)
        curvature = (d12 - d01) / (z2 - z0)
        vertex = np.clip((z0 + z1) / 2.0 - d01 / (2.0 * curvature), z0, z2)
    with np.errstate(divide="ignore", invalid="ignore"):
        contrast = (a0 + a2 - 2.0 * a1) / a1  # how much the focus grows one step either side
    ok = (best > 0) & (best < nz - 1) & np.isfinite(a0 + a1 + a2) & (curvature > 0) & (contrast >= min_contrast)
    return np.where(ok, vertex, np.nan)


def _robust_fit(
    terms: np.ndarray, values: np.ndarray, weights: np.ndarray, resolution_mm: float
) -> tuple[np.ndarray, float]:
    """Fit ``terms @ c ≈ values`` robustly: least median of squares over minimal subsets of the
    usable stacks (all of them when few, else a seeded sample of ``LMEDS_SUBSETS``; breakdown
    point ½, so vignetted or mis-focused stacks far from the lenslet's axis cannot pull the fit),
    then weighted least squares on the inliers (within ``INLIER_SIGMA`` robust standard
    deviations, the deviation no smaller than ``resolution_mm``, the best-focus estimates' own
    resolution). Returns (c, RMS residual of the inliers, mm)."""
    usable = np.nonzero(np.isfinite(values) & (weights > 0))[0]
    p = terms.shape[1]
    if len(usable) < p + 1:
        raise ValueError(
            f"only {len(usable)} axial stacks with a measurable best focus inside the scanned depth, "
            f"not vignetted: need ≥ {p + 1} per lenslet to fit a focal surface"
        )
    T, v, w = terms[usable], values[usable], weights[usable]
    if math.comb(len(usable), p) <= LMEDS_SUBSETS:
        subsets = np.array(list(itertools.combinations(range(len(usable)), p)))
    else:
        rng = np.random.default_rng(0)
        subsets = np.argsort(rng.random((LMEDS_SUBSETS, len(usable))), axis=1)[:, :p]
    A, b = T[subsets], v[subsets]  # (n, p, p), (n, p)
    solvable = np.abs(np.linalg.det(A)) > 1e-9 * np.abs(A).max() ** p
    if not solvable.any():
        raise ValueError(
            f"the {len(usable)} axial stacks with a measurable best focus span too little of the "
            f"field (a few nodes and their dithers, or one line) to fit a {p}-term focal surface"
        )
    c_all = np.linalg.solve(A[solvable], b[solvable][..., None])[..., 0]  # (n, p)
    median = np.median((v[None, :] - c_all @ T.T) ** 2, axis=1)
    best = c_all[np.argmin(median)]
    sigma = 1.4826 * (1.0 + 5.0 / (len(usable) - p)) * math.sqrt(float(median.min()))
    inliers = np.abs(v - T @ best) <= INLIER_SIGMA * max(sigma, resolution_mm)
    root = np.sqrt(w[inliers])
    c, *_ = np.linalg.lstsq(T[inliers] * root[:, None], v[inliers] * root, rcond=None)
    # a flat surface unless the paraboloid explains the inliers better by the Bayesian information
    # criterion (its 3 more parameters): noise in the stacks must not curve a flat field
    n = int(inliers.sum())
    flat = np.zeros_like(c)
    flat[0] = float(np.sum(w[inliers] * v[inliers]) / np.sum(w[inliers]))
    rss = [float(np.sum(w[inliers] * (v[inliers] - T[inliers] @ k) ** 2)) + 1e-30 for k in (flat, c)]
    if n * math.log(rss[0] / rss[1]) <= (p - 1) * math.log(n):
        c = flat
    rms = float(np.sqrt(np.mean((v[inliers] - T[inliers] @ c) ** 2)))
    return c, rms


def estimate_focal_surface(
    crops: np.ndarray | CropStore, grid_index: np.ndarray, axes: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> FocalSurface:
    """Fit every lenslet's best-focus surface (module docstring) to registered ``crops`` (N, J,
    h, w; in memory or on disk) at grid nodes ``grid_index`` (N, 3) as (ix, iy, iz) of ``axes`` (x, y, z mm)."""
    xs, ys, zs = (np.asarray(a, float) for a in axes)
    gi = np.asarray(grid_index)
    if len(zs) < 3:
        raise ValueError(f"a focal surface needs ≥ 3 scanned depths, the scan has {len(zs)}")
    J = crops.shape[1]
    area = np.full((len(ys), len(xs), J, len(zs)), np.inf)
    flux = np.zeros((len(ys), len(xs), J, len(zs)))
    for start, block in position_chunks(crops):
        g = gi[start : start + len(block)]
        area[g[:, 1], g[:, 0], :, g[:, 2]] = effective_area(block)
        flux[g[:, 1], g[:, 0], :, g[:, 2]] = np.clip(block, 0.0, None).sum(axis=(-2, -1), dtype=np.float64)
    brightest = flux.max(axis=-1) / np.maximum(flux.max(axis=(0, 1, 3)), 1e-300)  # (ny, nx, J), of the lenslet's
    z_best = stack_best_focus(area, zs, MIN_CONTRAST)  # (ny, nx, J)
    z_best[brightest < VIGNETTED_BELOW] = np.nan
    resolution = RESOLUTION_OF_STEP * float(np.median(np.diff(zs)))
    y, x = np.meshgrid(ys, xs, indexing="ij")
    terms = np.stack([np.ones(x.size), x.ravel(), y.ravel(), (x * x + y * y).ravel()], axis=-1)
    coefficients, rms = [], []
    for j in range(J):
        c, r = _robust_fit(terms, z_best[..., j].ravel(), brightest[..., j].ravel() ** 2, resolution)
        coefficients.append(c)
        rms.append(r)
    return FocalSurface(np.array(coefficients), np.array(rms))
