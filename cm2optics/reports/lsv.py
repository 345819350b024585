"""Figures and report sections for the LSV model.

:func:`write_build_figures` writes, next to a model: the approximation error against K
(``nmse_vs_rank.png``), the first basis PSFs as 3×3 focus arrays (``basis.png``), the first
coefficient maps on the calibration grid and interpolated in x, y and z (``coefficients.png``)
and the fitted geometry (``geometry.png``: axial shear of every lenslet and the magnification
against depth). :func:`add_lsv_section` builds a model from a scan for ``cm2 demo`` and shows a
simulated measurement.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from cm2optics.design import SystemDesign
from cm2optics.formats.atomic import write_atomic, write_json_atomic
from cm2optics.lsv.build import BuildResult
from cm2optics.lsv.model import LSVModel
from cm2optics.reports.document import Report

__all__ = [
    "FIGURES",
    "add_lsv_section",
    "heldout_positions",
    "heldout_rows",
    "write_build_figures",
    "write_build_report",
]

FIGURES = {
    "nmse_vs_rank.png": "Approximation error of the truncated SVD on the calibration set against the number of basis PSFs K",
    "basis.png": "The first basis PSFs, each a 3×3 array of registered foci (one patch per lenslet)",
    "coefficients.png": "The first coefficient maps: on the calibration grid, interpolated laterally (focal plane) and in x–z (y = 0)",
    "geometry.png": "Fitted geometry: axial shear of each lenslet's focus, and the magnification against depth",
}


def _save(fig: Figure, path: Path) -> None:
    write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight"))


def _mosaic(patches: np.ndarray, rows: int, cols: int) -> np.ndarray:
    J, h, w = patches.shape
    out = np.full((rows * (h + 1) - 1, cols * (w + 1) - 1), np.nan)
    for j in range(J):
        r, c = divmod(j, cols)
        out[r * (h + 1) : r * (h + 1) + h, c * (w + 1) : c * (w + 1) + w] = patches[j]
    return out


def plot_nmse(model: LSVModel, path: Path) -> None:
    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot()
    k = np.arange(1, len(model.nmse))
    ax.loglog(k, np.maximum(model.nmse[1:], 1e-12), label="‖X − X_K‖² / ‖X‖² (whole scan)")
    if len(model.nmse_per_psf) == len(model.nmse):
        ax.loglog(k, np.maximum(model.nmse_per_psf[1:], 1e-12), "--", label="mean per-position NMSE")
    ax.axvline(model.rank, color="k", lw=0.8)
    ax.axhline(0.025, color="gray", lw=0.8, ls=":", label="0.025 (paper, K = 64)")
    ax.set_xlabel("K (basis PSFs)")
    ax.set_ylabel("NMSE on the calibration set")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    _save(fig, path)


def plot_basis(model: LSVModel, path: Path, count: int = 8) -> None:
    count = min(count, model.rank)
    fig = Figure(figsize=(2.4 * min(count, 4), 2.4 * ((count + 3) // 4)))
    for k in range(count):
        ax = fig.add_subplot((count + 3) // 4, min(count, 4), k + 1)
        mosaic = _mosaic(model.basis[k], model.geometry.rows, model.geometry.cols)
        limit = np.nanmax(np.abs(mosaic)) or 1.0
        ax.imshow(mosaic, cmap="RdBu_r", vmin=-limit, vmax=limit)
        ax.set_title(f"basis {k + 1}", fontsize=9)
        ax.set_axis_off()
    _save(fig, path)


def plot_coefficients(model: LSVModel, path: Path, count: int = 4) -> None:
    count = min(count, model.rank)
    xs, ys, zs = model.axes
    iz = int(np.argmin(np.abs(zs)))
    fine_x = np.linspace(xs[0], xs[-1], 120)
    fine_y = np.linspace(ys[0], ys[-1], 120)
    fine_z = np.linspace(zs[0], zs[-1], 60)
    fig = Figure(figsize=(3.0 * count, 8.4))
    for k in range(count):
        coarse = model.coefficients[k, iz]
        # the central lenslet's, as every path interpolates them (along its focal surface if any)
        centre = model.n_lenslets // 2
        lateral = model.coefficients_at(
            fine_x[None, :], fine_y[:, None], np.full((len(fine_y), len(fine_x)), zs[iz]), lenslet=centre
        )[..., k]
        section = model.coefficients_at(
            fine_x[None, :], np.zeros((len(fine_z), len(fine_x))), fine_z[:, None], lenslet=centre
        )[..., k]
        for row, (data, extent, title, labels) in enumerate(
            (
                (coarse, (xs[0], xs[-1], ys[-1], ys[0]), f"k = {k + 1}: grid, z = {zs[iz]:g} mm", ("x mm", "y mm")),
                (lateral, (xs[0], xs[-1], ys[-1], ys[0]), "central lenslet, interpolated in x, y", ("x mm", "y mm")),
                (section, (xs[0], xs[-1], zs[-1], zs[0]), "central lenslet, in x, z (y = 0)", ("x mm", "z mm")),
            )
        ):
            ax = fig.add_subplot(3, count, row * count + k + 1)
            limit = float(np.max(np.abs(data))) or 1.0
            ax.imshow(
                data, cmap="RdBu_r", vmin=-limit, vmax=limit, extent=extent, aspect="auto", interpolation="nearest"
            )
            ax.set_title(title, fontsize=8)
            ax.set_xlabel(labels[0], fontsize=7)
            ax.set_ylabel(labels[1], fontsize=7)
            ax.tick_params(labelsize=6)
    fig.tight_layout()
    _save(fig, path)


def plot_geometry(model: LSVModel, path: Path) -> None:
    zs = np.linspace(model.grid_z_mm[0], model.grid_z_mm[-1], 50)
    shear = model.geometry.offsets(zs) - model.geometry.offsets(0.0)[None]
    A = model.geometry.A(zs)
    magnification = np.sqrt(np.abs(np.linalg.det(A))) * model.pixel_um / 1000.0
    fig = Figure(figsize=(11, 3.6))
    for axis, name in enumerate(("row", "column")):
        ax = fig.add_subplot(1, 3, axis + 1)
        for j in range(model.n_lenslets):
            ax.plot(zs, shear[:, j, axis], label=f"lenslet {j + 1}")
        ax.set_xlabel("z (mm, + towards the device)")
        ax.set_ylabel(f"shear along {name}s (px)")
        ax.grid(alpha=0.3)
    fig.axes[0].legend(fontsize=6, ncol=2)
    ax = fig.add_subplot(1, 3, 3)
    ax.plot(zs, magnification)
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("lateral magnification |m|")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)


def write_build_figures(model: LSVModel, folder: Path) -> dict[str, str]:
    """Write the four build figures into ``folder``; returns {file name: caption}."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    plot_nmse(model, folder / "nmse_vs_rank.png")
    plot_basis(model, folder / "basis.png")
    plot_coefficients(model, folder / "coefficients.png")
    plot_geometry(model, folder / "geometry.png")
    return dict(FIGURES)


def _summary_rows(summary: dict[str, Any]) -> list[list[object]]:
    rows = [
        ["rank K", summary["rank"]],
        ["NMSE on the calibration set (whole scan)", f"{summary['nmse_calibration']:.4g}"],
        ["mean per-position NMSE", f"{summary['nmse_calibration_per_psf']:.4g}"],
        ["NMSE of the truncated SVD (before the nodes' fluxes are kept)", f"{summary['nmse_calibration_svd']:.4g}"],
        ["numerical rank (σ > 1e-4 σ₁)", summary["numerical_rank"]],
        ["positions", summary["n_positions"]],
        ["patch per focus (px)", "×".join(str(v) for v in summary["patch_px"])],
        [
            "default grid (z, y, x)",
            f"{summary['default_grid']['shape']} × {[round(v, 3) for v in summary['default_grid']['voxel_um']]} µm",
        ],
    ]
    geometry = summary.get("geometry", {})
    for key in (
        "magnification_at_focus",
        "native_lateral_um",
        "lattice_pitch_px",
        "shear_rms_residual_px",
        "alignment",
    ):
        if key in geometry:
            rows.append([key.replace("_", " "), geometry[key]])
    return rows


def write_build_report(result: BuildResult, folder: Path) -> Path:
    """Figures, ``summary.json``, ``report.md`` and ``report.html`` of a build into ``folder``."""
    folder = Path(folder)
    figures = write_build_figures(result.model, folder)
    summary = result.summary()
    write_json_atomic(folder / "summary.json", summary)
    report = Report("3D-LSV model")
    report.heading("Summary")
    report.table(["quantity", "value"], _summary_rows(summary))
    report.table(
        ["K", "NMSE (whole scan)", "mean per position"],
        [[k, f"{v:.4g}", f"{summary['nmse_per_psf_vs_rank'][k]:.4g}"] for k, v in summary["nmse_vs_rank"].items()],
    )
    for name, caption in figures.items():
        report.figure(name, caption)
    return report.write(folder)


def add_lsv_section(
    report: Report,
    design: SystemDesign,
    scan_dir: str | Path | None,
    out_dir: str | Path,
    *,
    rank: int = 64,
    title: str = "3D-LSV forward model",
    oversample: int = 1,
    traced: Callable[[tuple[float, float, float]], np.ndarray] | None = None,
) -> dict[str, Any]:
    """Build an LSV model from ``scan_dir`` (a small analytic scan is made when it is None),
    write its figures and a simulated measurement of random emitters into ``out_dir/lsv``, and
    add a section to ``report``; returns the numbers shown.

    oversample: S of the model's effective-PSF basis (the scan needs its ``epsf.h5``).
    traced: position (x, y, z mm) → the traced image of a point there in the model's units; when
    given, the model (and its whole-pixel twin) are checked against traced points between the
    nodes (:func:`heldout_rows`)."""
    from cm2optics.formats.emitters import Emitters
    from cm2optics.lsv.build import build_model

    folder = Path(out_dir) / "lsv"
    folder.mkdir(parents=True, exist_ok=True)
    source = f"the scan {Path(scan_dir).name}" if scan_dir is not None else ""
    if scan_dir is None:
        from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan

        binning = 8
        analytic = AnalyticCM2.from_design(design, binning=binning, sigma0_um=design.sensor.pixel_um * binning)
        scan_dir = write_analytic_scan(
            folder / "scan",
            analytic,
            np.linspace(-4, 4, 9),
            np.linspace(-4, 4, 9),
            np.linspace(-0.5, 0.5, 11),
            binning=binning,
        )
        source = "a 9×9×11 analytic CM²-like scan (binned 8×; cm2optics.lsv.toy)"
    start = time.perf_counter()
    result = build_model(scan_dir, rank=rank, design=design, oversample=oversample)
    build_seconds = time.perf_counter() - start
    model = result.model
    model.save(folder / "model.h5")
    figures = write_build_figures(model, folder)
    summary = result.summary()
    rng = np.random.default_rng(0)
    n = 300
    radius = 3.5 * np.sqrt(rng.random(n))
    angle = 2 * np.pi * rng.random(n)
    zs = model.grid_z_mm
    emitters = Emitters(
        radius * np.cos(angle) * 1000,
        radius * np.sin(angle) * 1000,
        rng.uniform(zs[0], zs[-1], n) * 800,
        rng.uniform(10, 20, n),
        rng.uniform(0.5, 1.0, n),
    )
    start = time.perf_counter()
    image = model.forward_sparse(emitters)
    sparse_seconds = time.perf_counter() - start
    fig = Figure(figsize=(8, 5.4))
    ax = fig.add_subplot()
    ax.imshow(image, cmap="gray", vmax=float(np.percentile(image, 99.9)) or None)
    ax.set_title(f"simulated measurement: {n} emitters (10–20 µm) through the 3D-LSV model")
    ax.set_axis_off()
    _save(fig, folder / "measurement.png")
    report.heading(title)
    report.paragraph(
        f"Built from {source} in {build_seconds:.1f} s: foci cropped around their chief rays, axial shear undone, "
        f"truncated SVD with K = {model.rank}, coefficients interpolated in x, y and z along each lenslet's chief rays."
    )
    report.table(["quantity", "value"], _summary_rows(summary))
    for name, caption in figures.items():
        report.figure(f"lsv/{name}", caption)
    report.paragraph(f"{n} random emitters rendered by the sparse path in {sparse_seconds:.2f} s.")
    report.figure("lsv/measurement.png", "A measurement simulated with the model (no noise)")
    numbers = {"build_seconds": build_seconds, "sparse_seconds": sparse_seconds, **summary}
    if traced is not None:
        models = {f"oversample {oversample} (this model)": model}
        if oversample > 1:
            models["oversample 1 (whole pixels)"] = build_model(scan_dir, rank=rank, design=design).model
        rows, errors = heldout_rows(models, traced)
        report.paragraph(
            "Between the nodes, against the emission tracer: single 2-µm beads at seeded random positions that "
            "are not on the calibration grid, traced through the design (`cm2 psf image`) and rendered by the model; "
            "error ‖m − t‖/‖t‖ with the flux included (`benchmarks/bench_lsv_heldout.py` does the same at "
            "full scale; `BENCHMARKS.md`)."
        )
        report.table(["position (x, y, z mm)", *models], rows)
        numbers["heldout_error"] = errors
    return numbers


def heldout_positions(model: LSVModel, count: int = 4, seed: int = 0) -> list[tuple[float, float, float]]:
    """``count`` seeded positions (x, y, z mm) between ``model``'s nodes: radii spread from the
    axis to 3/4 of the grid's half-width, depths in the inner 80 % of its depth range."""
    rng = np.random.default_rng(seed)
    xs, _, zs = model.axes
    reach = 0.75 * min(abs(xs[0]), abs(xs[-1]))
    depth = zs[-1] - zs[0]
    out = []
    for r in np.linspace(0.0, reach, count):
        angle = rng.uniform(0, 2 * np.pi)
        z = rng.uniform(zs[0] + 0.1 * depth, zs[-1] - 0.1 * depth)
        r = max(float(r), 0.02)  # off the axis node too
        out.append((round(r * np.cos(angle), 4), round(r * np.sin(angle), 4), round(float(z), 4)))
    return out


def heldout_rows(
    models: dict[str, LSVModel], traced: Callable[[tuple[float, float, float]], np.ndarray]
) -> tuple[list[list[str]], dict[str, list[float]]]:
    """Error of each of ``models`` against ``traced`` points at :func:`heldout_positions` of the
    first model: the table's rows and {model name: errors}."""
    from cm2optics.lsv.validate import image_errors

    positions = heldout_positions(next(iter(models.values())))
    errors: dict[str, list[float]] = {name: [] for name in models}
    rows = []
    for position in positions:
        truth = traced(position)
        row = [", ".join(f"{v:+.3f}" for v in position)]
        for name, model in models.items():
            error = image_errors(model.point_image(*position), truth)["error"]
            errors[name].append(error)
            row.append(f"{error:.3f}")
        rows.append(row)
    return rows, errors
