"""``cm2 illum run`` as one library call: trace the V1 baseline, the design's collimator and
optionally an STL in the same setup, and return the result document (also written as
``illumination.json`` with the irradiance maps beside it)."""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.errors import UserError
from cm2optics.optics import first_order

__all__ = ["run_illumination", "run_spectral_ceiling"]


def _slug(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", label).strip("_").lower() or "design"


def _check_options(
    design: SystemDesign,
    collimator: Path | None,
    led_position: tuple[float, float, float] | None,
    led_axis: tuple[float, float, float] | None,
    rays: int,
    led_flux_mw: float | None,
    bin_mm: float,
) -> None:
    """A UserError for a ray count, LED flux (mW) or bin (mm) out of range, or an LED pose without an STL."""
    import math

    if rays < 1000 or rays > 100_000_000:
        raise UserError(f"--rays = {rays}: must lie within 1000–100000000")
    if collimator is None and (led_position is not None or led_axis is not None):
        raise UserError("--led-position/--led-axis place the LED in an STL: give the STL with --collimator")
    if led_flux_mw is not None and not (math.isfinite(led_flux_mw) and led_flux_mw > 0):
        raise UserError(f"--led-flux-mw = {led_flux_mw}: must be a number > 0")
    if not 0 < bin_mm <= design.volume.field_mm / 2:
        raise UserError(f"--bin-mm = {bin_mm}: must lie within 0–{design.volume.field_mm / 2} mm")


def _setup_record(design: SystemDesign, setup: Any, seed: int, start: float) -> dict[str, Any]:
    """The document's ``setup``: the design, the options the trace ran with, the backend and the
    seconds since ``start`` (a ``perf_counter`` reading)."""
    from cm2optics.optics.backend import variant

    return {
        "preset": design.name,
        "parameter_hash": design.parameter_hash(),
        "excitation_filter": setup.notes["excitation_filter"],
        "led_profile": setup.notes["led_profile"],
        "led_spectrum": setup.notes["led_spectrum"],
        "housing": setup.housing,
        "smooth_normals": setup.smooth_normals,
        "seed": seed,
        "sample_plane_z_mm": round(first_order.object_plane_z_mm(design), 4),
        "backend": variant().variant,
        "elapsed_s": round(time.perf_counter() - start, 2),
    }


def run_spectral_ceiling(design: SystemDesign, setup: Any) -> float | None:
    """The most of the LED's power the run's excitation filter can pass (every ray at normal
    incidence, :func:`cm2optics.illumination.bounds.spectral_ceiling`), from the run's own
    filter (a coating table's fit or the design's model) and LED spectrum; None without a filter."""
    from cm2optics.illumination.bounds import spectral_ceiling

    if setup.transmission is None:
        return None
    return round(spectral_ceiling(design, setup.transmission, setup.source.spectrum), 4)


def run_illumination(
    design: SystemDesign,
    out_dir: str | Path,
    *,
    collimator: Path | None = None,
    led_position: tuple[float, float, float] | None = None,
    led_axis: tuple[float, float, float] | None = None,
    rays: int = 1_000_000,
    led_profile: Path | None = None,
    led_spectrum: Path | None = None,
    filter_table: Path | None = None,
    no_filter: bool = False,
    no_housing: bool = False,
    flat_normals: bool = False,
    led_flux_mw: float | None = None,
    bin_mm: float = 0.5,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> tuple[dict[str, Any], list[Any]]:
    """Returns the document (figures of the last design, ``designs``, ``setup``, ``definitions``,
    ``maps``) and the per-design results. led_position (mm) and led_axis place the LED in the
    STL's frame (defaults 0,0,0 and 0,0,1)."""
    from cm2optics.formats.atomic import write_json_atomic
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.illumination.compare import (
        Setup,
        compare_designs,
        configurations,
        setup_from_options,
        stl_collimator,
    )
    from cm2optics.illumination.geometry import build_scene
    from cm2optics.illumination.metrics import DEFINITIONS, write_maps_png
    from cm2optics.optics.backend import mitsuba

    _check_options(design, collimator, led_position, led_axis, rays, led_flux_mw, bin_mm)
    stl = None
    if collimator is not None:
        stl = stl_collimator(
            design,
            collimator,
            np.array(led_position if led_position is not None else (0.0, 0.0, 0.0), dtype=float),
            np.array(led_axis if led_axis is not None else (0.0, 0.0, 1.0), dtype=float),
        )
        build_scene(design, stl, excitation_filter=not no_filter, housing=not no_housing)  # fits? LED outside?
    setup: Setup = setup_from_options(
        design,
        led_profile=led_profile,
        led_spectrum=led_spectrum,
        filter_table=filter_table,
        excitation_filter=not no_filter,
        led_flux_mw=led_flux_mw,
        housing=not no_housing,
        smooth_normals=not flat_normals,
        rays=rays,
        seed=seed,
        bin_mm=bin_mm,
    )
    claim_folder(out_dir, "illum run")  # inputs read and checked: the folder is this command's from here on
    mitsuba()  # choose the variant (and warn once if it is the scalar fallback) before tracing
    configs = configurations(design, stl)
    start = time.perf_counter()

    results = compare_designs(design, setup, configs, progress or (lambda label: None))
    primary = results[-1]
    document = primary.to_json()
    document["designs"] = {r.label: r.summary() for r in results}
    document["setup"] = _setup_record(design, setup, seed, start)
    document["spectral_ceiling"] = run_spectral_ceiling(design, setup)
    document["definitions"] = DEFINITIONS
    maps = {}
    for result in results:
        maps[result.label] = str(write_maps_png(result, Path(out_dir) / f"irradiance_{_slug(result.label)}.png"))
    document["maps"] = maps
    write_json_atomic(Path(out_dir) / "illumination.json", document)
    return document, results
