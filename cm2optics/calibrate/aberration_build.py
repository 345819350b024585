"""``cm2 lsv build --aberration-model``: node PSFs and basis material from the nodal-aberration model.

Steps (:mod:`cm2optics.emission.aberration_model` for the model): the design's pupils traced at every
node of the scan (all lenslets, the middle band); per lenslet the wavefront and aperture fitted
to them, and the placement (each PSF's offset and flux) fitted to the scan's own crops at the
nodes within :data:`PLACEMENT_FIELD_SHARE` of the scanned half-width; then the model's PSFs
rendered at every node (they replace the crops) and at ``dense`` seeded random positions over
the scanned volume (the basis is decomposed from those, :func:`~cm2optics.lsv.build.model_from_crops`).
:func:`aberration_psfs` is the ``node_psfs`` model that :func:`~cm2optics.lsv.build.build_model`
calls (the build itself traces nothing: the CLI passes it with the design).

The scan's positions are taken as the design's object coordinates (x, y from the central
lenslet's axis, z from the nominal focal plane, mm), as a synthetic scan's are. The crops must
be fine (an ePSF scan, even oversample ≥ 2): the render is integrated over one pixel.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cm2optics.emission.aberration_model import fit_lenslet_model, fit_placement, placement_features, trace_pupils
from cm2optics.lsv.crop_store import CropStore, crop_array
from cm2optics.lsv.preprocess import Geometry
from cm2optics.lsv.rotation import lenslet_axes

__all__ = ["PLACEMENT_FIELD_SHARE", "aberration_psfs", "pixel_samplers"]

Progress = Callable[[str, int, int], None]
#: Share of the scanned half-width within which the placement is fitted to the crops (the
#: cubic polynomials are poorest at the field's edge, where the foci leave the sensor).
PLACEMENT_FIELD_SHARE = 0.75


def _node_positions(grid_index: np.ndarray, axes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """(N, 3) source positions (mm) of the nodes ``grid_index`` (N, 3) of ``axes``."""
    gi = np.asarray(grid_index)
    return np.stack([np.asarray(axes[k], float)[gi[:, k]] for k in range(3)], -1)


def _fit_lenslets(
    design: Any,
    crops: np.ndarray | CropStore,
    positions: np.ndarray,
    fit_nodes: np.ndarray,
    axes_z_mm: np.ndarray,
    geometry: Geometry,
    oversample: int,
    pixel_um: float,
    seed: int,
    progress: Progress | None,
    phases: np.ndarray | None = None,
) -> tuple[dict[int, Any], dict[str, Any]]:
    """Per lenslet the model fitted to the nodes ``fit_nodes`` (indices into ``positions`` (N, 3)
    mm and ``crops``) alone: the design's pupils traced there, the placement fitted to their crops
    within :data:`PLACEMENT_FIELD_SHARE` of the scanned half-width; None for a lenslet with too few
    lit nodes. Returns the models and a record per lenslet. ``phases`` (N, J, 2): ``crops`` are
    whole-pixel windows (:func:`pixel_samplers`), the renders ``oversample`` times finer."""
    from cm2optics.emission.psf import EmissionModel
    from cm2optics.emission.source import calibration_pinhole

    if oversample < 2 or oversample % 2:
        raise ValueError(f"--aberration-model needs fine crops (an ePSF scan, even --oversample ≥ 2), not {oversample}")
    J = crops.shape[1]
    shape = crops.shape[2:] if phases is None else tuple(oversample * n for n in crops.shape[2:])
    sample_mm = pixel_um / oversample / 1000.0
    fit_nodes = np.asarray(fit_nodes)
    pupils = trace_pupils(
        EmissionModel(design, calibration_pinhole()), positions[fit_nodes], seed=seed, progress=progress
    )
    half_width = np.abs(positions[:, :2]).max(axis=0)
    near = np.all(np.abs(positions[:, :2]) <= PLACEMENT_FIELD_SHARE * half_width + 1e-9, axis=1)
    candidates = np.intersect1d(np.flatnonzero(near), fit_nodes)
    axes_mm = lenslet_axes(geometry, np.asarray(axes_z_mm, float))
    need = 2 * placement_features(np.zeros(3)).size
    models: dict[int, Any] = {}
    record: dict[str, Any] = {}
    for j in range(J):
        own = pupils.get(j, [])
        lit = [n for n in candidates if crops[(int(n), j)].sum() > 0]
        if len(own) < need or len(lit) < need:  # too few lit nodes to fit: the lenslet's PSFs stay zero
            models[j] = None
            record[j] = {"pupils": len(own), "placement_nodes": len(lit), "fitted": False}
            continue
        model = fit_lenslet_model(own, tuple(axes_mm[j]), shape, sample_mm, oversample)
        samplers = None if phases is None else pixel_samplers(phases[lit, j], crops.shape[2:], oversample)
        models[j] = fit_placement(model, [crops[(int(n), j)] for n in lit], positions[lit], samplers=samplers)
        record[j] = {"pupils": len(own), "placement_nodes": len(lit), "fitted": True}
        if progress is not None:
            progress("aberration model (lenslets fitted)", j + 1, J)
    return models, record


def pixel_samplers(
    phases: np.ndarray, window: tuple[int, ...], oversample: int
) -> list[Callable[[np.ndarray], np.ndarray]]:
    """Per node, the map of a fine PSF (h·S, w·S; chief ray on fine sample S·(h//2)) onto the
    node's whole-pixel window (h, w) whose pixel r lies at patch coordinate r − ``phases``
    (N, 2) (:func:`~cm2optics.lsv.epsf_estimate.pixel_windows`): the ePSF sampled at the pixel
    centres by the model's own Keys kernel (:func:`~cm2optics.lsv.epsf.sampling_matrix`)."""
    from cm2optics.lsv.epsf import sampling_matrix

    S = int(oversample)
    h, w = (int(n) for n in window)

    def sampler(eps: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        rows = sampling_matrix((np.arange(h) - eps[0]) * S, h * S)
        cols = sampling_matrix((np.arange(w) - eps[1]) * S, w * S)
        return lambda fine: rows @ np.asarray(fine, np.float64) @ cols.T

    return [sampler(np.asarray(eps, float)) for eps in np.asarray(phases, float)]


def _dense_positions(positions: np.ndarray, dense: int, seed: int) -> np.ndarray:
    """``dense`` seeded random positions (mm) uniform over the box of the nodes ``positions``."""
    rng = np.random.default_rng(seed)
    return rng.uniform(positions.min(axis=0), positions.max(axis=0), (dense, 3))


def _render(
    models: dict[int, Any],
    at: np.ndarray,
    shape: tuple[int, ...],
    memory_bytes: int,
    progress: Progress | None,
    what: str,
) -> np.ndarray | CropStore:
    """(len(at), J, h, w) the lenslet ``models``' PSFs at the positions ``at`` (mm); zero for a lenslet not fitted."""
    out = crop_array((len(at), len(models), *shape), memory_bytes)
    for j, model in models.items():
        if model is not None:
            for m in range(len(at)):
                out[m, j] = model.predict(at[m])
        if progress is not None:
            progress(what, j + 1, len(models))
    return out


def aberration_psfs(
    design: Any,
    crops: np.ndarray | CropStore,
    grid_index: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    geometry: Geometry,
    oversample: int,
    pixel_um: float,
    *,
    dense: int = 1000,
    seed: int = 0,
    held_out: np.ndarray | None = None,
    progress: Progress | None = None,
    memory_bytes: int,
    phases: np.ndarray | None = None,
) -> tuple[np.ndarray | CropStore, np.ndarray | CropStore, dict[str, Any]]:
    """The model's PSFs at the nodes (N, J, h, w) and at ``dense`` random positions (dense, J, h,
    w), on the fine grid of ``crops`` (``pixel_um`` / ``oversample`` per sample), and a record of
    the fit. ``design``: the :class:`~cm2optics.design.SystemDesign` whose pupils are traced.
    ``held_out``: node indices (H,) left out of the fit (neither their pupils nor their crops
    enter it); the node PSFs returned are then those of the held-out nodes alone (H, J, h, w), the
    model's predictions there (:func:`cm2optics.lsv.leave_out.leave_out_nodes`). ``phases`` (N, J,
    2): ``crops`` are whole-pixel windows of the frames (a scan without fine ePSFs,
    :func:`~cm2optics.lsv.epsf_estimate.pixel_windows`), each focus's chief ray at patch coordinate
    h//2 + its phase; the placement is fitted to them (:func:`pixel_samplers`) and the PSFs are
    rendered ``oversample`` times finer."""
    positions = _node_positions(grid_index, axes)
    N = len(positions)
    keep = np.ones(N, bool)
    if held_out is not None:
        keep[np.asarray(held_out)] = False
    models, lenslets = _fit_lenslets(
        design, crops, positions, np.flatnonzero(keep), axes[2], geometry, oversample, pixel_um, seed, progress, phases
    )
    shape = crops.shape[2:] if phases is None else tuple(oversample * n for n in crops.shape[2:])
    at_nodes = positions if held_out is None else positions[np.asarray(held_out)]
    node_psfs = _render(models, at_nodes, shape, memory_bytes, progress, "aberration model (node PSFs)")
    dense_psfs = _render(
        models, _dense_positions(positions, dense, seed), shape, memory_bytes, progress, "aberration model (basis PSFs)"
    )
    record: dict[str, Any] = {"dense_positions": dense, "seed": seed, "lenslets": lenslets}
    record["placement_from"] = "fine ePSF crops" if phases is None else "whole-pixel frames (each at its own phase)"
    if held_out is not None:
        record["held_out_nodes"] = int(N - keep.sum())
    return node_psfs, dense_psfs, record
