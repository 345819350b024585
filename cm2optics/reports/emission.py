"""The PSF section of ``cm2 demo``: a small synthetic scan, its montage, and the key numbers.

:func:`add_psf_section` simulates a 3 × 3 × 3 scan (±2 mm, ±0.5 mm, binning 4) with the
calibration pinhole, and measures on the model: magnification and object pixel against the
design, the axial shear of a side focus against paraxial optics, the on-axis focus against
the diffraction limit (at the design's focal plane, the best focus, and at the paraxial plane), the
vignetting radius
and the energy fall-off at the edge of the field. About a minute on two cores.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.emission import analysis
from cm2optics.emission.psf import EmissionModel, PSFSettings
from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, simulate_scan
from cm2optics.emission.source import calibration_pinhole, fluorescent_bead
from cm2optics.formats.atomic import write_atomic
from cm2optics.optics import first_order
from cm2optics.reports.document import Report

__all__ = ["CHAIN_SCAN", "add_psf_section", "psf_numbers", "simulate_chain_scan"]

#: The demo's calibration scan for the 3D-LSV model of section 6 (one chain: design → traced scan
#: → model → synthetic data → reconstruction): a 7 × 7 × 3 grid over ±3.5 mm and ±0.3 mm of
#: 2-µm fluorescent beads, binned 8×, with the 4× effective PSFs beside the frames.
CHAIN_SCAN = {"counts": (7, 7, 3), "field_mm": 7.0, "depth_mm": 0.6, "binning": 8, "oversample": 4, "bead_um": 2.0}


def psf_numbers(design: SystemDesign, binning: int = 4) -> dict[str, float]:
    """The key numbers of the emission model of ``design`` (see the module docstring)."""
    fine = EmissionModel(design, calibration_pinhole(), settings=PSFSettings(binning=1))
    coarse = EmissionModel(design, calibration_pinhole(), settings=PSFSettings(binning=binning))
    magnification = analysis.measured_magnification(fine)
    cells = fine.optics.lenslets
    side = max(fine._visible, key=lambda k: cells[k].vertex_x_mm - abs(cells[k].vertex_y_mm))  # the +x lenslet
    shear = analysis.measured_shear(fine, side, np.array([-0.5, 0.0, 0.5]))[0]
    shear_paraxial = analysis.paraxial_shear(fine, side)[0]
    fine.foci((0.0, 0.0, 0.0))  # warm-up (kernels compiled, tables built)
    times = []
    for _ in range(3):
        start = time.perf_counter()
        fine.foci((0.0, 0.0, 0.0))
        times.append(time.perf_counter() - start)
    per_position = min(times)
    paraxial = analysis.on_axis_focus(fine, -first_order.focus_shift_mm(design))
    best_z = analysis.best_focus_z_mm(fine)
    best = analysis.on_axis_focus(fine, 0.0)
    return {
        "magnification": magnification,
        "magnification_design": first_order.magnification(design),
        "object_pixel_um": design.sensor.pixel_um / magnification,
        "object_pixel_um_design": first_order.object_pixel_um(design),
        "shear_side_focus": shear,
        "shear_paraxial": shear_paraxial,
        "paraxial_plane_z_mm": -first_order.focus_shift_mm(design),
        "fwhm_paraxial_um": paraxial.fwhm_um,
        "strehl_paraxial": paraxial.strehl,
        "best_focus_z_mm": best_z,
        "fwhm_best_um": best.fwhm_um,
        "fwhm_diffraction_um": best.ideal_fwhm_um,
        "strehl_best": best.strehl,
        "image_na": best.na,
        "vignetting_radius_y_mm": analysis.vignetting_radius_mm(coarse, 90.0, step_mm=0.1, max_mm=2.5, start_mm=1.0),
        "vignetting_radius_x_mm": analysis.vignetting_radius_mm(coarse, 0.0, step_mm=0.1, max_mm=2.5, start_mm=1.0),
        "edge_energy": analysis.relative_energy(coarse, (design.volume.field_mm / 2, 0.0, 0.0)),
        "seconds_per_position_b1": per_position,
    }


def _z_stack_figure(model: EmissionModel, path: Path, zs: np.ndarray) -> Path:
    from matplotlib.figure import Figure

    k = analysis.central_lenslet(model)
    fig = Figure(figsize=(1.9 * len(zs), 2.2))
    axes = fig.subplots(1, len(zs))
    for ax, z in zip(np.atleast_1d(axes), zs, strict=True):
        focus = model.foci((0.0, 0.0, float(z)), lenslets=[k])[0]
        r, c = focus.centroid_px()
        r, c = int(round(r)) - focus.row0, int(round(c)) - focus.col0
        half = 12
        crop = focus.patch[max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1]
        ax.imshow(np.sqrt(crop / crop.max()), cmap="magma", interpolation="nearest")
        ax.set_title(f"z = {z:+.2f} mm", fontsize=8)
        ax.axis("off")
    fig.suptitle(
        f"central focus of an on-axis source ({model.grid.pitch_mm * 1000:.1f}-µm pixels, √ intensity)", fontsize=8
    )
    fig.tight_layout()
    return write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


def _numbers_rows(n: dict) -> list[list[str]]:
    """The PSF section's table: the model's magnification, pixel, shear, FWHMs (µm), focus and
    vignetting (mm), edge energy and speed, each against its reference."""
    return [
        ["magnification |m| at z = 0", f"{n['magnification']:.4f}", f"{n['magnification_design']:.4f} (design)"],
        [
            "object pixel (µm)",
            f"{n['object_pixel_um']:.3f}",
            f"{n['object_pixel_um_design']:.3f} (design), 4.15 (paper)",
        ],
        [
            "axial shear of a side focus (mm/mm)",
            f"{n['shear_side_focus']:.4f}",
            f"{n['shear_paraxial']:.4f} (paraxial)",
        ],
        [
            f"on-axis FWHM at the paraxial plane, z = {n['paraxial_plane_z_mm']:+.2f} mm (µm, sensor)",
            f"{n['fwhm_paraxial_um']:.2f}",
            f"Strehl {n['strehl_paraxial']:.3f}",
        ],
        [
            "best focus of the model (mm from the focal plane)",
            f"{n['best_focus_z_mm']:+.2f}",
            "0: the design's focal plane is the least RMS wavefront error",
        ],
        [
            "on-axis FWHM at z = 0, best focus (µm, sensor)",
            f"{n['fwhm_best_um']:.2f}",
            f"{n['fwhm_diffraction_um']:.2f} (diffraction limit, NA' {n['image_na']:.3f})",
        ],
        [
            "vignetting radius (mm; x, y)",
            f"{n['vignetting_radius_x_mm']:.1f}, {n['vignetting_radius_y_mm']:.1f}",
            "≈ 1.7 (paper: side foci missing beyond)",
        ],
        [
            "central-focus energy at the field edge",
            f"{n['edge_energy'] * 100:.0f} %",
            "≈ 15 % (paper: drops ≈ 85 %)",
        ],
        ["one position, full sensor (s)", f"{n['seconds_per_position_b1']:.2f}", "≤ 1 s target"],
    ]


def simulate_chain_scan(design: SystemDesign, folder: str | Path) -> tuple[dict, float]:
    """Trace :data:`CHAIN_SCAN` of ``design`` into ``folder``; returns (manifest, seconds)."""
    c = CHAIN_SCAN
    start = time.perf_counter()
    settings = ScanSettings(
        psf=PSFSettings(binning=c["binning"], oversample=c["oversample"]), source=fluorescent_bead(c["bead_um"])
    )
    positions = calibration_grid_mm(design, c["counts"], field_mm=c["field_mm"], depth_mm=c["depth_mm"])
    manifest = simulate_scan(design, positions, folder, settings, workers=1, processes=False, progress=False)
    return manifest, time.perf_counter() - start


def add_psf_section(
    report: Report, design: SystemDesign, out_dir: str | Path, title: str = "PSFs and calibration scans"
) -> Path:
    """Simulate a small PSF scan into ``out_dir/psf-scan`` and the chain's calibration scan
    (:data:`CHAIN_SCAN`) into ``out_dir/psf-calibration``, and add their section to ``report``;
    returns the calibration scan's folder."""
    out_dir = Path(out_dir)
    start = time.perf_counter()
    settings = ScanSettings(psf=PSFSettings(binning=4), source=calibration_pinhole())
    positions = calibration_grid_mm(design, (3, 3, 3), field_mm=4.0)
    # In this process (one Dask worker thread): a 27-position scan does not repay starting worker processes.
    manifest = simulate_scan(
        design, positions, out_dir / "psf-scan", settings, workers=1, processes=False, progress=False
    )
    scan_s = time.perf_counter() - start
    numbers = psf_numbers(design)
    model = EmissionModel(design, calibration_pinhole(), settings=PSFSettings(binning=1))
    _z_stack_figure(
        model, out_dir / "psf_focus_through_z.png", np.array([-0.5, 0.0, 0.5, numbers["paraxial_plane_z_mm"]])
    )
    report.heading(title)
    report.paragraph(
        "Point sources traced through the emission filter (angle-shifted passband per ray), mask, housing bore, "
        "spherical lenslets and absorption film to the sensor (Dr.Jit float64 ray trace, housing as a Mitsuba "
        "scene); each lenslet's wavefront on its reference sphere gives its PSF by the Debye–Wolf "
        "integral (FFT), per 10-nm band weighted by fluorophore emission × filters × sensor QE; lenslets with "
        "more than 5 waves RMS of aberration use the geometric branch. Source: the paper's 5-µm pinhole with a "
        "Gaussian emission profile (1/e² half-angle 26°)."
    )
    report.paragraph(
        f"Scan: {len(positions)} positions (3 × 3 × 3 over ±2 mm, ±0.5 mm; binning 4) in {scan_s:.1f} s on Dask "
        f"({manifest['timings']['per_position_s_mean']:.2f} s per position per worker). Format: positions.csv, 16-bit "
        "TIFFs, scan.yaml (cm2optics.formats.scan), read back with read_scan. The full 9 × 9 × 11 calibration: "
        "`cm2 psf simulate --preset cm2-v2 --grid 9x9x11 --binning 2`."
    )
    report.table(["quantity", "model", "reference"], _numbers_rows(numbers))
    report.figure("psf-scan/montage.png", "Synthetic PSF scan, focal plane: each tile one source position (x, y in mm)")
    report.figure(
        "psf_focus_through_z.png",
        "Central focus of an on-axis source through depth (z = 0: best focus), and at the paraxial plane",
    )
    calibration = out_dir / "psf-calibration"
    chain, chain_s = simulate_chain_scan(design, calibration)
    c = CHAIN_SCAN
    report.paragraph(
        f"The calibration scan the rest of this demo is built on: {chain['inputs']['positions']} positions "
        f"({' × '.join(map(str, c['counts']))} over ±{c['field_mm'] / 2:g} mm and ±{c['depth_mm'] / 2:g} mm) of a "
        f"{c['bead_um']:g}-µm fluorescent bead (isotropic, as a lab's bead scan), binned {c['binning']}×, with each "
        f"position's effective PSF on a {c['oversample']}× finer grid (`epsf.h5`) — {chain_s:.1f} s. Sections 6 and 7 "
        "build the 3D-LSV model from it and simulate and reconstruct through that model: one chain from the design "
        f"to the volume. The same command: `cm2 psf simulate --grid {'x'.join(map(str, c['counts']))} --field-mm "
        f"{c['field_mm']:g} --depth-mm {c['depth_mm']:g} --binning {c['binning']} --profile isotropic --pinhole-um "
        f"{c['bead_um']:g} --oversample {c['oversample']}`."
    )
    report.figure("psf-calibration/montage.png", "The chain's calibration scan, focal plane (binned 8×)")
    return calibration
