"""Robustness of a built illumination design: a Monte Carlo over manufacturing and assembly errors.

Each sample draws, independently for every LED unit (``numpy.random.default_rng(seed)``):

* **LED placement**: the LED's centre moved in its own plane by ``(dx, dy)``, each uniform in
  ``±led_placement_mm`` (the collimator, housing and filter stay where they are);
* **unit tilt**: the whole unit (LED, collimator, filter, housing) rotated about the LED's
  centre by two angles, about the unit's x and y axes, each uniform in ``±unit_tilt_deg``;
* **printer surface error**: the collimator's surface moved along its vertex normals by a
  smooth random field — :data:`SURFACE_WAVES` plane waves ``cos(k·p + φ)``, directions uniform
  on the sphere, wavelengths log-uniform in :data:`SURFACE_WAVELENGTHS_MM`, phases uniform —
  scaled to ``surface_rms_um`` RMS over the surface. The flat exit face is left as it is (it
  rests on the excitation filter, and its error only changes the air film between them).

Every sample traces the same LED rays (the same trace seed: common random numbers), so the
spread between samples is the errors' effect rather than ray noise; each sample's own Monte
Carlo error is reported beside it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh

from cm2optics.illumination.geometry import CollimatorMesh, IlluminationScene, Role, corner_normals

__all__ = [
    "SURFACE_WAVELENGTHS_MM",
    "SURFACE_WAVES",
    "Tolerances",
    "UnitError",
    "draw_errors",
    "expected_figures",
    "perturbed_figures",
    "perturbed_scene",
    "robustness_study",
    "surface_error",
]

#: Plane waves summed into one random printer surface error.
SURFACE_WAVES = 24
#: Range of the surface error's wavelengths, mm (features of a few hundred µm to the part's size).
SURFACE_WAVELENGTHS_MM = (0.3, 3.0)


@dataclass(frozen=True)
class Tolerances:
    """The error ranges of the Monte Carlo.

    led_placement_mm: LED centre in its plane, ± each of x and y, mm.
    unit_tilt_deg: unit tilt about each of its x and y axes, ± degrees.
    surface_rms_um: RMS of the printer's surface error, µm.
    """

    led_placement_mm: float = 0.05
    unit_tilt_deg: float = 1.0
    surface_rms_um: float = 2.0

    def __post_init__(self) -> None:
        for name in ("led_placement_mm", "unit_tilt_deg", "surface_rms_um"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} = {value}: must be a number ≥ 0")


@dataclass(frozen=True, eq=False)
class UnitError:
    """One unit's drawn errors: LED offset (mm, LED frame), tilt angles about the unit's x and
    y axes (degrees), and its collimator's mesh with the surface error (LED frame; None: nominal)."""

    led_offset_mm: np.ndarray
    tilt_deg: np.ndarray
    collimator: trimesh.Trimesh | None


def _rotation(tilt_deg: np.ndarray) -> np.ndarray:
    """4 × 4 rotation: about x by ``tilt_deg[0]``, then about y by ``tilt_deg[1]`` (degrees)."""
    ax, ay = np.radians(tilt_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    matrix = np.eye(4)
    matrix[:3, :3] = ry @ rx
    return matrix


def surface_error(mesh: trimesh.Trimesh, rms_um: float, rng: np.random.Generator) -> trimesh.Trimesh:
    """``mesh`` (LED frame, mm) with a smooth random normal displacement of ``rms_um`` RMS
    (area-weighted over its vertices), its flat top face (the exit face) kept."""
    vertices = np.asarray(mesh.vertices, dtype=float)
    k_dir = rng.normal(size=(SURFACE_WAVES, 3))
    k_dir /= np.linalg.norm(k_dir, axis=1, keepdims=True)
    low, high = SURFACE_WAVELENGTHS_MM
    wavelength = np.exp(rng.uniform(math.log(low), math.log(high), SURFACE_WAVES))
    phase = rng.uniform(0, 2 * np.pi, SURFACE_WAVES)
    field = np.cos(vertices @ (2 * np.pi * k_dir / wavelength[:, None]).T + phase).sum(axis=1)
    top = vertices[:, 2] >= vertices[:, 2].max() - 1e-6
    field[top] = 0.0
    # Vertex areas: a third of each adjacent face's area.
    area = np.zeros(len(vertices))
    np.add.at(area, np.asarray(mesh.faces).ravel(), np.repeat(mesh.area_faces / 3.0, 3))
    rms = math.sqrt(np.sum(area * field**2) / np.sum(area))
    displaced = vertices + (1e-3 * rms_um / rms) * field[:, None] * np.asarray(mesh.vertex_normals)
    return trimesh.Trimesh(displaced, np.asarray(mesh.faces), process=False)


def draw_errors(
    collimator: CollimatorMesh, units: int, tolerances: Tolerances, rng: np.random.Generator
) -> list[UnitError]:
    """One Monte Carlo sample's errors for every unit."""
    errors = []
    for _ in range(units):
        offset = rng.uniform(-1, 1, 2) * tolerances.led_placement_mm
        tilt = rng.uniform(-1, 1, 2) * tolerances.unit_tilt_deg
        mesh = surface_error(collimator.mesh, tolerances.surface_rms_um, rng) if tolerances.surface_rms_um > 0 else None
        errors.append(UnitError(offset, tilt, mesh))
    return errors


def _place(matrix: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    return vertices @ matrix[:3, :3].T + matrix[:3, 3]


def perturbed_scene(scene: IlluminationScene, errors: list[UnitError]) -> IlluminationScene:
    """``scene`` with each unit's errors: its parts turned by its tilt about the LED's centre,
    its collimator replaced by the mesh with the surface error, its LED moved by the offset."""
    if len(errors) != scene.units:
        raise ValueError(f"{len(errors)} unit errors for {scene.units} units")
    poses = scene.poses.copy()
    moves = []
    for unit, error in enumerate(errors):
        tilted = scene.poses[unit] @ _rotation(error.tilt_deg)
        moves.append((tilted, tilted @ np.linalg.inv(scene.poses[unit])))
        shift = np.eye(4)
        shift[:2, 3] = error.led_offset_mm
        poses[unit] = tilted @ shift
    parts = []
    for part in scene.parts:
        if part.unit < 0:
            parts.append(part)
            continue
        tilted, move = moves[part.unit]
        mesh = errors[part.unit].collimator
        if part.role == Role.DIELECTRIC and part.name.startswith("collimator") and mesh is not None:
            vertices = np.asarray(mesh.vertices, dtype=float)
            faces = np.asarray(mesh.faces, dtype=np.int64)
            normals = None
            if part.corner_normals is not None:
                normals = corner_normals(vertices, faces, scene.collimator.face_ids) @ tilted[:3, :3].T
            parts.append(
                dataclasses.replace(part, vertices_mm=_place(tilted, vertices), faces=faces, corner_normals=normals)
            )
            continue
        normals = None if part.corner_normals is None else part.corner_normals @ move[:3, :3].T
        parts.append(dataclasses.replace(part, vertices_mm=_place(move, part.vertices_mm), corner_normals=normals))
    return dataclasses.replace(scene, parts=tuple(parts), poses=poses)


def _figures(scene: IlluminationScene, setup: Any) -> dict[str, float]:
    from cm2optics.illumination.metrics import figures_of_merit
    from cm2optics.illumination.tracer import trace

    record = trace(
        scene, setup.source, setup.rays, transmission=setup.transmission, seed=setup.seed, max_bounces=setup.max_bounces
    )
    figures = figures_of_merit(record, scene, bin_mm=setup.bin_mm)
    return {
        "delivered_fraction": figures.delivered_fraction.value,
        "delivered_fraction_stderr": figures.delivered_fraction.stderr,
        "uniformity_cv": figures.uniformity_cv.value,
        "uniformity_cv_stderr": figures.uniformity_cv.stderr,
        "uniformity_cv_noise": figures.uniformity_cv_noise,
        "uniformity_cv_corrected": math.sqrt(max(figures.uniformity_cv.value**2 - figures.uniformity_cv_noise**2, 0.0)),
    }


def _mean_sd(values: list[float]) -> dict[str, float]:
    array = np.asarray(values, dtype=float)
    return {"mean": float(array.mean()), "sd": float(array.std(ddof=1)) if array.size > 1 else 0.0}


def perturbed_figures(
    scene: IlluminationScene,
    setup: Any,
    tolerances: Tolerances,
    samples: int,
    seed: int,
    advance: Callable[[], None] | None = None,
) -> list[dict[str, Any]]:
    """The figures of ``samples`` perturbed copies of ``scene`` (see the module docstring), each
    with its drawn LED offsets and tilts; the errors come from ``numpy.random.default_rng(seed)``,
    so the same seed draws the same errors for any design (common random numbers).
    ``advance`` is called after each trace (a progress bar)."""
    if scene.collimator is None:
        raise ValueError("the scene has no collimator: nothing to perturb but the LED (use a design with one)")
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(samples):
        errors = draw_errors(scene.collimator, scene.units, tolerances, rng)
        figures = _figures(perturbed_scene(scene, errors), setup)
        figures["led_offset_mm"] = [[round(float(v), 5) for v in e.led_offset_mm] for e in errors]
        figures["tilt_deg"] = [[round(float(v), 4) for v in e.tilt_deg] for e in errors]
        rows.append(figures)
        if advance is not None:
            advance()
    return rows


def expected_figures(rows: list[dict[str, Any]], max_cv: float) -> dict[str, float]:
    """The expected figures of perturbed samples (:func:`perturbed_figures`): the mean delivered
    fraction, the mean CV without the Monte Carlo noise floor (CV′), the share of samples with
    CV′ ≤ ``max_cv`` and the score ``E[D] − 2 max(0, E[CV′] − max_cv)`` (the sweep's ranking on
    the expected values)."""
    delivered = float(np.mean([r["delivered_fraction"] for r in rows]))
    cv_corrected = np.asarray([r["uniformity_cv_corrected"] for r in rows], dtype=float)
    mean_cv = float(cv_corrected.mean())
    return {
        "expected_delivered_fraction": delivered,
        "expected_uniformity_cv_corrected": mean_cv,
        "share_within_max_cv": float(np.mean(cv_corrected <= max_cv)),
        "expected_score": delivered - 2.0 * max(0.0, mean_cv - max_cv),
    }


def robustness_study(
    scene: IlluminationScene,
    setup: Any,
    tolerances: Tolerances,
    samples: int,
    seed: int,
    advance: Callable[[], None] | None = None,
    max_cv: float = 0.10,
) -> dict[str, Any]:
    """The nominal scene's figures and ``samples`` perturbed ones (see the module docstring),
    with the mean ± sd of the delivered fraction and the CV (as measured, and with each
    sample's Monte Carlo noise floor taken out in quadrature: ``uniformity_cv_corrected``) and
    the share of samples whose corrected CV is ≤ ``max_cv``. ``setup``: the :class:`~cm2optics.illumination.compare.Setup` of the traces.
    ``advance`` is called after each trace (a progress bar)."""
    if samples < 2:
        raise ValueError(f"samples = {samples}: must be ≥ 2 for a spread")
    nominal = _figures(scene, setup)
    if advance is not None:
        advance()
    rows = perturbed_figures(scene, setup, tolerances, samples, seed, advance)
    delivered = [r["delivered_fraction"] for r in rows]
    cv = [r["uniformity_cv"] for r in rows]
    cv_corrected = [r["uniformity_cv_corrected"] for r in rows]
    return {
        "label": scene.label,
        "tolerances": dataclasses.asdict(tolerances),
        "surface_error_model": {"waves": SURFACE_WAVES, "wavelengths_mm": list(SURFACE_WAVELENGTHS_MM)},
        "samples": samples,
        "seed": seed,
        "rays": setup.rays,
        "nominal": nominal,
        "delivered_fraction": _mean_sd(delivered),
        "uniformity_cv": _mean_sd(cv),
        "uniformity_cv_corrected": _mean_sd(cv_corrected),
        "share_within_max_cv": expected_figures(rows, max_cv)["share_within_max_cv"],
        "max_cv": max_cv,
        "per_sample": rows,
    }


def write_robustness_png(study: dict[str, Any], path: Any) -> Any:
    """One PNG: every sample's delivered fraction against its CV (without the Monte Carlo noise
    floor), the nominal design marked."""
    from pathlib import Path

    from matplotlib.figure import Figure

    from cm2optics.formats.atomic import write_atomic

    fig = Figure(figsize=(6, 4.4), constrained_layout=True)
    ax = fig.subplots()
    rows = study["per_sample"]
    ax.scatter(
        [100 * r["uniformity_cv_corrected"] for r in rows],
        [r["delivered_fraction"] for r in rows],
        s=14,
        label="samples",
    )
    nominal = study["nominal"]
    ax.scatter(
        [100 * nominal["uniformity_cv_corrected"]],
        [nominal["delivered_fraction"]],
        marker="*",
        s=160,
        c="k",
        label="as designed",
    )
    ax.axvline(100 * study["max_cv"], color="grey", ls="--", lw=1)
    ax.set_xlabel("uniformity CV without the Monte Carlo noise floor (%)")
    ax.set_ylabel("delivered fraction")
    tol = study["tolerances"]
    ax.set_title(
        f"{study['label']}: LED ±{1e3 * tol['led_placement_mm']:g} µm, tilt ±{tol['unit_tilt_deg']:g}°, "
        f"surface {tol['surface_rms_um']:g} µm RMS",
        fontsize=9,
    )
    ax.legend()
    path = Path(path)
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    return path
