"""Collimator design search: a parallel sweep over the collimator's parameters on Dask.

Objective: the array's delivered fraction into the field circle, subject to its uniformity
``CV ≤ max_cv`` inside the circle (:mod:`.metrics`). A candidate is a set of values for
:data:`PARAMETERS`: the collimator's own fields (lens angle, cavity, LED gap, entry wall,
height; the filter stays on the exit face: ``led_array.excitation_gap_mm = led_gap_mm +
height_mm``) and the beam-shaping fields (output spreads and mapping exponents, see
:mod:`cm2optics.optics.collimator_shaping`; with zero spreads a candidate is exactly the collimating
cm2-v2 architecture). Each candidate's section is computed, revolved into a mesh
(:func:`.revolve.revolve_profile`) and traced with the LED,
filter, housings and sample plane of the design. Candidates whose optics cannot be built in
the envelope (the TIR surface above the flange, the lens vertex below the entry plane, a TIR
wall that would leak …) are recorded as infeasible with the reason.

Search: a scrambled Sobol sweep of ``samples`` points over the parameter box, then ``rounds``
sweeps of ``samples // 2`` points in a box half as wide around the best candidate so far
(ranked by ``delivered − 2 · max(0, CV′ − max_cv)``, CV′ = √(CV² − CV_noise²) the uniformity
with the Monte Carlo noise of the candidate's few rays taken out). Every candidate is an independent task
(embarrassingly parallel): a local Dask cluster by default, an existing scheduler when an
address is given. The profile and the placement are swept: the delivered fraction of a faceted
mesh traced with discrete reflect/refract choices is piecewise constant in them. The lens's
Zernike terms alone also have a gradient search through Dr.Jit (:mod:`.gradient_search`, on
the smooth objective of :mod:`.differentiable`).

The :data:`CONFIRMED` best candidates meeting the constraint (else the best ranked) are traced
again with 4× the rays, and the one delivering most whose measured CV — noise included — is
≤ max_cv there is chosen (else the first); its figures in the result come from that run. ``design.yaml`` holds the improved
design; ``collimator.stl`` and ``collimator.step`` are the CAD part built from it
(:mod:`cm2optics.cad.collimator`), the STL checked for printing with
:func:`cm2optics.cad.mesh_checks.check_mesh` (watertight, consistently wound, thinnest wall ≥
``mechanics.min_wall_mm``); that part itself is traced once more (``built_part`` in the result,
its irradiance maps in ``irradiance.png``).

The étendue bound and the uniform-beam bound (:mod:`.bounds`) are reported beside the result,
and with ``free_aim`` the bound of re-aimed units with the finite LED (:func:`.bounds.free_aim_bound`).

With an :class:`SBRFloor` every candidate's SBR is computed from its traced beam
(:func:`.traced_sbr.traced_sbr`): a candidate meets the constraints only with both SBRs at or above
the floor (in the sweep and in its confirmation), and its score is scaled by the shortfall,
``min(1, SBR/floor)`` of each chain, so the refinement stays where the excitation mirrored by the
sample does not reach the lenslets.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.design import DesignError, SystemDesign, design_from_dict
from cm2optics.illumination.bounds import etendue_bound, free_aim_bound, uniform_beam_bound
from cm2optics.illumination.robustness import Tolerances, expected_figures, perturbed_figures

__all__ = [
    "AIM_PARAMETERS",
    "PARAMETERS",
    "RobustScoring",
    "SBRFloor",
    "design_bounds",
    "evaluate_candidate",
    "export_collimator",
    "optimize_collimator",
    "read_inputs",
    "search_box",
    "trace_built_part",
]

#: The swept parameters and their ranges (mm, degrees).
PARAMETERS: dict[str, tuple[float, float]] = {
    "collimator.lens_half_angle_deg": (20.0, 46.0),
    "collimator.cavity_radius_mm": (0.5, 0.9),
    "collimator.led_gap_mm": (0.05, 0.4),
    "collimator.entry_wall_mm": (0.41, 0.7),
    "collimator.height_mm": (1.6, 2.6),
    "collimator.lens_spread_deg": (0.0, 40.0),
    "collimator.tir_spread_deg": (0.0, 40.0),
    "collimator.lens_exponent": (0.2, 0.6),
    "collimator.tir_exponent": (0.2, 0.6),
}
#: The profile swept with ``cone_wall``: the LED at (or just under) the cavity mouth, a cavity
#: that encloses the 1-mm emitter (half-diagonal 0.707 mm) and the prescribed TIR wall
#: (:attr:`cm2optics.design.Collimator.tir_cone_deg`) stopping at ``tir_max_radius_mm``; the lens's
#: mapping as in :data:`PARAMETERS`, the wall's sub-beam unshaped (``tir_spread_deg`` 0).
CONE_PARAMETERS: dict[str, tuple[float, float]] = {
    "collimator.lens_half_angle_deg": (20.0, 40.0),
    "collimator.cavity_radius_mm": (0.72, 0.9),
    "collimator.led_gap_mm": (0.0, 0.1),
    "collimator.entry_wall_mm": (0.41, 0.6),
    "collimator.height_mm": (1.8, 2.6),
    "collimator.lens_spread_deg": (0.0, 20.0),
    "collimator.lens_exponent": (0.2, 0.6),
    "collimator.tir_cone_deg": (20.0, 45.0),
    "collimator.tir_cone_curvature_per_mm": (-0.5, 0.3),
    "collimator.tir_max_radius_mm": (1.6, 1.95),
}
#: The fields of a prescribed wall, reset when :data:`PARAMETERS` sweeps the designed one.
CONE_WALL_FIELDS = ("tir_cone_deg", "tir_cone_curvature_per_mm", "tir_max_radius_mm")
#: The units' placement, swept with ``free_aim``: tilt, aperture offset, aim point on the focal
#: plane (:attr:`cm2optics.design.LEDArray.aim_mm`) and the array's azimuth against the square
#: imaging tower (mm, degrees). A candidate whose units enter the tower, reach below its flange
#: or overlap (:func:`cm2optics.optics.layout.unit_clashes`) is infeasible.
AIM_PARAMETERS: dict[str, tuple[float, float]] = {
    "led_array.tilt_deg": (40.0, 60.0),
    "led_array.offset_mm": (6.0, 10.5),
    "led_array.aim_mm": (-2.0, 3.5),
    "led_array.azimuth_deg": (0.0, 45.0),
}
#: The lens's Zernike terms (:attr:`cm2optics.design.Collimator.lens_freeform_um`, µm), swept with
#: ``freeform``: Noll 3 (tilt), 4 (defocus), 6 (astigmatism), 7 (coma), 11 (spherical) — the
#: terms that keep each unit's mirror symmetry about its plane of tilt (its local y–z plane).
FREEFORM_TERMS = (3, 4, 6, 7, 11)
FREEFORM_PARAMETERS: dict[str, tuple[float, float]] = {
    f"collimator.lens_freeform_um[{j}]": (-15.0, 15.0) for j in FREEFORM_TERMS
}
#: The TIR wall's departure from revolution (:attr:`cm2optics.design.Collimator.tir_cos2`,
#: ``tir_cos4``: its radial departure from the entry ring scaled by 1 + c₂ cos 2φ + c₄ cos 4φ,
#: dimensionless), swept with ``tir_azimuthal``: c₂ makes the beam elliptical (across / in the
#: unit's plane of tilt), c₄ widens the wall into the flange's corners (c₄ < 0) or its sides.
TIR_AZIMUTHAL_PARAMETERS: dict[str, tuple[float, float]] = {
    "collimator.tir_cos2": (-0.2, 0.2),
    "collimator.tir_cos4": (-0.1, 0.1),
}
#: Best candidates traced again with 4× the rays before one is chosen.
CONFIRMED = 4
#: Segments per turn of the revolved mesh in the sweep (the written STL uses 256).
SWEEP_SEGMENTS = 128


def search_box(
    free_aim: bool,
    freeform: bool = False,
    fixed_profile: bool = False,
    cone_wall: bool = False,
    tir_azimuthal: bool = False,
) -> dict[str, tuple[float, float]]:
    """The swept parameters and their ranges: the collimator's profile (unless ``fixed_profile``;
    :data:`CONE_PARAMETERS` with ``cone_wall``), the units' placement with ``free_aim``, the
    lens's Zernike terms with ``freeform``, the TIR wall's azimuthal terms with ``tir_azimuthal``."""
    profile = CONE_PARAMETERS if cone_wall else PARAMETERS
    return {
        **({} if fixed_profile else profile),
        **(AIM_PARAMETERS if free_aim else {}),
        **(FREEFORM_PARAMETERS if freeform else {}),
        **(TIR_AZIMUTHAL_PARAMETERS if tir_azimuthal else {}),
    }


def _changes(values: dict[str, float], design: SystemDesign) -> dict[str, Any]:
    """The design changes of a candidate of ``design``: its values (Zernike terms merged into the
    design's own list), and when the profile is swept the TIR sub-beam crossing the axis, the
    excitation filter kept on the collimator's exit face, and either wall alone (a prescribed
    cone drops the designed wall's spread; the designed wall drops a base's cone)."""
    changes: dict[str, Any] = {}
    terms = list(design.collimator.lens_freeform_um) if design.collimator is not None else []
    for name, value in values.items():
        if name.startswith("collimator.lens_freeform_um["):
            j = int(name[len("collimator.lens_freeform_um[") : -1])
            terms += [0.0] * (j - len(terms))
            terms[j - 1] = float(value)
            changes["collimator.lens_freeform_um"] = terms
        else:
            changes[name] = float(value)
    if any(name in values for name in PARAMETERS):
        changes["collimator.tir_crossing"] = True
    if "collimator.tir_cone_deg" in values:
        changes["collimator.tir_spread_deg"] = 0.0  # a prescribed wall has no ray mapping
    elif "collimator.tir_spread_deg" in values:  # the designed wall (PARAMETERS), whole, from any base
        changes.update({f"collimator.{name}": 0.0 for name in CONE_WALL_FIELDS})
    gap = changes.get("collimator.led_gap_mm")
    height = changes.get("collimator.height_mm")
    if gap is not None and height is not None:
        changes["led_array.excitation_gap_mm"] = gap + height
    return changes


def candidate_collimator(design: SystemDesign, values: dict[str, float], segments: int = SWEEP_SEGMENTS) -> Any:
    """(design with the candidate's fields, its collimator mesh, its profile)."""
    from cm2optics.illumination.geometry import CollimatorMesh
    from cm2optics.illumination.revolve import revolve_profile
    from cm2optics.optics.collimator import collimator_profile

    candidate = design.with_changes(_changes(values, design))
    profile = collimator_profile(candidate)
    mesh = CollimatorMesh(
        f"{design.name} (optimised)",
        revolve_profile(
            profile,
            segments,
            candidate.collimator.lens_freeform_um,
            (candidate.collimator.tir_cos2, candidate.collimator.tir_cos4),
        ),
        candidate.collimator.material,
    )
    return candidate, mesh, profile


@functools.lru_cache(maxsize=4)
def read_inputs(led_profile: str | None, led_spectrum: str | None, filter_table: str | None) -> tuple[Any, Any, Any]:
    """(angular profile, spectrum, filter transmission) read from the files given (None: the
    design's models), once per worker process: fitting a coating table takes seconds."""
    from cm2optics.illumination.excitation import filter_from_table
    from cm2optics.illumination.source import read_angular_profile, read_source_spectrum

    return (
        read_angular_profile(led_profile) if led_profile else None,
        read_source_spectrum(led_spectrum) if led_spectrum else None,
        filter_from_table(filter_table) if filter_table else None,
    )


def evaluate_candidate(
    design_data: dict[str, Any],
    values: dict[str, float],
    rays: int,
    seed: int,
    max_cv: float,
    threads: int | None = None,
    inputs: tuple[str | None, str | None, str | None] = (None, None, None),
    robust: RobustScoring | None = None,
    sbr_floor: SBRFloor | None = None,
) -> dict[str, Any]:
    """Trace one candidate (runs on a Dask worker). Returns its parameters and figures, or
    ``feasible: False`` and the reason. ``design_data``: the base design as plain data.
    inputs: paths of the LED's angular profile, its spectrum and the excitation filter's
    coating table (each None: the design's model). robust: also trace the candidate under
    ``robust.samples`` drawn builds and score it on their expected figures (:class:`RobustScoring`).
    sbr_floor: also compute its traced SBR and hold it to the floor (:class:`SBRFloor`)."""
    from cm2optics.optics.backend import mitsuba

    mi = mitsuba()
    if threads is not None and not mi.variant().startswith("scalar"):
        import drjit as dr

        dr.set_thread_count(threads)
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.geometry import build_scene
    from cm2optics.illumination.metrics import figures_of_merit
    from cm2optics.illumination.source import led_source
    from cm2optics.illumination.tracer import trace
    from cm2optics.optics.layout import unit_clashes

    entry: dict[str, Any] = {"parameters": {k: round(float(v), 5) for k, v in values.items()}}
    start = time.perf_counter()
    try:
        design, collimator, _ = candidate_collimator(design_from_dict(design_data), values)
        scene = build_scene(design, collimator)
    except (DesignError, ValueError, RuntimeError) as error:
        entry.update(feasible=False, reason=str(error).splitlines()[0][:300])
        return entry
    clashes = unit_clashes(design)
    if clashes:
        entry.update(
            feasible=False, reason=f"housing: {clashes[0]}" + (f" (+{len(clashes) - 1} more)" if clashes[1:] else "")
        )
        return entry
    profile, spectrum, table = read_inputs(*inputs)
    transmission = table if table is not None else design_filter_transmission(design)
    source = led_source(design, profile, spectrum)
    record = trace(scene, source, rays, transmission=transmission, seed=seed)
    figures = figures_of_merit(record, scene)
    delivered, cv = figures.delivered_fraction.value, figures.uniformity_cv.value
    # Monte Carlo noise adds in quadrature to the true spread: rank on the noise-free estimate.
    cv_corrected = math.sqrt(max(cv**2 - figures.uniformity_cv_noise**2, 0.0))
    entry.update(
        feasible=True,
        delivered_fraction=delivered,
        delivered_fraction_stderr=figures.delivered_fraction.stderr,
        uniformity_cv=cv,
        uniformity_cv_stderr=figures.uniformity_cv.stderr,
        uniformity_cv_noise=figures.uniformity_cv_noise,
        uniformity_cv_corrected=cv_corrected,
        throughput=figures.throughput.value,
        meets_uniformity=bool(cv_corrected <= max_cv),
        score=delivered - 2.0 * max(0.0, cv_corrected - max_cv),
    )
    if robust is not None:
        entry.update(nominal_score=entry["score"], nominal_meets_uniformity=entry["meets_uniformity"])
        entry.update(robust.score(scene, source, transmission, rays, seed, max_cv))
    if sbr_floor is not None:
        entry.update(sbr_floor.check(record, scene, seed, entry["score"]))
    entry["seconds"] = round(time.perf_counter() - start, 2)
    return entry


@dataclasses.dataclass(frozen=True)
class RobustScoring:
    """Score candidates on their expected figures over drawn builds (:mod:`.robustness`).

    samples: builds drawn per candidate. tolerances: the error ranges. seed: the error draws'
    seed — the same builds (LED offsets, tilts, surface fields) for every candidate and the
    same LED rays as the candidate's own trace: common random numbers, so candidates differ by
    their design, not by their draws. A scored candidate's ``score`` becomes
    ``E[D] − 2 max(0, E[CV′] − max_cv)`` and ``meets_uniformity`` E[CV′] ≤ max_cv; its nominal
    figures stay beside them.
    """

    samples: int
    tolerances: Tolerances
    seed: int

    def score(
        self, scene: Any, source: Any, transmission: Any, rays: int, trace_seed: int, max_cv: float
    ) -> dict[str, Any]:
        """The expected figures of ``scene`` (:func:`.robustness.expected_figures`), with the
        nominal ``score`` and ``meets_uniformity`` replaced by their expected counterparts."""
        from cm2optics.illumination.compare import Setup

        setup = Setup(source=source, transmission=transmission, rays=rays, seed=trace_seed)
        rows = perturbed_figures(scene, setup, self.tolerances, self.samples, self.seed)
        expected = expected_figures(rows, max_cv)
        return {
            **expected,
            "score": expected["expected_score"],
            "meets_uniformity": bool(expected["expected_uniformity_cv_corrected"] <= max_cv),
        }


@dataclasses.dataclass(frozen=True)
class SBRFloor:
    """The least SBR a candidate's traced beam may give (:func:`.traced_sbr.traced_sbr`, coarse
    sampling): interference-only chain and hybrid chain (0: that chain unconstrained)."""

    interference_only: float = 0.0
    hybrid: float = 0.0

    def __post_init__(self) -> None:
        for name in ("interference_only", "hybrid"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"SBR floor {name} = {value!r}: must be a finite number ≥ 0")

    def check(self, record: Any, scene: Any, seed: int, score: float) -> dict[str, Any]:
        """The traced SBRs of ``record`` in ``scene``, whether they meet the floor, and ``score``
        scaled by their shortfall."""
        from cm2optics.illumination.traced_sbr import COARSE_SAMPLING, traced_sbr

        result = traced_sbr(record, scene, seed=seed, **COARSE_SAMPLING)
        shares = [
            min(1.0, value / floor) if floor > 0 else 1.0
            for value, floor in (
                (result.sbr_interference_only, self.interference_only),
                (result.sbr_hybrid, self.hybrid),
            )
        ]
        return {
            "sbr_interference_only": round(result.sbr_interference_only, 4),
            "sbr_hybrid": round(result.sbr_hybrid, 2),
            "meets_sbr": bool(min(shares) >= 1.0),
            "score": score * shares[0] * shares[1] if score > 0 else score,
        }


def _sobol(box: dict[str, tuple[float, float]], count: int, seed: int) -> list[dict[str, float]]:
    from scipy.stats import qmc

    names = list(box)
    # A power-of-two draw keeps Sobol's balance; the first ``count`` points are used.
    unit = qmc.Sobol(len(names), scramble=True, seed=seed).random_base2(max(0, math.ceil(math.log2(count))))[:count]
    lows = np.array([box[n][0] for n in names])
    highs = np.array([box[n][1] for n in names])
    return [dict(zip(names, lows + u * (highs - lows), strict=True)) for u in unit]


def _client(dask_address: str | None, workers: int) -> Any:
    from dask.distributed import Client, LocalCluster

    if dask_address:
        try:
            return Client(dask_address, timeout="15s"), None
        except (OSError, TimeoutError, ValueError) as error:
            raise ValueError(f"--dask-address {dask_address}: cannot reach a Dask scheduler there ({error})") from None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    return Client(cluster), cluster


def optimize_collimator(
    design: SystemDesign,
    out_dir: str | Path,
    *,
    rays: int = 200_000,
    max_cv: float = 0.10,
    samples: int = 64,
    rounds: int = 2,
    dask_address: str | None = None,
    workers: int = 2,
    seed: int = 0,
    show_progress: bool = True,
    free_aim: bool = False,
    inputs: tuple[str | None, str | None, str | None] = (None, None, None),
    freeform: bool = False,
    fixed_profile: bool = False,
    cone_wall: bool = False,
    robust: RobustScoring | None = None,
    sbr_floor: SBRFloor | None = None,
    tir_azimuthal: bool = False,
) -> dict[str, Any]:
    """Run the sweep (see the module docstring) and write ``design.yaml``, ``collimator.stl``,
    ``collimator.step``, ``irradiance.png`` and ``sweep.json`` into ``out_dir``; returns the
    summary (also ``result.json``).

    rays: rays per candidate (all LEDs). max_cv: uniformity constraint (0–1). samples:
    candidates of the first sweep. rounds: refinement sweeps. dask_address: an existing
    scheduler, or None for a local cluster of ``workers`` processes. seed: sweep and trace seed.
    free_aim: sweep the units' tilt, offset, aim point and azimuth too (:data:`AIM_PARAMETERS`);
    the chosen design is then checked with the CAD assembly's interference check.
    freeform: sweep the lens's Zernike terms too (:data:`FREEFORM_PARAMETERS`).
    fixed_profile: keep the design's profile (:data:`PARAMETERS` not swept): refine its
        placement and/or freeform terms.
    cone_wall: sweep the profile with the prescribed TIR wall (:data:`CONE_PARAMETERS`).
    tir_azimuthal: sweep the TIR wall's departure from revolution too (:data:`TIR_AZIMUTHAL_PARAMETERS`).
    inputs: paths of the LED's angular profile, spectrum and the excitation filter's coating
    table (each None: the design's model), used by every trace and by the bounds.
    robust: rank every candidate (and choose among the confirmed ones) on its expected figures
        over drawn builds instead of its nominal ones (:class:`RobustScoring`).
    sbr_floor: hold every candidate's traced SBR to this floor (:class:`SBRFloor`).
    """
    from cm2optics.formats.atomic import write_json_atomic

    if design.collimator is None:
        raise ValueError(f"design {design.name!r} has no collimator to optimise (use a preset with one, e.g. cm2-v2)")
    base = design.to_dict()
    client, cluster = _client(dask_address, workers)
    threads = 1 if dask_address is None else None
    candidates: list[dict[str, Any]] = []
    start = time.perf_counter()
    try:
        box = search_box(free_aim, freeform, fixed_profile, cone_wall, tir_azimuthal)
        if not box:
            raise ValueError("nothing to sweep: a fixed profile needs free aim, freeform or TIR azimuthal terms")
        _sweep(
            client,
            base,
            box,
            candidates,
            rays,
            max_cv,
            samples,
            rounds,
            seed,
            threads,
            show_progress,
            inputs,
            robust,
            sbr_floor,
        )
        feasible = [c for c in candidates if c["feasible"]]
        meeting = [c for c in feasible if _meets(c)]
        best, confirm, assembly = _confirm_finalists(
            client, base, feasible, meeting, rays, max_cv, seed, threads, inputs, free_aim, robust, sbr_floor
        )
    finally:
        client.close()
        if cluster is not None:
            cluster.close()

    name = design.name if design.name.endswith("-optimised") else f"{design.name}-optimised"  # refining one: once
    improved = design.with_changes({**_changes(best["parameters"], design), "name": name})
    out_dir = Path(out_dir)
    stl_path, checks = export_collimator(improved, out_dir)
    improved.save(out_dir / "design.yaml")
    built = trace_built_part(improved, out_dir, 4 * rays, seed + 2, inputs)
    result = {
        "design": str(out_dir / "design.yaml"),
        "stl": str(stl_path),
        "step": str(out_dir / "collimator.step"),
        "built_part": built,
        "parameters": best["parameters"],
        "meets_uniformity": bool(confirm.get("feasible") and _confirmed_uniform(confirm, max_cv)),
        "max_cv": max_cv,
        **{key: confirm.get(key) for key in _CONFIRMED_FIGURES},
        "sbr": None
        if sbr_floor is None
        else {
            "floor": dataclasses.asdict(sbr_floor),
            **{key: confirm.get(key) for key in ("sbr_interference_only", "sbr_hybrid", "meets_sbr")},
        },
        "robust": None
        if robust is None
        else {
            "samples": robust.samples,
            "seed": robust.seed,
            "tolerances": dataclasses.asdict(robust.tolerances),
            **{key: confirm.get(key) for key in _EXPECTED_FIGURES},
        },
        "rays": 4 * rays,
        "printability": checks,
        "free_aim": free_aim,
        "freeform": freeform,
        "tir_azimuthal": tir_azimuthal,
        "fixed_profile": fixed_profile,
        "assembly_interferences": assembly,
        "base_plate_min_wall_mm": best.get("base_plate_min_wall_mm"),
        "base_plate_printable": None
        if "base_plate_min_wall_mm" not in best
        else bool(best["base_plate_min_wall_mm"] >= improved.mechanics.min_wall_mm - 1e-6),
        **design_bounds(improved, max_cv, inputs, free_aim),
        "candidates_traced": len(candidates),
        "candidates_feasible": len(feasible),
        "candidates_meeting_uniformity": len(meeting),  # and the SBR floor, with one
        "seconds": round(time.perf_counter() - start, 1),
    }
    write_json_atomic(out_dir / "sweep.json", {"candidates": candidates})
    write_json_atomic(out_dir / "result.json", result)
    result["candidates"] = candidates
    return result


#: The figures of the chosen candidate's confirmation run copied into the result.
_CONFIRMED_FIGURES = (
    "delivered_fraction",
    "delivered_fraction_stderr",
    "uniformity_cv",
    "uniformity_cv_stderr",
    "uniformity_cv_noise",
    "throughput",
)
#: With robust scoring, the chosen candidate's expected figures (its confirmation run).
_EXPECTED_FIGURES = (
    "expected_delivered_fraction",
    "expected_uniformity_cv_corrected",
    "share_within_max_cv",
    "expected_score",
)


def design_bounds(
    design: SystemDesign, max_cv: float, inputs: tuple[str | None, str | None, str | None], free_aim: bool
) -> dict[str, Any]:
    """The result's bounds for ``design``, their spectral ceiling from the run's inputs: étendue,
    the uniform beam along the units' axes, and with ``free_aim`` re-aimed units with the finite LED."""
    _, spectrum, table = read_inputs(*inputs)
    uniform = uniform_beam_bound(design, max_cv, table, spectrum=spectrum)
    free = free_aim_bound(design, max_cv, table, spectrum=spectrum) if free_aim else None
    return {
        "etendue_bound": etendue_bound(design, table, spectrum=spectrum),
        "uniform_beam_bound": {k: v for k, v in uniform.items() if k not in ("profile", "ring_edges_deg")},
        "free_aim_bound": None if free is None else {k: v for k, v in free.items() if k != "placements"},
    }


def _sweep(
    client: Any,
    base: dict[str, Any],
    parameters: dict[str, tuple[float, float]],
    candidates: list[dict[str, Any]],
    rays: int,
    max_cv: float,
    samples: int,
    rounds: int,
    seed: int,
    threads: int | None,
    show_progress: bool,
    inputs: tuple[str | None, str | None, str | None],
    robust: RobustScoring | None = None,
    sbr_floor: SBRFloor | None = None,
) -> None:
    """A Sobol sweep of the box ``parameters`` (name → range), then ``rounds`` sweeps of a box
    halved each round around the best feasible candidate so far; every evaluated candidate is
    appended to ``candidates`` (as it comes, so that a failure keeps those done)."""
    from rich.progress import Progress

    box = dict(parameters)
    batches = [_sobol(box, samples, seed)]
    with Progress(disable=not show_progress, transient=True) as progress:
        task = progress.add_task("collimator sweep", total=samples + rounds * max(samples // 2, 1))
        for round_index in range(rounds + 1):
            points = batches[-1]
            futures = [
                client.submit(
                    evaluate_candidate, base, p, rays, seed + 1, max_cv, threads, inputs, robust, sbr_floor, pure=False
                )
                for p in points
            ]
            for future in futures:
                candidates.append(future.result())
                progress.advance(task)
            if round_index == rounds:
                break
            ranked = [c for c in candidates if c["feasible"]]
            if not ranked:
                break
            best = max(ranked, key=lambda c: c["score"])
            span = 0.5 ** (round_index + 1)
            box = {}
            for name, (low, high) in parameters.items():
                centre, half = best["parameters"][name], span * (high - low) / 2
                box[name] = (max(low, centre - half), min(high, centre + half))
            batches.append(_sobol(box, max(samples // 2, 1), seed + round_index + 1))


def _confirm_finalists(
    client: Any,
    base: dict[str, Any],
    feasible: list[dict[str, Any]],
    meeting: list[dict[str, Any]],
    rays: int,
    max_cv: float,
    seed: int,
    threads: int | None,
    inputs: tuple[str | None, str | None, str | None],
    check_assembly: bool = False,
    robust: RobustScoring | None = None,
    sbr_floor: SBRFloor | None = None,
) -> tuple[dict[str, Any], dict[str, Any], list[dict[str, Any]] | None]:
    """Re-trace the best ``CONFIRMED`` candidates with 4 × ``rays``; returns the chosen candidate
    (the most light among those confirmed uniform, else the first), its confirmation and, with
    ``check_assembly``, the CAD assembly's interferences of the chosen design (the first of the
    confirmed ones, in order of light, that has none; else the last one checked) — None without.
    With ``check_assembly`` the finalists are the best candidates whose base plate can be printed
    (:func:`base_plate_wall_mm` ≥ ``mechanics.min_wall_mm``; the best one if none can). With
    ``robust`` the candidates are ranked, confirmed and chosen on their expected figures."""
    from cm2optics.cad.assembly import aim_interferences

    pool = meeting or feasible
    if not pool:
        raise ValueError("no candidate could be built: every parameter set was rejected by the profile construction")
    ranked = sorted(pool, key=lambda c: _light(c) if meeting else c["score"], reverse=True)
    finalists = ranked[:CONFIRMED]
    if check_assembly:  # placements whose base plate can be printed, best first (else the best, to report)
        base_design = design_from_dict(base)
        printable = []
        for candidate in ranked:
            if len(printable) == CONFIRMED:
                break
            wall = base_plate_wall_mm(base_design.with_changes(_changes(candidate["parameters"], base_design)))
            candidate["base_plate_min_wall_mm"] = round(wall, 4)
            if wall >= base_design.mechanics.min_wall_mm - 1e-6:
                printable.append(candidate)
        finalists = printable or ranked[:1]
    confirmations = [
        f.result()
        for f in [
            client.submit(
                evaluate_candidate,
                base,
                c["parameters"],
                4 * rays,
                seed + 2,
                max_cv,
                threads,
                inputs,
                robust,
                sbr_floor,
                pure=False,
            )
            for c in finalists
        ]
    ]
    passing = [
        i
        for i, c in enumerate(confirmations)
        if c.get("feasible") and _confirmed_uniform(c, max_cv) and c.get("meets_sbr", True)
    ]
    order = sorted(passing, key=lambda i: _light(confirmations[i]), reverse=True) or [0]
    if not check_assembly:
        return finalists[order[0]], confirmations[order[0]], None
    for i in order:
        clashes = aim_interferences(base_design.with_changes(_changes(finalists[i]["parameters"], base_design)))
        if not clashes:
            break
    return finalists[i], confirmations[i], clashes


def _light(candidate: dict[str, Any]) -> float:
    """A candidate's delivered fraction to rank by: the expected one when it was scored robustly."""
    return candidate.get("expected_delivered_fraction", candidate["delivered_fraction"])


def _meets(candidate: dict[str, Any]) -> bool:
    """Whether a swept candidate meets the constraints: the CV limit, and the SBR floor when one is set."""
    return bool(candidate["meets_uniformity"] and candidate.get("meets_sbr", True))


def _confirmed_uniform(confirmation: dict[str, Any], max_cv: float) -> bool:
    """Whether a confirmation run meets the CV limit: its measured CV (noise included), or when
    scored robustly its expected CV′ (``meets_uniformity``)."""
    if "expected_uniformity_cv_corrected" in confirmation:
        return bool(confirmation["meets_uniformity"])
    return confirmation["uniformity_cv"] <= max_cv


def base_plate_wall_mm(design: SystemDesign) -> float:
    """Thinnest wall of ``design``'s base plate (mm, :func:`cm2optics.cad.mesh_checks.check_mesh`
    on its STL): the units' placement moves its sockets, and some placements leave slivers."""
    import tempfile

    import trimesh

    from cm2optics.cad.base_plate import build_base_plate
    from cm2optics.cad.mesh_checks import check_mesh
    from cm2optics.cad.tessellate import DEFAULT_TOLERANCE_UM, export_stl

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "base_plate.stl"
        export_stl(build_base_plate(design).val(), path, DEFAULT_TOLERANCE_UM / 1000.0)
        return check_mesh(trimesh.load_mesh(path, force="mesh")).min_wall_mm


def trace_built_part(
    design: SystemDesign, out_dir: Path, rays: int, seed: int, inputs: tuple[str | None, str | None, str | None]
) -> dict[str, Any]:
    """Trace the chosen design's CAD part (the exported solid, not the sweep's revolved mesh)
    with the run's inputs, write its irradiance maps (``irradiance.png``) and return its figures."""
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.geometry import build_scene, collimator_from_design
    from cm2optics.illumination.metrics import figures_of_merit, write_maps_png
    from cm2optics.illumination.source import led_source
    from cm2optics.illumination.tracer import trace

    profile, spectrum, table = read_inputs(*inputs)
    scene = build_scene(design, collimator_from_design(design))
    transmission = table if table is not None else design_filter_transmission(design)
    record = trace(scene, led_source(design, profile, spectrum), rays, transmission=transmission, seed=seed)
    figures = figures_of_merit(record, scene)
    maps = write_maps_png(figures, out_dir / "irradiance.png")
    return {
        "maps": str(maps),
        "rays": rays,
        "delivered_fraction": figures.delivered_fraction.value,
        "delivered_fraction_stderr": figures.delivered_fraction.stderr,
        "uniformity_cv": figures.uniformity_cv.value,
        "uniformity_cv_noise": figures.uniformity_cv_noise,
    }


def export_collimator(design: SystemDesign, out_dir: Path) -> tuple[Path, dict[str, Any]]:
    """Write the design's CAD collimator as STL and STEP and check the STL for printing."""
    import trimesh

    from cm2optics.cad.collimator import build_collimator
    from cm2optics.cad.mesh_checks import check_mesh
    from cm2optics.cad.tessellate import DEFAULT_TOLERANCE_UM, export_step, export_stl
    from cm2optics.formats.atomic import write_atomic

    path = out_dir / "collimator.stl"
    part = build_collimator(design)
    solid = part.val()
    write_atomic(path, lambda tmp: export_stl(solid, tmp, DEFAULT_TOLERANCE_UM / 1000.0))
    write_atomic(out_dir / "collimator.step", lambda tmp: export_step(part, tmp))
    report = check_mesh(trimesh.load_mesh(path, force="mesh"))
    min_wall = design.mechanics.min_wall_mm
    checks = {
        "watertight": report.watertight,
        "winding_consistent": report.winding_consistent,
        "volume_mm3": round(report.volume_mm3, 4),
        "min_wall_mm": round(report.min_wall_mm, 4),
        "required_min_wall_mm": min_wall,
        "printable": bool(report.watertight and report.winding_consistent and report.min_wall_mm >= min_wall - 1e-6),
    }
    return path, checks
