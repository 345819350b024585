"""Gradient search of the lens's Zernike terms: Adam on the smooth objective of :mod:`.differentiable`.

Each iteration traces ``rays`` fresh rays (seed ``seed + 1 + k`` at iteration k: a stochastic
gradient, no overfitting to one draw), takes one Adam step of ``learning_rate_um`` µm
(β₁ = 0.9, β₂ = 0.999) on the terms :data:`.optimize.FREEFORM_TERMS`, kept in the sweep's
box (±15 µm). The result is the mean of the iterates of the second half (Polyak averaging:
the iterates' Monte Carlo jitter averages out). Like the sweep it writes ``design.yaml``, the
CAD part (``collimator.stl``, ``.step``, checked for printing), the part's own trace at
4 × ``rays`` (``built_part``, maps in ``irradiance.png``), ``history.json`` (every iteration:
coefficients, smooth figures, gradient, rays traced so far) and ``result.json``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign

__all__ = ["ADAM_BETAS", "lens_terms", "optimize_lens_gradient"]

#: Adam's moment decay rates (β₁, β₂).
ADAM_BETAS = (0.9, 0.999)


def lens_terms(terms: tuple[int, ...], values: np.ndarray, start: np.ndarray, start_piston: float) -> dict[str, float]:
    """The candidate values (:func:`.optimize.candidate_collimator`) setting ``terms`` to ``values``
    (µm), the piston moved from ``start_piston`` so that the lens's rim stays where the terms
    ``start`` had it (:func:`cm2optics.optics.freeform.rim_piston_um`)."""
    from cm2optics.optics.freeform import rim_piston_um

    values = {f"collimator.lens_freeform_um[{j}]": float(v) for j, v in zip(terms, values, strict=True)}
    piston = start_piston + rim_piston_um(terms, [v - s for v, s in zip(values.values(), start, strict=True)])
    return {"collimator.lens_freeform_um[1]": float(piston), **values}


def optimize_lens_gradient(
    design: SystemDesign,
    out_dir: str | Path,
    *,
    rays: int = 100_000,
    iterations: int = 24,
    learning_rate_um: float = 1.5,
    max_cv: float = 0.10,
    seed: int = 0,
    inputs: tuple[str | None, str | None, str | None] = (None, None, None),
    show_progress: bool = True,
) -> dict[str, Any]:
    """Run the search (module docstring) from ``design``'s own lens terms; returns the summary
    (also ``result.json``). inputs: paths of the LED's angular profile, spectrum and the
    excitation filter's coating table (each None: the design's model)."""
    from rich.progress import Progress

    from cm2optics.formats.atomic import write_json_atomic
    from cm2optics.illumination.differentiable import smooth_objective
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.optimize import (
        FREEFORM_PARAMETERS,
        FREEFORM_TERMS,
        candidate_collimator,
        design_bounds,
        export_collimator,
        read_inputs,
        trace_built_part,
    )
    from cm2optics.illumination.source import led_source

    if design.collimator is None:
        raise ValueError(f"design {design.name!r} has no collimator to optimise (use a preset with one, e.g. cm2-v2)")
    terms = FREEFORM_TERMS
    low = np.array([FREEFORM_PARAMETERS[f"collimator.lens_freeform_um[{j}]"][0] for j in terms])
    high = np.array([FREEFORM_PARAMETERS[f"collimator.lens_freeform_um[{j}]"][1] for j in terms])
    own = list(design.collimator.lens_freeform_um) + [0.0] * max(terms)
    c = np.clip(np.array([own[j - 1] for j in terms], dtype=float), low, high)
    c_start, start_piston = c.copy(), float(own[0])
    profile, spectrum, table = read_inputs(*inputs)
    beta1, beta2 = ADAM_BETAS
    m, v = np.zeros_like(c), np.zeros_like(c)
    history: list[dict[str, Any]] = []
    traced = 0
    start = time.perf_counter()
    with Progress(disable=not show_progress, transient=True) as progress:
        task = progress.add_task("gradient search", total=iterations)
        for k in range(iterations):
            candidate, mesh, _ = candidate_collimator(design, lens_terms(terms, c, c_start, start_piston))
            transmission = table if table is not None else design_filter_transmission(candidate)
            figures = smooth_objective(
                candidate,
                mesh,
                led_source(candidate, profile, spectrum),
                transmission,
                terms,
                rays,
                seed=seed + 1 + k,
                max_cv=max_cv,
            )
            traced += figures.rays
            history.append(
                {
                    "iteration": k,
                    "coefficients_um": [round(float(x), 5) for x in c],
                    "objective": figures.objective,
                    "delivered": figures.delivered,
                    "uniformity_cv": figures.cv,
                    "uniformity_cv_noise": figures.cv_noise,
                    "uniformity_cv_corrected": figures.cv_corrected,
                    "gradient": [float(g) for g in figures.gradient],
                    "rays_traced": traced,
                }
            )
            g = -figures.gradient  # Adam minimises −J
            m = beta1 * m + (1 - beta1) * g
            v = beta2 * v + (1 - beta2) * g * g
            m_hat, v_hat = m / (1 - beta1 ** (k + 1)), v / (1 - beta2 ** (k + 1))
            c = np.clip(c - learning_rate_um * m_hat / (np.sqrt(v_hat) + 1e-12), low, high)
            progress.advance(task)
    tail = [h["coefficients_um"] for h in history[len(history) // 2 :]]
    final = np.mean(np.array(tail), axis=0)
    values = lens_terms(terms, final, c_start, start_piston)
    changes = {"collimator.lens_freeform_um": _merged_terms(own, values)}
    name = design.name if design.name.endswith("-optimised") else f"{design.name}-optimised"
    improved = design.with_changes({**changes, "name": name})
    out_dir = Path(out_dir)
    stl_path, checks = export_collimator(improved, out_dir)
    improved.save(out_dir / "design.yaml")
    built = trace_built_part(improved, out_dir, 4 * rays, seed + 2, inputs)
    result = {
        "design": str(out_dir / "design.yaml"),
        "stl": str(stl_path),
        "step": str(out_dir / "collimator.step"),
        "method": "gradient",
        "built_part": built,
        "parameters": {name: round(value, 5) for name, value in values.items()},
        "meets_uniformity": bool(built["uniformity_cv"] <= max_cv),
        "max_cv": max_cv,
        "delivered_fraction": built["delivered_fraction"],
        "delivered_fraction_stderr": built["delivered_fraction_stderr"],
        "uniformity_cv": built["uniformity_cv"],
        "uniformity_cv_noise": built["uniformity_cv_noise"],
        "rays": 4 * rays,
        "iterations": iterations,
        "rays_per_iteration": rays,
        "learning_rate_um": learning_rate_um,
        "rays_traced": traced,
        "printability": checks,
        **design_bounds(improved, max_cv, inputs, False),
        "seconds": round(time.perf_counter() - start, 1),
    }
    write_json_atomic(out_dir / "history.json", {"iterations": history})
    write_json_atomic(out_dir / "result.json", result)
    return result


def _merged_terms(own: list[float], values: dict[str, float]) -> list[float]:
    """The design's Zernike list (µm) with the candidate ``values`` (:func:`lens_terms`) set,
    trailing zeros dropped."""
    merged = list(own)
    for name, value in values.items():
        merged[int(name[len("collimator.lens_freeform_um[") : -1]) - 1] = round(float(value), 5)
    while merged and merged[-1] == 0.0:
        merged.pop()
    return merged
