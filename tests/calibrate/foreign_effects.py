"""Two effects outside the calibration's library, written for the tests: the loop is not told
of them and has no parameter that explains them.

- :func:`filter_scratch`: an opaque scratch on the emission filter's top face, a strip
  (x0 ± width/2, y0–y1 mm, device frame). Each lenslet's beam crosses that face in a footprint
  (its square aperture projected from the source onto the face); the lenslet's focus loses the
  share of its footprint the strip covers (× 1 − transmission). The footprint moves with the
  source, so the loss depends on the source position, lenslet by lenslet — no constant
  per-lenslet transmission reproduces it. First order: refraction in the filter is ignored.
- :func:`ghost`: a weak displaced, defocused copy of every focus (a reflection between the
  sensor's cover glass and the absorption filter): share × the image shifted by (row, col) px
  and blurred by a Gaussian of σ px.

Both act on a noise-free scan's frames (counts above dark) before the sensor noise is added.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter, shift

from cm2optics.design import SystemDesign
from cm2optics.formats.scan import read_scan, write_scan
from cm2optics.optics import first_order
from cm2optics.optics.lenslets import lens_cells


def scratch_loss(
    design: SystemDesign,
    positions_mm: np.ndarray,
    x0_mm: float,
    width_mm: float,
    y_range_mm: tuple[float, float],
    transmission: float = 0.0,
) -> np.ndarray:
    """(N, J) share of each lenslet's light the scratch removes, per source position (N, 3) mm."""
    top = design.emission_filter_z_mm + design.emission_filter.thickness_mm
    lens = design.mla_vertex_z_mm
    half = design.mla.aperture_mm / 2.0
    cells = [c for c in lens_cells(design.mla, design.as_built) if not c.partial]
    out = np.zeros((len(positions_mm), len(cells)))
    for i, (x, y, z) in enumerate(np.asarray(positions_mm, float)):
        height = first_order.object_z_to_height_mm(design, z)
        t = (height - top) / (height - lens)  # aperture → filter face, projected from the source
        for cell in cells:
            fx = (x + (cell.vertex_x - half - x) * t, x + (cell.vertex_x + half - x) * t)
            fy = (y + (cell.vertex_y - half - y) * t, y + (cell.vertex_y + half - y) * t)
            over_x = max(0.0, min(fx[1], x0_mm + width_mm / 2) - max(fx[0], x0_mm - width_mm / 2))
            over_y = max(0.0, min(fy[1], y_range_mm[1]) - max(fy[0], y_range_mm[0]))
            out[i, cell.row * design.mla.cols + cell.col] = (
                over_x * over_y / ((fx[1] - fx[0]) * (fy[1] - fy[0])) * (1.0 - transmission)
            )
    return out


def _nearest_lenslet(design: SystemDesign, binning: int, shape: tuple[int, int], position_mm) -> np.ndarray:
    """(y, x) index of the lenslet whose chief-ray focus is nearest each pixel."""
    x, y, z = position_mm
    m = first_order.chief_ray_magnification(design, first_order.object_z_to_height_mm(design, z))
    pitch = design.sensor.pixel_um * binning / 1000.0
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    best = np.full(shape, np.inf)
    out = np.zeros(shape, int)
    for cell in lens_cells(design.mla, design.as_built):
        if cell.partial:
            continue
        sx, sy = cell.vertex_x - m * (x - cell.vertex_x), cell.vertex_y - m * (y - cell.vertex_y)
        r, c = sy / pitch + (shape[0] - 1) / 2, sx / pitch + (shape[1] - 1) / 2
        distance = np.hypot(rows - r, cols - c)
        closer = distance < best
        best[closer], out[closer] = distance[closer], cell.row * design.mla.cols + cell.col
    return out


def filter_scratch(scan_dir: Path, out_dir: Path, design: SystemDesign, **strip) -> tuple[Path, np.ndarray]:
    """``scan_dir`` (noise-free) seen through a scratched filter (:func:`scratch_loss`'s
    arguments in ``strip``), written to ``out_dir``; and the (N, J) loss injected."""
    scan = read_scan(scan_dir)
    loss = scratch_loss(design, scan.positions_mm, **strip)
    frames = scan.images.astype(np.float64) - scan.meta.dark_level
    for i, position in enumerate(scan.positions_mm):
        owner = _nearest_lenslet(design, scan.meta.binning, frames.shape[-2:], position)
        frames[i] *= 1.0 - loss[i][owner]
    return _write(scan, frames, out_dir), loss


def ghost(scan_dir: Path, out_dir: Path, share: float, offset_px: tuple[float, float], sigma_px: float) -> Path:
    """``scan_dir`` (noise-free) with a ghost of every focus (module docstring) in ``out_dir``."""
    scan = read_scan(scan_dir)
    frames = scan.images.astype(np.float64) - scan.meta.dark_level
    for i in range(len(frames)):
        frames[i] += share * gaussian_filter(shift(frames[i], offset_px, order=1), sigma_px)
    return _write(scan, frames, out_dir)


def _write(scan, frames: np.ndarray, out_dir: Path) -> Path:
    top = 2**scan.meta.bit_depth - 1
    counts = np.clip(np.rint(frames + scan.meta.dark_level), 0, top).astype(np.uint16)
    return write_scan(out_dir, counts, scan.positions_mm, scan.exposure_ms, scan.meta, names=list(scan.files))
