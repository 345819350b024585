"""A CM² measurement of a volume or of emitters through an LSV model (``cm2 simulate``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cm2optics.errors import UserError

__all__ = ["simulate_measurement"]


def simulate_measurement(
    out: str | Path,
    model_path: str | Path,
    *,
    volume_path: str | Path | None = None,
    emitters_path: str | Path | None = None,
    voxel_um: tuple[float, float, float] | None = None,
    noise: bool = False,
    peak_photons: float = 500.0,
    read_noise: float = 0.017,
    offset: float = 0.048,
    bit_depth: int = 12,
    per_lenslet: bool = False,
    lsi: bool = False,
    seed: int = 0,
    subpixel_steps: int = 4,
    progress: Any = None,
) -> dict[str, Any]:
    """Render the measurement, scale its brightest pixel to full scale, add the paper's mixed
    noise if asked, write 16-bit counts to ``out`` and ``out``.yaml (model, scale, noise);
    returns the summary (measurement, sidecar, shape, max_count, mean_count, counts_per_unit).
    A .npy volume without ``voxel_um`` is taken to be on the model's default grid spacing.
    """
    import numpy as np

    import cm2optics
    from cm2optics.formats.emitters import read_emitters
    from cm2optics.formats.measurement import write_measurement
    from cm2optics.formats.volume import VolumeGrid, read_volume
    from cm2optics.lsv.model import load_model
    from cm2optics.synth.noise import poisson_gaussian

    if (volume_path is None) == (emitters_path is None):
        raise UserError("give exactly one of --volume and --emitters")
    if bit_depth not in (8, 10, 12, 14, 16):
        raise UserError(f"--bit-depth = {bit_depth}: must be one of 8, 10, 12, 14, 16")
    if not (peak_photons > 0 and read_noise >= 0 and 0 <= offset < 1):
        raise UserError("--peak-photons must be > 0, --read-noise ≥ 0, --offset within [0, 1)")
    out = Path(out)
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise UserError(f"--out {out}: the measurement is written as a TIFF (.tif)")
    if not 0 <= subpixel_steps <= 64:
        raise UserError(f"--subpixel-steps = {subpixel_steps}: must lie within 0–64 (0: exact placement)")
    model = load_model(model_path)
    if lsi:
        from cm2optics.lsv.lsi import lsi_model

        model = lsi_model(model)
    spacing = voxel_um
    if volume_path is not None:
        if spacing is None and volume_path.suffix.lower() == ".npy":
            spacing = model.default_grid.voxel_um
        volume, grid = read_volume(volume_path, spacing)
        grid = VolumeGrid(volume.shape, grid.voxel_um)
        lit = np.nonzero(volume)
        model.warn_outside_calibration(
            np.stack([grid.axis_mm(2)[lit[2]], grid.axis_mm(1)[lit[1]], grid.axis_mm(0)[lit[0]]], -1), "lit voxels"
        )
        image = model.operator(grid).forward(volume, per_lenslet=per_lenslet, progress=progress)
        source = {"volume": str(volume_path), "grid": grid.to_dict()}
    else:
        emitters = read_emitters(emitters_path)
        model.warn_outside_calibration(emitters.positions_mm(), "emitters")
        image = model.forward_sparse(emitters, per_lenslet=per_lenslet, subpixel_steps=subpixel_steps or None)
        source = {
            "emitters": str(emitters_path),
            "count": len(emitters),
            "subpixel_steps": subpixel_steps or "exact",
        }
    image = np.asarray(image, dtype=np.float64)
    peak = float(image.max())
    if not peak > 0:
        raise UserError("the simulated image is empty (nothing in the volume reaches the sensor)")
    normalised = np.clip(image / peak, 0, None)
    rng = np.random.default_rng(seed)
    if noise:
        normalised = poisson_gaussian(normalised, peak_photons, offset, read_noise, rng)
    full = 2**bit_depth - 1
    counts = np.clip(np.round(normalised * full), 0, full).astype(np.uint16)
    sidecar = {
        "pixel_um": model.pixel_um,
        "bit_depth": bit_depth,
        "dark_level": round(offset * full, 3) if noise else 0.0,
        "counts_per_unit": float(full / peak),
        "noise": {"poisson_peak_photons": peak_photons, "read_noise": read_noise, "offset": offset, "seed": seed}
        if noise
        else None,
        "generator": f"cm2optics {cm2optics.__version__} (cm2 simulate)",
        "model": str(model_path),
        "baseline": "lsi" if lsi else "lsv",
        "source": source,
        "per_lenslet": per_lenslet,
    }
    _, sidecar_path = write_measurement(out, counts, sidecar)
    summary = {
        "measurement": str(out),
        "sidecar": str(sidecar_path),
        "shape": list(counts.shape),
        "max_count": int(counts.max()),
        "mean_count": float(counts.mean()),
        "counts_per_unit": sidecar["counts_per_unit"],
    }
    return summary
