"""``cm2 lsv validate --refit``: leave-one-out in pixels, with the model's own build redone
without the held-out nodes.

The issue's leave-one-out figure for the model a user built: for a seeded sample of interior
nodes, everything the build learns from the scan is learnt again without them, and each held-out
node is predicted and compared with its own frame (whole pixels, as the sensor saw it), the
prediction placed at the node's exact sub-pixel focus
(:func:`~cm2optics.lsv.epsf_validate.predicted_nodes_nmse`, the metric of
:func:`~cm2optics.lsv.epsf_validate.leave_one_out_pixels`). What is redone depends on the build:

- **A model of the node PSFs** (``cm2 lsv build --aberration-model N``): the model is fitted
  again to the other nodes alone (their pupils and crops; ``node_psfs``, passed by the CLI with the
  design, as the build's), its prediction at each held-out node is the node's PSF, and the basis is
  decomposed again from its PSFs at the build's N seeded random positions.
- **The crops themselves**: each held-out node predicted from its neighbours along x, y and z
  (the model's focal surface, turn and warp as built), the basis decomposed from the other nodes'
  crops (:func:`~cm2optics.lsv.epsf_validate.leave_one_out_pixels`).

The imaging geometry (the chief rays, from which the crops are registered and each frame's
sub-pixel focus is taken) and a crops model's focal surface are the build's, fitted to all nodes.
Either way the basis has the model's structure: one basis of K focus arrays, or each lenslet
its own K terms (:func:`~cm2optics.lsv.decompose.lenslet_bases`, a per-lenslet model). Node NMSE
Σ_j ‖p_j − y_j‖² / Σ_j ‖y_j‖²; its mean and median over the held-out nodes, per lenslet, full rank
(the prediction itself) and on the basis (``nmse``: the model's figure).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.formats.scan import ScanError, ScanIndex, open_scan
from cm2optics.lsv.build import scan_fingerprint
from cm2optics.lsv.crop_store import DEFAULT_MEMORY_BYTES
from cm2optics.lsv.decompose import decompose, lenslet_bases
from cm2optics.lsv.epsf_validate import heldout_nodes, leave_one_out_pixels, predicted_nodes_nmse
from cm2optics.lsv.model import LSVModel
from cm2optics.lsv.preprocess import Geometry, extract_crops, prepared_image
from cm2optics.lsv.rotation import AzimuthTurn

__all__ = ["TARGET", "TERMS", "held_frames", "leave_out_nodes"]

Progress = Callable[[str, int, int], None]
#: Terms (per lenslet for a per-lenslet model) at which the figure is also reported.
TERMS = (16, 32, 64, 128, 256)
#: The issue's leave-one-out target (node NMSE); ``nodes_at_or_below_target`` counts the nodes within it.
TARGET = 0.08


def held_frames(
    index: ScanIndex, geometry: Geometry, held: np.ndarray, patch: tuple[int, int]
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Each held-out node's whole-pixel frames (J, h+3, w+3), background removed
    (:func:`~cm2optics.lsv.preprocess.prepared_image`), whose pixel (1 + h//2, 1 + w//2) holds the
    chief ray's integer part, and the chief ray's fraction ``eps`` (J, 2), by node."""
    h, w = patch
    targets: dict[int, np.ndarray] = {}
    eps: dict[int, np.ndarray] = {}
    J = geometry.n_lenslets
    for n in held:
        x, y, z = index.positions_mm[n]
        focus = np.asarray(geometry.focus(x, y, z), float).reshape(J, 2)
        base = np.floor(focus).astype(np.int64)
        image = prepared_image(index, int(n))
        H, W = image.shape
        frame = np.zeros((J, h + 3, w + 3))
        for j in range(J):
            r0, c0 = base[j, 0] - 1 - h // 2, base[j, 1] - 1 - w // 2
            rs, re, cs, ce = max(r0, 0), min(r0 + h + 3, H), max(c0, 0), min(c0 + w + 3, W)
            if rs < re and cs < ce:
                frame[j, rs - r0 : re - r0, cs - c0 : ce - c0] = image[rs:re, cs:ce]
        targets[int(n)] = frame
        eps[int(n)] = focus - base
    return targets, eps


def _structure(model: LSVModel) -> tuple[bool, int]:
    """(per-lenslet basis?, terms: per lenslet for a per-lenslet model, else the model's rank)."""
    options = model.provenance.get("options", {})
    if options.get("basis") == "per lenslet":
        return True, int(options.get("rank", max(len(model.lenslet_terms(j)) for j in range(model.n_lenslets))))
    return False, int(model.rank)


def _fine_crops(index: ScanIndex, model: LSVModel, patch: int, S: int, memory_bytes: int, progress: Progress | None):
    """The scan's registered crops as the build took them: fine (epsf.h5) for S > 1, else whole pixels."""
    if S == 1:
        return extract_crops(index, model.geometry, (patch, patch), progress=progress, memory_bytes=memory_bytes)
    if not (index.folder / "epsf.h5").is_file():
        raise ScanError(
            f"{index.folder}: --refit of an ePSF model needs the scan's fine ePSFs (epsf.h5); an ePSF basis estimated "
            "from whole-pixel frames is not refitted"
        )
    from cm2optics.lsv.epsf import epsf_crops

    return epsf_crops(index, model.geometry, (patch, patch), S, progress=progress, memory_bytes=memory_bytes)


def leave_out_nodes(
    model: LSVModel,
    scan_dir: str | Path,
    *,
    n_heldout: int = 48,
    seed: int = 0,
    node_psfs: Callable[..., tuple[Any, Any, dict[str, Any]]] | None = None,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Leave-one-out node NMSE of ``model`` on its own calibration scan ``scan_dir`` (module
    docstring): ``n_heldout`` interior nodes (seeded by ``seed``) held out of everything the build
    fits. ``node_psfs``: for a model built with a model of the node PSFs, that model (as the
    build's ``node_psfs``, called with ``held_out=``; the CLI passes the aberration model with the
    design and the build's number of random positions and seed). A JSON-able dict; ``nmse`` (the
    model's figure, on its basis) and ``nmse_median``, ``nmse_full`` (the prediction at full rank),
    ``nmse_per_lenslet``, ``nmse_vs_terms``."""
    start = time.perf_counter()
    index = open_scan(scan_dir)
    calibration = model.provenance.get("scan", {})
    if calibration.get("fingerprint") != scan_fingerprint(index):
        raise ScanError(f"{scan_dir}: --refit needs the model's own calibration scan (this is another scan)")
    options = model.provenance.get("options", {})
    S = int(model.provenance.get("epsf", {}).get("oversample", model.oversample))
    patch = int(options.get("patch_px", model.patch_shape[0]))
    per_lenslet, terms = _structure(model)
    gi = index.grid_index()
    held = heldout_nodes(gi, n_heldout, seed)
    node_model = model.provenance.get("node_psfs")
    frame_phases: dict[str, np.ndarray] = {}
    if node_model is not None and S > 1 and not (index.folder / "epsf.h5").is_file():
        # a node model built from whole-pixel frames: refitted on them, each at its own phase
        from cm2optics.lsv.epsf_estimate import pixel_windows

        crops, foci = pixel_windows(index, model.geometry, (patch, patch), progress=progress)
        frame_phases["phases"] = foci - np.floor(foci)
    else:
        crops = _fine_crops(index, model, patch, S, memory_bytes, progress)
    targets, eps = held_frames(index, model.geometry, held, (patch, patch))
    axes = index.grid_axes_mm()
    reported = tuple(k for k in TERMS if k < terms) + (terms,)
    result: dict[str, Any] = {
        "method": "",
        "basis": f"per lenslet, {terms} terms each" if per_lenslet else f"one basis of {terms} focus arrays",
        "seed": seed,
        "held_out_nodes": [int(n) for n in held],
        "oversample": S,
        "patch_px": patch,
    }
    if node_model is not None:
        if node_psfs is None:
            raise ValueError("the model was built with a model of the node PSFs: --refit needs it (the design)")
        predictions, dense, record = node_psfs(
            crops,
            gi,
            axes,
            model.geometry,
            S,
            index.meta.pixel_um,
            held_out=held,
            progress=progress,
            memory_bytes=memory_bytes,
            **frame_phases,
        )
        basis = lenslet_bases(dense, terms, progress=progress) if per_lenslet else decompose(dense, terms).basis
        del dense
        prediction = np.asarray(predictions[:], np.float32)
        figures = predicted_nodes_nmse(prediction, targets, eps, held, S, basis=basis, terms=reported)
        result["method"] = (
            "node model refitted without the held-out nodes (their pupils and crops), each predicted by it; basis "
            f"decomposed from its PSFs at {record.get('dense_positions')} seeded random positions"
        )
        result["node_model"] = record
        result |= {
            "nmse": figures["rank"],
            "nmse_median": figures["rank_median"],
            "nmse_full": figures["full"],
            "nmse_full_median": figures["full_median"],
            "nmse_per_lenslet": figures["rank_per_lenslet"],
            "nmse_per_lenslet_median": figures["rank_per_lenslet_median"],
            "nmse_full_per_lenslet": figures["full_per_lenslet"],
            "lit_nodes_per_lenslet": figures["rank_per_lenslet_nodes"],
            "nmse_vs_terms": figures.get("rank_vs_terms", {}),
            "nmse_per_node": figures["rank_per_node"],
            "nmse_full_per_node": figures["full_per_node"],
            "n_heldout": figures["n_heldout"],
            "nodes_at_or_below_target": sum(v <= TARGET for v in figures["rank_per_node"]),
            "target": TARGET,
        }
    else:
        keep = np.ones(len(gi), bool)
        keep[held] = False
        kept = np.asarray(crops[np.flatnonzero(keep)])
        basis = lenslet_bases(kept, terms, progress=progress) if per_lenslet else decompose(kept, terms).basis
        del kept
        turn = None
        if model.rotate_aberrations:  # the pivots in the crops' frame (S samples per pixel; chief ray at h // 2)
            turn = AzimuthTurn.of_model(model)
            pivots = S * (turn.pivots / model.oversample - np.array(model.patch_shape) // 2 + patch // 2)
            turn = replace(turn, pivots=pivots)
        crops = np.asarray(crops[:])
        figures = leave_one_out_pixels(
            crops,
            gi,
            axes,
            targets,
            eps,
            S,
            held=held,
            basis=basis,
            surface=model.focal_surface,
            turn=turn,
            warp=model.warp_shapes,
        )
        result["method"] = (
            "each node predicted from its neighbours along x, y and z (as the model interpolates), basis decomposed "
            "from the other nodes' crops"
        )
        result |= {
            "nmse": figures["interpolated_rank"],
            "nmse_median": figures.get("interpolated_rank_median"),
            "nmse_full": figures["interpolated_full"],
            "nmse_per_axis": figures["per_axis_rank"],
            "parts": figures.get("parts"),
            "n_heldout": figures["n_heldout"],
        }
    result["seconds"] = round(time.perf_counter() - start, 1)
    return result
