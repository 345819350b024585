"""``cm2 lsv build``: a PSF scan folder → an :class:`~cm2optics.lsv.model.LSVModel`.

Steps (the paper's, Supplement 1): dark level, exposure and background removed; the imaging
geometry fitted (foci, magnification against depth, axial shear from the on-axis stack); the
nine foci cropped around their chief rays (``patch`` px, 160 at full resolution) with the shear
undone; a truncated SVD into K basis PSFs and coefficients on the calibration grid; the model
scaled so that the in-focus image of a unit source on the axis sums to 1. The coefficients are
interpolated in x, y and z whenever the model is used (trilinearly, along each lenslet's chief
rays), onto whatever grid the volume has; ``default_grid`` (4.15 × 4.15 × 10 µm for a CM² V2:
one sensor pixel per voxel at the focal plane) spans the scanned volume.
"""

from __future__ import annotations

import hashlib
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

import cm2optics
from cm2optics.design import SystemDesign, default_design
from cm2optics.formats.scan import ScanError, ScanIndex, open_scan
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.crop_store import DEFAULT_MEMORY_BYTES, CropStore, position_chunks
from cm2optics.lsv.decompose import (
    Decomposition,
    basis_gram,
    decompose,
    decompose_per_lenslet,
    lenslet_blocks,
    numerical_rank,
    products,
    project,
    trim_window,
)
from cm2optics.lsv.epsf_validate import turn_check
from cm2optics.lsv.focal_surface import FocalSurface, estimate_focal_surface
from cm2optics.lsv.model import LSVModel
from cm2optics.lsv.preprocess import Geometry, GeometryFit, estimate_geometry, extract_crops
from cm2optics.lsv.rotation import AzimuthTurn

__all__ = [
    "BuildResult",
    "build_model",
    "default_patch_px",
    "keep_node_flux",
    "model_from_crops",
    "node_nmse",
    "scan_fingerprint",
]

Progress = Callable[[str, int, int], None]
#: A model of the node PSFs (``build_model``'s ``node_psfs``): (node PSFs, basis PSFs, record).
NodePSFs = Callable[..., tuple[Any, Any, dict[str, Any]]]
#: Crop side at full resolution (the paper's 160 × 160 px per focus).
FULL_RESOLUTION_PATCH_PX = 160
#: Stage/sensor cross-coupling that moves no point of the scanned field by 0.1 px is set to zero.
ALIGNMENT_SNAP_PX = 0.1


@dataclass(frozen=True)
class BuildResult:
    """model; decomposition (all singular values, NMSE against K; a streamed SVD's: those of the
    terms it computed); geometry fit; crops (N, J, h, w) as fitted (in memory, or on disk: a
    :class:`~cm2optics.lsv.crop_store.CropStore`); grid_index (N, 3) of every crop as (ix, iy, iz); seconds per step."""

    model: LSVModel
    decomposition: Decomposition
    fit: GeometryFit
    crops: np.ndarray | CropStore
    grid_index: np.ndarray
    seconds: dict[str, float]

    def summary(self) -> dict[str, Any]:
        """The numbers ``cm2 lsv build --json`` prints."""
        model, dec = self.model, self.decomposition
        ks = sorted({k for k in (1, 2, 4, 8, 16, 32, 64, 128, 256, model.rank) if k < len(dec.nmse)})
        return {
            "rank": model.rank,
            **_calibration_error(model, dec),
            "numerical_rank": numerical_rank(dec.singular_values),
            "nmse_vs_rank": {str(k): float(dec.nmse[k]) for k in ks},
            "nmse_per_psf_vs_rank": {str(k): float(dec.nmse_per_psf[k]) for k in ks},
            "n_positions": int(len(self.crops)),
            "calibration_grid": {
                "x_mm": model.grid_x_mm.tolist(),
                "y_mm": model.grid_y_mm.tolist(),
                "z_mm": model.grid_z_mm.tolist(),
            },
            "patch_px": list(model.patch_shape),
            "lenslets": [model.geometry.rows, model.geometry.cols],
            "default_grid": model.default_grid.to_dict(),
            "geometry": model.provenance.get("geometry", {}),
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
        }


def default_patch_px(binning: int) -> int:
    """Crop side (even) for images binned ``binning``×: 160 px at full resolution."""
    return max(8, 2 * int(round(FULL_RESOLUTION_PATCH_PX / binning / 2)))


def scan_fingerprint(index: ScanIndex) -> str:
    """SHA-256 of positions.csv, scan.yaml and the names and sizes of the images."""
    digest = hashlib.sha256()
    for name in ("positions.csv", "scan.yaml"):
        digest.update((index.folder / name).read_bytes())
    for name in sorted({f.partition("#")[0] for f in index.files}):
        digest.update(f"{name}:{(index.folder / name).stat().st_size};".encode())
    return digest.hexdigest()


def _layout(index: ScanIndex, design: SystemDesign | None) -> tuple[int, int]:
    value = index.meta.extra.get("lenslets")
    if value is not None:
        try:
            rows, cols = (int(v) for v in value)
        except (TypeError, ValueError):
            raise ScanError(f"{index.folder / 'scan.yaml'}: lenslets = {value!r}: must be [rows, cols]") from None
        if rows < 1 or cols < 1:
            raise ScanError(f"{index.folder / 'scan.yaml'}: lenslets = {value!r}: must be positive")
        return rows, cols
    if design is None:
        raise ScanError(f"{index.folder / 'scan.yaml'}: no `lenslets: [rows, cols]` and no design to take them from")
    return design.mla.rows, design.mla.cols


def _design_fallback(design: SystemDesign | None, pixel_um: float) -> Callable[[float], np.ndarray] | None:
    if design is None:
        return None
    from cm2optics.lsv.toy import AnalyticCM2

    analytic = AnalyticCM2.from_design(design)

    def fallback(z_mm: float) -> np.ndarray:
        m = float(analytic.magnification_at(z_mm)) * 1000.0 / pixel_um
        return np.array([[0.0, -m], [-m, 0.0]])  # row ← y, col ← x, inverted

    return fallback


def _snap_alignment(geometry: Geometry, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> tuple[Geometry, str]:
    """Zero the stage/sensor cross terms of A when they move a point by < 0.01 px over the field."""
    A = geometry.A(zs)
    half = np.array([max(abs(xs[0]), abs(xs[-1])), max(abs(ys[0]), abs(ys[-1]))])
    diag = np.max(np.abs(A[:, 0, 0]) * half[0] + np.abs(A[:, 1, 1]) * half[1])
    anti = np.max(np.abs(A[:, 0, 1]) * half[1] + np.abs(A[:, 1, 0]) * half[0])
    poly = geometry.A_poly.copy()
    if diag < ALIGNMENT_SNAP_PX:
        poly[:, 0, 0] = 0.0
        poly[:, 1, 1] = 0.0
        return replace(geometry, A_poly=poly), "aligned: rows follow y, columns follow x"
    if anti < ALIGNMENT_SNAP_PX:
        poly[:, 0, 1] = 0.0
        poly[:, 1, 0] = 0.0
        return replace(geometry, A_poly=poly), "aligned: rows follow x, columns follow y"
    angle = math.degrees(math.atan2(min(diag, anti), max(diag, anti)))
    return (
        geometry,
        f"stage and sensor axes are not aligned (cross-coupling up to {min(diag, anti):.2f} px, ≈ {angle:.3f}°): modelled as such",
    )


def _check_build_options(
    oversample: int,
    rank: int,
    lateral_um: float | None,
    axial_um: float | None,
    design: SystemDesign | None,
    refine: int = 1,
) -> float:
    """Check build_model's options; returns the axial voxel pitch (µm), defaulted from the design."""
    if not (isinstance(oversample, int) and 1 <= oversample <= 16):
        raise ValueError(f"oversample = {oversample!r}: must be an integer within 1–16")
    if not (isinstance(refine, int) and 1 <= refine <= 64):
        raise ValueError(f"refine = {refine!r}: must be an integer within 1–64")
    if rank < 1:
        raise ValueError(f"rank = {rank}: must be ≥ 1")
    if axial_um is None:
        axial_um = (design or default_design()).volume.axial_step_um
    if axial_um <= 0 or (lateral_um is not None and lateral_um <= 0):
        raise ValueError("voxel sizes must be > 0 µm")
    return axial_um


def _phase_check(index: ScanIndex, geometry: Geometry, oversample: int) -> tuple[int, dict[str, Any]]:
    """The oversample S to build with (1 if every focus shares one sub-pixel phase, with a warning) and the ePSF record."""
    epsf_info: dict[str, Any] = {"oversample": oversample}
    if oversample > 1:
        from cm2optics.lsv.epsf_estimate import phase_coverage

        coverage = phase_coverage(geometry, index.positions_mm, oversample)
        epsf_info["phase_coverage"] = coverage
        if coverage["single_phase"]:
            message = (
                f"oversample = {oversample}: every position of the scan puts the foci at the same sub-pixel phase, "
                "so the frames cannot tell a finer grid apart: built with whole pixels (oversample 1) instead"
            )
            warnings.warn(message, stacklevel=3)  # at build_model's caller
            epsf_info.update({"oversample": 1, "requested_oversample": oversample, "fallback": message})
            oversample = 1
    return oversample, epsf_info


def _scan_crops(
    index: ScanIndex,
    geometry: Geometry,
    patch: int,
    oversample: int,
    epsf_info: dict[str, Any],
    estimate_options: dict[str, Any] | None,
    progress: Progress | None,
    memory_bytes: int,
) -> np.ndarray | CropStore:
    """The registered crops (N, J, patch·S, patch·S; image px / S): from epsf.h5 if S > 1 and
    present, estimated per node from the frames of each node and its sub-pixel dithers if S > 1
    and the scan has dithers, else the frames (N, J, patch, patch; whole pixels: an ePSF basis is
    then estimated jointly with the coefficients, in :func:`model_from_crops`); the epsf.h5 crops
    and the frames on disk if they take more than ``memory_bytes``."""
    if oversample > 1 and (index.folder / "epsf.h5").is_file():
        from cm2optics.lsv.epsf import epsf_crops

        epsf_info["source"] = "synthetic ePSFs (epsf.h5)"
        return epsf_crops(index, geometry, (patch, patch), oversample, progress=progress, memory_bytes=memory_bytes)
    if oversample > 1:
        from cm2optics.lsv.epsf_estimate import has_dithers, local_epsf_crops, pixel_windows

        x, y, z = index.positions_mm.T
        depth = index.grid_index()[:, 2]
        if has_dithers(geometry.focus(x, y, z), depth):
            windows, foci = pixel_windows(index, geometry, (patch, patch), progress=progress)
            crops, epsf_info["estimate"] = local_epsf_crops(
                windows, foci, depth, oversample, progress=progress, **(estimate_options or {})
            )
            epsf_info["source"] = "estimated from the whole-pixel frames of each node and its sub-pixel dithers"
            alone = epsf_info["estimate"]["nodes_of_one_phase"]
            if alone:
                message = (
                    f"oversample = {oversample}: {alone} of {len(index)} nodes have no sub-pixel dither (no frame "
                    f"at another phase within {epsf_info['estimate']['dither_px']:g} px at their depth), so their "
                    "ePSFs rest on one phase, filled in by the smoothness prior: dither every node (e.g. 2 × 2 by ½ px)"
                )
                warnings.warn(message, stacklevel=3)  # at build_model's caller
                epsf_info["warning"] = message
            return crops
        epsf_info["source"] = "estimated from the whole-pixel frames"
    return extract_crops(index, geometry, (patch, patch), progress=progress, memory_bytes=memory_bytes)


def _build_provenance(
    index: ScanIndex, fit: GeometryFit, alignment: str, options: dict[str, Any], epsf_info: dict[str, Any]
) -> dict[str, Any]:
    """The model's provenance from a scan: the scan, the build options, the ePSF record and the geometry fit (px)."""
    xs, ys, zs = index.grid_axes_mm()
    x0, y0 = fit.axis_position_mm
    return {
        "scan": {
            "folder": str(index.folder.resolve()),
            "fingerprint": scan_fingerprint(index),
            "n_positions": len(index),
            "grid_shape_xyz": [len(xs), len(ys), len(zs)],
            "pixel_um": index.meta.pixel_um,
            "binning": index.meta.binning,
            "meta": index.meta.to_dict(),
        },
        "options": options,
        "epsf": epsf_info,
        "geometry": {
            "axis_position_mm": [x0, y0],
            "lattice_pitch_px": round(fit.pitch_px, 3),
            "shear_rms_residual_px": round(fit.shear_residual_px, 4),
            "max_translation_residual_px": float(np.nanmax(fit.residual_px))
            if np.any(np.isfinite(fit.residual_px))
            else None,
            "dark_images": int(np.sum(~fit.bright)),
            "alignment": alignment,
            "notes": list(fit.notes),
        },
    }


def _open_for_build(
    scan_dir: str | Path, design: SystemDesign | None, patch_px: int | None
) -> tuple[ScanIndex, int, int, int]:
    """Open the scan; returns it, its lenslet layout (rows, cols) and the crop side (image px), checked."""
    index = open_scan(scan_dir, sensor_pixel_um=design.sensor.pixel_um if design is not None else None)
    rows, cols = _layout(index, design)
    patch = patch_px if patch_px is not None else default_patch_px(index.meta.binning)
    if patch < 4:
        raise ValueError(f"patch_px = {patch}: must be ≥ 4")
    return index, rows, cols, patch


def _fit_geometry(
    index: ScanIndex, rows: int, cols: int, design: SystemDesign | None, degree: int, progress: Progress | None
) -> tuple[GeometryFit, Geometry, str]:
    """The scan's geometry fit, its geometry with negligible stage/sensor cross terms zeroed, and that note."""
    fit = estimate_geometry(
        index, rows, cols, fallback_A=_design_fallback(design, index.meta.pixel_um), degree=degree, progress=progress
    )
    xs, ys, zs = index.grid_axes_mm()
    geometry, alignment = _snap_alignment(fit.geometry, xs, ys, zs)
    return fit, geometry, alignment


def _focal_surface(
    crops: np.ndarray, grid_index: np.ndarray, axes: tuple[np.ndarray, np.ndarray, np.ndarray], refine: int
) -> tuple[FocalSurface | None, dict[str, Any]]:
    """Each lenslet's best-focus surface estimated from the registered crops, and its record; a
    scan that cannot fix one (fewer than 3 depths, or too few stacks whose best focus lies inside
    the scanned depth) gets a warning and plain interpolation, said so in the record."""
    try:
        surface = estimate_focal_surface(crops, grid_index, axes)
    except ValueError as error:
        message = f"no focal surface ({error}): the coefficients are interpolated at fixed depth"
        warnings.warn(message, stacklevel=3)  # at build_model's caller
        return None, {"fallback": message}
    return surface, {
        "refine": refine,
        "coefficients": surface.coefficients.round(6).tolist(),
        "rms_residual_mm": surface.rms_mm.round(5).tolist(),
        "lenslet_axes_mm": surface.axes_mm().round(4).tolist(),
    }


#: The turn (the warp) is kept where it predicts held-out nodes from their lateral neighbours at
#: least this much better (relative NMSE) than blending them at a fixed orientation (without it).
TURN_GAIN = 0.1


def _choose_interpolation(
    model: LSVModel,
    crops: np.ndarray,
    grid_index: np.ndarray,
    rotate: bool | None,
    warp: bool | None,
    refine: int,
    crop_sampling: int,
) -> tuple[LSVModel, dict[str, Any]]:
    """The model with its lateral neighbours turned with the azimuth (:mod:`cm2optics.lsv.rotation`)
    if ``rotate`` is True, and its neighbours blended by displacement interpolation
    (:mod:`cm2optics.lsv.warp`) if ``warp`` is True; each (None) if the scan itself says so:
    held-out nodes predicted from their lateral neighbours better by :data:`TURN_GAIN`
    (:func:`~cm2optics.lsv.epsf_validate.turn_check`; the warp judged with the turn as chosen);
    False: never. Returns it and the record for the provenance. ``crop_sampling``: samples per
    pixel of ``crops``. A geometry whose lenslet axes cannot be found keeps the fixed
    orientation, with a warning."""
    record: dict[str, Any] = {}
    turn = None
    if rotate is not False:
        try:
            turn = AzimuthTurn.of_model(model)
        except ValueError as error:
            message = f"no turn with the azimuth ({error}): neighbours are blended at a fixed orientation"
            warnings.warn(message, stacklevel=3)  # at build_model's caller
            record["fallback"] = message
            rotate = False
    if turn is not None:
        # the pivots in the crops' frame: c samples per pixel (the basis may be trimmed, and an
        # estimated ePSF basis is finer than its whole-pixel crops); the chief ray at pixel h // 2 in both
        c = crop_sampling
        crop_px = np.array(crops.shape[-2:]) // c
        pivots = c * (turn.pivots / model.oversample - np.array(model.patch_shape) // 2 + crop_px // 2)
        turn = replace(turn, pivots=pivots)
        record["lenslet_axes_mm"] = turn.lens_axes.round(4).tolist()
    if rotate is None or warp is None:
        lateral = _lateral_nodes(model)
        check = turn_check(
            crops, grid_index, model.axes, model.focal_surface, turn, warp=warp is not False, lateral=lateral
        )
        if lateral is not None:
            check["dithers_skipped"] = "each node predicted from the next nodes beyond its sub-pixel dithers"
        record["leave_one_out"] = check
        if rotate is None:
            rotate = _better(check.get("nmse_turned"), check["nmse_fixed_orientation"])
        if warp is None:
            plain, warped = ("turned", "turned_warped") if rotate else ("fixed_orientation", "warped")
            warp = _better(check.get(f"nmse_{warped}"), check[f"nmse_{plain}"])
    record["turned"], record["warped"] = bool(rotate), bool(warp)
    if not (rotate or warp):
        return model, record
    return replace(model, refine=refine, rotate_aberrations=bool(rotate), warp_shapes=bool(warp)), record


def _lateral_nodes(model: LSVModel) -> tuple[np.ndarray, np.ndarray] | None:
    """The indices of the x and y grid values that are nodes, not sub-pixel dithers (values whose
    foci lie within :data:`~cm2optics.lsv.epsf_estimate.DITHER_PX` of the previous node's); None
    when every value is a node."""
    from cm2optics.lsv.epsf_estimate import DITHER_PX
    from cm2optics.lsv.epsf_validate import undithered_axis

    xs, ys, zs = model.axes
    step_mm = 1e-3
    z = np.full(2, float(np.median(zs)))
    focus = model.geometry.focus(np.array([0.0, step_mm]), np.zeros(2), z)  # (2, J, 2) px
    px_per_mm = float(np.abs(focus[1] - focus[0]).max() / step_mm)
    nodes = (undithered_axis(xs, px_per_mm, DITHER_PX), undithered_axis(ys, px_per_mm, DITHER_PX))
    return None if len(nodes[0]) == len(xs) and len(nodes[1]) == len(ys) else nodes


def _better(candidate: float | None, reference: float | None) -> bool:
    """True if ``candidate`` NMSE is below ``reference`` by at least :data:`TURN_GAIN`."""
    return candidate is not None and reference is not None and candidate < (1.0 - TURN_GAIN) * reference


def _warn_rank(rank: int, positions: str, model_rank: int) -> None:
    """Warn (at build_model's caller) that the ``positions`` (e.g. "the scan's 147 positions") allow fewer basis PSFs than asked."""
    warnings.warn(
        f"--rank {rank}: {positions} allow only {model_rank} basis PSFs; the model has rank {model_rank}",
        stacklevel=3,
    )


def build_model(
    scan_dir: str | Path,
    *,
    rank: int = 64,
    patch_px: int | None = None,
    lateral_um: float | None = None,
    axial_um: float | None = None,
    design: SystemDesign | None = None,
    degree: int = 2,
    trim: float | None = 1e-6,
    progress: Progress | None = None,
    oversample: int = 1,
    estimate_options: dict[str, Any] | None = None,
    focal_surface: bool = True,
    refine: int = 2,
    rotate: bool | None = None,
    warp: bool | None = None,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
    node_psfs: NodePSFs | None = None,
    per_lenslet_basis: bool = False,
    scan_node_coefficients: bool = False,
) -> BuildResult:
    """Build an LSV model from the scan folder ``scan_dir`` (see the module docstring).

    rank: K, the number of basis PSFs (capped by the number of positions).
    patch_px: crop side per focus in image pixels (default: 160 at full resolution, scaled by
        the scan's binning).
    lateral_um, axial_um: voxel pitch of the default reconstruction grid, µm (lateral default:
        one sensor pixel per voxel at the focal plane; axial default: ``volume.axial_step_um`` of
        ``design``, or of the cm2-v2 preset without one).
    design: the design to take the lenslet layout from (unless scan.yaml says ``lenslets``) and
        to fall back on for the magnification if the scan's positions cannot fix it.
    trim: share of the PSF energy the basis may lose when its crops' dark margins are cut
        (None: keep the full crops).
    oversample: S > 1 builds an effective-PSF basis on a grid S times finer than the pixels
        (:mod:`cm2optics.lsv.epsf`): from the scan's ``epsf.h5`` if it has one (synthetic scans),
        else estimated from the whole-pixel frames (:mod:`cm2optics.lsv.epsf_estimate`); a scan
        whose foci all share one sub-pixel phase falls back to whole pixels, with a warning.
    estimate_options: options of the estimate from the frames: of
        :func:`~cm2optics.lsv.epsf_estimate.local_epsf_crops` for a scan with sub-pixel dithers
        (``within_px``, ``smoothness``, ``cg_steps``), else of
        :func:`~cm2optics.lsv.epsf_estimate.estimate_epsf_basis` (``iterations``, ``cg_steps``,
        ``smoothness``).
    focal_surface: interpolate between lateral nodes at equal defocus from each lenslet's
        best-focus surface, estimated from the scan (:mod:`cm2optics.lsv.focal_surface`), on the
        grid refined ``refine`` times laterally; False: at fixed depth.
    rotate: turn each lateral neighbour's PSF to the source's azimuth about the lenslet's axis
        before the blend (:mod:`cm2optics.lsv.rotation`; on the grid refined ``refine`` times);
        None: if held-out nodes of the scan say so (:func:`_choose_interpolation`); False: never.
    warp: blend neighbouring PSFs by displacement interpolation, each warped to the interpolated
        focus shape (:mod:`cm2optics.lsv.warp`; on the refined grid); None: if held-out nodes of
        the scan say so; False: never.
    memory_bytes: crops larger than this are kept in a temporary file and read in chunks of
        positions (:mod:`cm2optics.lsv.crop_store`), their SVD randomized and streamed
        (:func:`~cm2optics.lsv.decompose.streamed_decompose`); smaller ones are held in memory
        and decomposed exactly.
    node_psfs: a model of the node PSFs that replaces the crops (e.g. the nodal-aberration model of
        :mod:`cm2optics.calibrate.aberration_build`, which the CLI passes with the design): called
        as ``node_psfs(crops, grid_index, axes_mm, geometry, oversample, pixel_um, progress=,
        memory_bytes=)`` on the scan's fine crops (a scan without them: on its whole-pixel windows
        (:func:`~cm2optics.lsv.epsf_estimate.pixel_windows`) with ``phases=`` (N, J, 2), each focus's
        sub-pixel phase), it returns the fine PSFs at the nodes, the PSFs the basis is decomposed
        from and a record for the provenance; None: the crops themselves.
    per_lenslet_basis: each lenslet its own basis of ``rank`` single-lenslet PSFs instead of one
        basis of ``rank`` J-lenslet focus arrays (J·rank terms in all, each lenslet's forward
        using its own ``rank``: the forward's cost is the same, the model's rank J times).
    scan_node_coefficients: with ``node_psfs``, only the basis comes from its PSFs; the node
        coefficients (and the focal surface, the turn/warp choice, the node fluxes) from the
        scan's own fine crops, as without it (needs fine crops: a synthetic scan's epsf.h5)."""
    axial_um = _check_build_options(oversample, rank, lateral_um, axial_um, design, refine)
    seconds: dict[str, float] = {}
    start = time.perf_counter()
    index, rows, cols, patch = _open_for_build(scan_dir, design, patch_px)
    seconds["open"] = time.perf_counter() - start

    start = time.perf_counter()
    fit, geometry, alignment = _fit_geometry(index, rows, cols, design, degree, progress)
    seconds["geometry"] = time.perf_counter() - start

    start = time.perf_counter()
    oversample, epsf_info = _phase_check(index, geometry, oversample)
    crops = _scan_crops(index, geometry, patch, oversample, epsf_info, estimate_options, progress, memory_bytes)
    seconds["crops"] = time.perf_counter() - start

    gi = index.grid_index()
    basis_psfs, node_model = None, None
    if node_psfs is not None:
        start = time.perf_counter()
        if oversample < 2:
            raise ScanError(
                "a model of the node PSFs renders an ePSF basis: it needs --oversample ≥ 2 and foci at several "
                "sub-pixel phases"
            )
        if scan_node_coefficients and crops.shape[-1] == patch:
            raise ScanError(
                "node coefficients from the scan need its fine crops (epsf.h5): a scan of whole-pixel frames "
                "takes them from the node model"
            )
        scan_crops, frame_phases = crops, {}
        if crops.shape[-1] == patch:  # whole-pixel frames only: the node model is placed on them, phase by phase
            from cm2optics.lsv.epsf_estimate import pixel_windows

            scan_crops, foci = pixel_windows(index, geometry, (patch, patch), progress=progress)
            frame_phases["phases"] = foci - np.floor(foci)
        crops, basis_psfs, node_model = node_psfs(
            scan_crops,
            gi,
            index.grid_axes_mm(),
            geometry,
            oversample,
            index.meta.pixel_um,
            progress=progress,
            memory_bytes=memory_bytes,
            **frame_phases,
        )
        if scan_node_coefficients:
            crops = scan_crops  # the basis from the model's PSFs, the nodes from the scan's own crops
            node_model["node_coefficients"] = "the scan's own crops projected on the basis"
        seconds["node_psfs"] = time.perf_counter() - start

    start = time.perf_counter()
    surface, surface_info = _focal_surface(crops, gi, index.grid_axes_mm(), refine) if focal_surface else (None, None)
    options = dict(rank=rank, patch_px=patch, trim=trim, lateral_um=lateral_um, axial_um=axial_um, degree=degree)
    options |= {"design": design.name if design is not None else None, "oversample": oversample}
    options |= {"focal_surface": surface is not None, "refine": refine if surface is not None else 1}
    options |= {"rotate": {None: "data decides", True: "on", False: "off"}[rotate]}
    options |= {"warp": {None: "data decides", True: "on", False: "off"}[warp]}
    options |= {"svd": "exact (crops in memory)" if isinstance(crops, np.ndarray) else "streamed (crops on disk)"}
    if per_lenslet_basis:
        options |= {"svd": "exact, per lenslet", "basis": "per lenslet"}
    provenance = _build_provenance(index, fit, alignment, options, epsf_info) | {"focal_surface": surface_info}
    if node_model is not None:
        provenance["node_psfs"] = node_model
    fine = crops.shape[-1] != patch  # fine crops (synthetic or dithered), else an ePSF basis fitted to the frames
    model, decomposition = model_from_crops(
        crops,
        gi,
        index.grid_axes_mm(),
        geometry,
        rank=rank,
        sensor_shape=index.shape,
        pixel_um=index.meta.pixel_um,
        lateral_um=lateral_um,
        axial_um=axial_um,
        trim=trim,
        provenance=provenance,
        oversample=oversample,
        frames=None if oversample == 1 or fine else (index, estimate_options),
        focal_surface=surface,
        refine=refine,
        progress=progress,
        basis_psfs=basis_psfs,
        per_lenslet=per_lenslet_basis,
    )
    if node_model is not None:  # the model's error at the nodes against the scan's own crops (fine ones only)
        scan_error = (
            None if scan_crops.shape[-1] == patch else node_nmse(decomposition, _trim_like(scan_crops, decomposition))
        )
        model.provenance["node_psfs"]["nmse_nodes_vs_scan"] = scan_error[0] if scan_error else None
    seconds["svd"] = time.perf_counter() - start
    start = time.perf_counter()
    if (rotate is False and warp is False) or refine < 2:
        turn_info = {"turned": False, "warped": False}
        if refine < 2 and not (rotate is False and warp is False):
            turn_info["fallback"] = "refine 1: a turn or warp needs the refined grid"
    else:
        model, turn_info = _choose_interpolation(model, crops, gi, rotate, warp, refine, oversample if fine else 1)
    model.provenance["rotation"] = turn_info
    seconds["rotation"] = time.perf_counter() - start
    if model.rank < rank * (model.n_lenslets if per_lenslet_basis else 1):
        source = f"the scan's {len(index)} positions"
        if basis_psfs is not None:
            source = f"the {len(basis_psfs)} positions the basis is decomposed from"
        _warn_rank(rank, source, model.rank)
    model.provenance["seconds"] = {k: round(v, 3) for k, v in seconds.items()}
    return BuildResult(model, decomposition, replace(fit, geometry=geometry), crops, gi, seconds)


def _calibration_error(model: LSVModel, dec: Decomposition) -> dict[str, Any]:
    """The saved model's error at its nodes (``nmse_calibration``, ``…_per_psf``; after
    :func:`keep_node_flux`) beside the truncated SVD's (``…_svd``), and which one the first is."""
    svd = model.provenance.get("svd", {})
    before = {
        "nmse_calibration_svd": float(dec.nmse[model.rank]),
        "nmse_calibration_per_psf_svd": float(dec.nmse_per_psf[model.rank]),
    }
    if svd.get("nmse_model") is None:  # an estimated ePSF basis: no model error on the whole-pixel crops
        return {
            "nmse_calibration": before["nmse_calibration_svd"],
            "nmse_calibration_per_psf": before["nmse_calibration_per_psf_svd"],
            "nmse_calibration_of": "the whole-pixel SVD (the estimated ePSF basis is finer than the frames)",
        } | before
    return {
        "nmse_calibration": svd["nmse_model"],
        "nmse_calibration_per_psf": svd["nmse_per_psf_model"],
        "nmse_calibration_of": "the saved model (node fluxes kept)",
    } | before


#: Positions converted to float64 at a time where crops are summed exactly.
FLOAT64_ROWS = 32


def node_nmse(decomposition: Decomposition, crops: np.ndarray | CropStore) -> tuple[float, float] | None:
    """The error of ``coefficients · basis`` at the nodes against ``crops`` (N, J, h, w) on the
    basis's grid: ``‖X − X̂‖²_F / ‖X‖²_F`` and the mean over non-dark nodes of ``‖x_n − x̂_n‖² /
    ‖x_n‖²`` (as :mod:`cm2optics.lsv.decompose` defines them); None if the grids differ (an
    estimated ePSF basis). Float64 sums over a few positions at a time: ``‖x‖² − 2 c·(B x) + cᵀ G c``."""
    if decomposition.basis.shape[1:] != crops.shape[1:]:
        return None
    basis = decomposition.basis
    blocks = lenslet_blocks(basis)
    norms = np.zeros(len(crops))
    projections = np.zeros((len(crops), len(basis)))
    gram = basis_gram(basis, blocks)
    for first, block in position_chunks(crops):
        for start in range(0, len(block), FLOAT64_ROWS):
            x = block[start : start + FLOAT64_ROWS]
            rows = slice(first + start, first + start + len(x))
            flat = x.reshape(len(x), -1)
            norms[rows] = np.einsum("np,np->n", flat, flat, dtype=np.float64)
            projections[rows] = products(x, basis, blocks)
    c = decomposition.coefficients.astype(np.float64)
    errors = np.clip(
        norms - 2.0 * np.einsum("nk,nk->n", c, projections) + np.einsum("nk,kl,nl->n", c, gram, c), 0, None
    )
    valid = norms > 1e-12 * max(float(norms.max()), 1e-300)
    total = float(norms.sum())
    per_psf = float(np.mean(errors[valid] / norms[valid])) if valid.any() else 0.0
    return (float(errors.sum()) / total if total > 0 else 0.0), per_psf


def _trim_like(crops: np.ndarray | CropStore, decomposition: Decomposition) -> np.ndarray | CropStore:
    """``crops`` cut to the basis's window: centred on the chief ray's sample (h // 2), as
    :func:`_trim` cuts fine crops (whole pixels about it)."""
    (h, w), (hb, wb) = crops.shape[2:], decomposition.basis.shape[2:]
    rows, cols = slice(h // 2 - hb // 2, h // 2 - hb // 2 + hb), slice(w // 2 - wb // 2, w // 2 - wb // 2 + wb)
    return crops[:, :, rows, cols] if isinstance(crops, np.ndarray) else crops.windowed(rows, cols)


def _whole_pixels(window: slice, n: int, S: int) -> slice:
    """``window`` (centred on n//2) widened so that its half-width is a whole number of pixels."""
    centre = n // 2
    half = max(centre - window.start, window.stop - centre)
    half = min(int(math.ceil(half / S)) * S, centre, n - centre)
    half -= half % S
    return slice(centre - half, centre + half)


def keep_node_flux(decomposition: Decomposition, crops: np.ndarray | CropStore) -> tuple[Decomposition, np.ndarray]:
    """Each node's coefficients moved so that its modelled flux equals its crop's, changing its
    shape least: the least-squares fit under the flux constraint, ``c + λ G⁻¹b`` (G the basis's
    Gram matrix, b each basis PSF's flux, λ from the constraint). A rank-K truncation is optimal in
    the squared error, which faint wide halos hardly enter, so it drops their flux (on the 9×9×11
    ePSF scan the K = 64 model's node fluxes were 0.5–1.2 of their crops'). ``crops`` (N, J, h, w)
    on the basis's grid or a whole-pixel one (an estimated ePSF basis): flux = sum × the sample
    area. Returns the decomposition and each node's flux ratio before (N,)."""
    basis = decomposition.basis
    area = (crops.shape[-2] * crops.shape[-1]) / (decomposition.basis.shape[-2] * decomposition.basis.shape[-1])
    b = basis.reshape(len(basis), -1).sum(axis=1, dtype=np.float64) * area  # (K,) flux of each basis PSF
    target = np.concatenate([block.sum(axis=(1, 2, 3), dtype=np.float64) for _, block in position_chunks(crops)])
    c = decomposition.coefficients.astype(np.float64)
    modelled = c @ b
    direction = np.linalg.lstsq(basis_gram(basis, lenslet_blocks(basis)), b, rcond=None)[0]  # G⁻¹ b
    denominator = float(b @ direction)
    if not denominator > 0:
        return decomposition, np.ones(len(c))
    c += ((target - modelled) / denominator)[:, None] * direction[None]
    before = modelled / np.where(np.abs(target) > 0, target, 1.0)
    return replace(decomposition, coefficients=c.astype(np.float32)), before


def _trim(
    decomposition: Decomposition, crops: np.ndarray | CropStore, trim: float, S: int
) -> tuple[Decomposition, np.ndarray | CropStore]:
    """Cut the basis's and crops' dark margins holding less than ``trim`` of the energy (whole pixels if S > 1)."""
    rows, cols = trim_window(decomposition.basis, decomposition.singular_values, trim)
    if S > 1 and crops.shape[-1] % S == 0:  # keep whole pixels, the chief ray on S·(h//2)
        rows, cols = (_whole_pixels(sl, n, S) for sl, n in zip((rows, cols), crops.shape[2:], strict=True))
    decomposition = replace(decomposition, basis=np.ascontiguousarray(decomposition.basis[:, :, rows, cols]))
    return decomposition, crops[:, :, rows, cols] if isinstance(crops, np.ndarray) else crops.windowed(rows, cols)


def _default_grid(
    axes: tuple[np.ndarray, np.ndarray, np.ndarray], native_um: float, lateral_um: float | None, axial_um: float | None
) -> VolumeGrid:
    """The reconstruction grid spanning ``axes`` (mm): ``lateral_um`` (default ``native_um``) × ``axial_um`` voxels."""
    xs, ys, zs = axes
    dxy = lateral_um if lateral_um is not None else native_um
    if axial_um is None:  # the cm2-v2 preset's axial step
        axial_um = default_design().volume.axial_step_um
    shape = (
        int(math.floor((zs[-1] - zs[0]) * 1000.0 / axial_um + 1e-9)) + 1,
        int(math.floor((ys[-1] - ys[0]) * 1000.0 / dxy + 1e-9)) + 1,
        int(math.floor((xs[-1] - xs[0]) * 1000.0 / dxy + 1e-9)) + 1,
    )
    return VolumeGrid(shape, (axial_um, dxy, dxy))


def _model_provenance(
    provenance: dict[str, Any] | None, geometry: Geometry, zs: np.ndarray, pixel_um: float, native_um: float
) -> dict[str, Any]:
    """A copy of ``provenance`` with its creation stamp and the geometry's magnification, native pitch (µm) and shear (px)."""
    provenance = dict(provenance or {})
    provenance.setdefault("created", datetime.now(UTC).isoformat(timespec="seconds"))
    provenance.setdefault("cm2optics_version", cm2optics.__version__)
    provenance.setdefault("geometry", {})
    provenance["geometry"].update(
        {
            "magnification_at_focus": round(
                math.sqrt(abs(float(np.linalg.det(geometry.A(0.0))))) * pixel_um / 1000.0, 6
            ),
            "native_lateral_um": round(native_um, 5),
            "shear_px_over_scan": [
                [round(float(v), 3) for v in row] for row in (geometry.offsets(zs[-1]) - geometry.offsets(zs[0]))
            ],
        }
    )
    return provenance


def model_from_crops(
    crops: np.ndarray | CropStore,
    grid_index: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    geometry: Geometry,
    *,
    rank: int,
    sensor_shape: tuple[int, int],
    pixel_um: float,
    lateral_um: float | None = None,
    axial_um: float | None = None,
    trim: float | None = 1e-6,
    provenance: dict[str, Any] | None = None,
    oversample: int = 1,
    frames: tuple[Any, dict[str, Any] | None] | None = None,
    focal_surface: FocalSurface | None = None,
    refine: int = 1,
    progress: Progress | None = None,
    basis_psfs: np.ndarray | CropStore | None = None,
    per_lenslet: bool = False,
) -> tuple[LSVModel, Decomposition]:
    """Truncated SVD of registered ``crops`` (N, J, h, w) at grid positions ``grid_index`` (N, 3) as
    (ix, iy, iz) of ``axes`` (x, y, z mm), scaled so that the in-focus on-axis image of a unit source
    sums to 1, with a default grid spanning the axes (``axial_um`` None: the cm2-v2 preset's). ``trim``:
    drop dark margins holding less than this share of the energy (None: keep the full crops).
    ``basis_psfs`` (M, J, h, w): PSFs to decompose instead of the crops (the aberration model's
    at positions between the nodes); the crops' coefficients are then their projections on that
    basis, and the decomposition's errors against K are those of ``basis_psfs``. ``per_lenslet``:
    each lenslet its own ``rank``-term basis (:func:`~cm2optics.lsv.decompose.decompose_per_lenslet`;
    J·rank terms in all, each lenslet's forward uses its own ``rank``)."""
    xs, ys, zs = axes
    S = int(oversample)
    split = decompose_per_lenslet if per_lenslet else decompose
    if basis_psfs is None:
        decomposition = split(crops, rank, progress=progress)
    else:
        decomposition = split(basis_psfs, rank, progress=progress)
        decomposition = replace(decomposition, coefficients=project(crops, decomposition.basis))
    K = decomposition.rank
    crop_shape = crops.shape[2:]
    if trim:
        decomposition, crops = _trim(decomposition, crops, trim, S)
    estimate: dict[str, Any] | None = None
    if frames is not None and S > 1:  # a measured scan: the ePSF basis from whole-pixel frames
        from cm2optics.lsv.epsf_estimate import estimate_epsf_basis

        if per_lenslet:
            raise ScanError(
                "a per-lenslet basis needs fine crops (a synthetic scan's epsf.h5) or whole pixels (--oversample 1): "
                "the ePSF estimate from whole-pixel frames fits one basis of focus arrays"
            )

        index, options = frames
        whole = crops if isinstance(crops, np.ndarray) else crops[:]  # the estimate holds the whole-pixel crops
        decomposition, estimate = estimate_epsf_basis(index, geometry, decomposition, whole, S, **(options or {}))
    decomposition, flux_before = keep_node_flux(decomposition, crops)
    model_error = node_nmse(decomposition, crops)
    gi = np.asarray(grid_index)
    coefficients = np.zeros((K, len(zs), len(ys), len(xs)), np.float32)
    coefficients[:, gi[:, 2], gi[:, 1], gi[:, 0]] = decomposition.coefficients.T
    A0 = geometry.A(0.0)
    native_um = 1000.0 / math.sqrt(abs(float(np.linalg.det(A0))))
    model = LSVModel(
        basis=decomposition.basis,
        coefficients=coefficients,
        grid_x_mm=xs,
        grid_y_mm=ys,
        grid_z_mm=zs,
        geometry=geometry,
        sensor_shape=sensor_shape,
        pixel_um=pixel_um,
        default_grid=_default_grid(axes, native_um, lateral_um, axial_um),
        oversample=S if decomposition.basis.shape[-1] % S == 0 else 1,
        focal_surface=focal_surface,
        refine=refine if focal_surface is not None else 1,
    )
    on_axis = model.focus_patches(0.0, 0.0, 0.0).sum(dtype=np.float64) / model.oversample**2
    if not on_axis > 0:
        raise ScanError("the in-focus PSF on the axis is empty after background removal")
    scale = 1.0 / float(on_axis)
    provenance = _model_provenance(provenance, geometry, zs, pixel_um, native_um)
    provenance["svd"] = {
        "rank": K,
        "basis": f"per lenslet ({rank} terms each at most)" if per_lenslet else "focus arrays",
        "crop_px": list(crop_shape),
        "patch_px": list(model.patch_shape),
        "trim_energy": trim,
        "numerical_rank": numerical_rank(decomposition.singular_values),
        "nmse": float(decomposition.nmse[K]),  # the truncated SVD's, before keep_node_flux
        "nmse_per_psf": float(decomposition.nmse_per_psf[K]),
        "nmse_model": model_error[0] if model_error else None,  # the saved model's at its nodes
        "nmse_per_psf_model": model_error[1] if model_error else None,
    }
    provenance["svd"]["node_flux_before"] = {  # the truncated basis's flux at the nodes / the crops' (1: kept)
        f"p{q}": round(float(v), 4) for q, v in zip((5, 50, 95), np.percentile(flux_before, [5, 50, 95]), strict=True)
    }
    if estimate is not None:
        provenance.setdefault("epsf", {})["estimate"] = estimate
    model = replace(
        model,
        coefficients=coefficients * np.float32(scale),
        scale=scale,
        singular_values=decomposition.singular_values * scale,
        nmse=decomposition.nmse,
        nmse_per_psf=decomposition.nmse_per_psf,
        provenance=provenance,
    )
    return model, decomposition
