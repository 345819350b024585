"""Gradient search of the lens's Zernike terms on the smooth objective of :mod:`.differentiable`.

Two step rules on the terms :data:`.optimize.FREEFORM_TERMS`, kept in the sweep's box (±15 µm):

* ``adam``: each iteration traces ``rays`` fresh rays (seed ``seed + 1 + k`` at iteration k: a
  stochastic gradient, no overfitting to one draw) and takes one Adam step of
  ``learning_rate_um`` µm per term (β₁ = 0.9, β₂ = 0.999) on ``J = D − 2 max(0, CV′ − max_cv)``.
  The result is the mean of the iterates of the second half (Polyak averaging).
* ``projected``: every iteration traces the same rays (seed ``seed + 1``: common random numbers,
  so that two iterates' objectives differ by the design, not by the draw) and takes a gradient
  projection step (:func:`projected_step`) of ``learning_rate_um`` µm (Euclidean length) on
  dD/dc, with dCV′/dc kept apart: CV′ ≤ max_cv is a constraint, not a penalty whose gradient,
  ≈ 20 × dD/dc's, would dominate the step. A step whose point scores a lower J than the best
  so far is undone and the length halved; an accepted one grows it by 1.5 (a trust region). The
  result is the best iterate.

Like the sweep it writes ``design.yaml``, the CAD part (``collimator.stl``, ``.step``, checked
for printing), the part's own trace at 4 × ``rays`` (``built_part``, maps in
``irradiance.png``), ``history.json`` (every iteration: coefficients, smooth figures, gradients,
step length, rays traced so far) and ``result.json``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign

__all__ = ["ADAM_BETAS", "STEP_RULES", "lens_terms", "optimize_lens_gradient", "projected_step"]

#: Adam's moment decay rates (β₁, β₂).
ADAM_BETAS = (0.9, 0.999)
#: The search's step rules (module docstring).
STEP_RULES = ("adam", "projected")
#: Factors of the projected rule's step length after an accepted and a rejected step.
_GROW, _SHRINK = 1.5, 0.5


def projected_step(
    gradient_delivered: np.ndarray, gradient_cv: np.ndarray, cv: float, max_cv: float, length_um: float
) -> np.ndarray:
    """One step (µm) of gradient projection for the largest D subject to CV′ ≤ ``max_cv``, both
    linearised: ``length_um`` along dD/dc; when the constraint is active (CV′ > max_cv, or the
    step would take CV′ past it) along dD/dc less its component along dCV′/dc instead, plus the
    Newton step ``−(CV′ − max_cv) ∇CV′/|∇CV′|²`` (at most ``length_um`` long) that lands the
    linearised CV′ on max_cv. Gradients in 1/µm."""
    gd, gc = np.asarray(gradient_delivered, dtype=float), np.asarray(gradient_cv, dtype=float)
    step = length_um * gd / max(float(np.linalg.norm(gd)), 1e-30)
    gc2 = float(gc @ gc)
    excess = cv - max_cv
    if gc2 == 0.0 or (excess <= 0.0 and excess + float(step @ gc) <= 0.0):
        return step
    tangent = gd - float(gd @ gc) / gc2 * gc
    newton = -excess / gc2 * gc
    newton *= min(1.0, length_um / max(float(np.linalg.norm(newton)), 1e-30))
    return length_um * tangent / max(float(np.linalg.norm(tangent)), 1e-30) + newton


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
    step_rule: str = "adam",
    inputs: tuple[str | None, str | None, str | None] = (None, None, None),
    show_progress: bool = True,
) -> dict[str, Any]:
    """Run the search (module docstring; ``step_rule``: one of :data:`STEP_RULES`) from
    ``design``'s own lens terms; returns the summary (also ``result.json``). inputs: paths of
    the LED's angular profile, spectrum and the excitation filter's coating table (each None:
    the design's model)."""
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
    if step_rule not in STEP_RULES:
        raise ValueError(f"step rule {step_rule!r}: must be one of {', '.join(STEP_RULES)}")
    projected = step_rule == "projected"
    terms = FREEFORM_TERMS
    low = np.array([FREEFORM_PARAMETERS[f"collimator.lens_freeform_um[{j}]"][0] for j in terms])
    high = np.array([FREEFORM_PARAMETERS[f"collimator.lens_freeform_um[{j}]"][1] for j in terms])
    own = list(design.collimator.lens_freeform_um) + [0.0] * max(terms)
    c = np.clip(np.array([own[j - 1] for j in terms], dtype=float), low, high)
    c_start, start_piston = c.copy(), float(own[0])
    profile, spectrum, table = read_inputs(*inputs)
    beta1, beta2 = ADAM_BETAS
    m, v = np.zeros_like(c), np.zeros_like(c)
    best: tuple[np.ndarray, Any] | None = None  # projected: the best iterate and its figures
    length = learning_rate_um
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
                seed=seed + 1 + (0 if projected else k),
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
                    "gradient_delivered": [float(g) for g in figures.gradient_delivered],
                    "gradient_cv": [float(g) for g in figures.gradient_cv],
                    "rays_traced": traced,
                }
            )
            if projected:
                if best is None or figures.objective >= best[1].objective:
                    best = (c, figures)
                    length = length * (_GROW if k else 1.0)
                else:
                    length *= _SHRINK
                history[-1]["step_um"] = length
                at, f = best
                c = np.clip(
                    at + projected_step(f.gradient_delivered, f.gradient_cv, f.cv_corrected, max_cv, length), low, high
                )
            else:
                g = -figures.gradient  # Adam minimises −J
                m = beta1 * m + (1 - beta1) * g
                v = beta2 * v + (1 - beta2) * g * g
                m_hat, v_hat = m / (1 - beta1 ** (k + 1)), v / (1 - beta2 ** (k + 1))
                c = np.clip(c - learning_rate_um * m_hat / (np.sqrt(v_hat) + 1e-12), low, high)
            progress.advance(task)
    if projected:
        final = best[0]
    else:
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
        "step_rule": step_rule,
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
