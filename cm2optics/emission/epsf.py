"""Effective PSFs (ePSF, Anderson & King, PASP 112, 1360, 2000) of synthetic foci.

The ePSF is the optical PSF already integrated over one saved pixel's area, tabulated on a grid
``S`` times finer than the saved pixels (``S`` = the oversampling). The image of a point source at
any sub-pixel position is the ePSF *sampled* at the pixel centres: no interpolation of an
undersampled image is ever needed.

The emission model evaluates each focus on ``q`` sub-samples per saved pixel (sub-sample ``k`` of
pixel ``r`` centred at ``r + (k + ½)/q − ½`` pixels) and sums them into pixels. A box of ``q``
consecutive sub-samples starting at sub-sample ``i`` is the pixel integral centred at ``i/q``
pixels from the first pixel's centre, so with ``q`` a multiple of ``S`` the ePSF at steps of
``1/S`` pixel is a running sum of the sub-samples, taken every ``q/S``: exact, no resampling.

Layout of an ePSF patch: fine sample ``(a, b)`` is the pixel integral centred at the pixel
coordinate ``(row0 + a/S, col0 + b/S)``; the fine origin ``(S·row0, S·col0)`` is stored, so that
fine index ``u`` of the whole frame is the pixel coordinate ``u/S``. Sampling fine indices
``S·m`` gives back the ordinary pixel image (pixel ``m``).

Files: ``epsf.h5`` in the scan folder, beside the ordinary frames (which keep the measured-scan
format): attributes ``format = "cm2optics-epsf"``, ``oversample``, ``units`` (the scan's
normalised units, counts per ms, before any background removal); one group per scan row
``p00000`` … with datasets ``lenslet`` (F,), ``origin`` (F, 2) fine (row, col) of each patch's
``[0, 0]``, ``shape`` (F, 2) and ``data`` (all patches, raveled, float32). The LSV stage reads it with
:func:`cm2optics.lsv.epsf.read_epsf_position`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["EPSF_FILE", "epsf_from_subsamples", "write_epsf_file"]

EPSF_FILE = "epsf.h5"
FORMAT = "cm2optics-epsf"


def _running_box(fine: np.ndarray, q: int, step: int, n_out: int, axis: int) -> np.ndarray:
    """Sums of ``q`` consecutive samples along ``axis``, starting every ``step``: ``n_out`` of them
    (zeros beyond the end)."""
    fine = np.moveaxis(fine, axis, -1)
    padded = np.concatenate([np.zeros(fine.shape[:-1] + (1,)), np.cumsum(fine, axis=-1, dtype=np.float64)], -1)
    starts = np.arange(n_out) * step
    lo = np.minimum(starts, fine.shape[-1])
    hi = np.minimum(starts + q, fine.shape[-1])
    out = np.take(padded, hi, axis=-1) - np.take(padded, lo, axis=-1)
    return np.moveaxis(out, -1, axis)


def epsf_from_subsamples(fine: np.ndarray, q: int, oversample: int) -> np.ndarray:
    """The ePSF (R·S, C·S) of a focus sampled on ``q`` × ``q`` sub-samples per pixel ((R·q, C·q),
    each the PSF integrated over its sub-sample's area): sample (a, b) is the whole-pixel integral
    centred at ``(a/S, b/S)`` pixels from pixel (0, 0)'s centre. ``q`` must be a multiple of
    ``oversample``."""
    S = int(oversample)
    if S < 1 or q % S:
        raise ValueError(f"oversample = {oversample!r}: must be ≥ 1 and divide the sub-samples per pixel ({q})")
    R, C = fine.shape[0] // q, fine.shape[1] // q
    step = q // S
    rows = _running_box(np.asarray(fine, np.float64), q, step, R * S, axis=0)
    return _running_box(rows, q, step, C * S, axis=1)


def write_epsf_file(path: Path, oversample: int, units: str, positions: list[dict[str, np.ndarray]]) -> None:
    """Write ``epsf.h5`` (see the module docstring) at ``path`` (the caller renames it in place)."""
    import h5py

    with h5py.File(path, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["version"] = 1
        f.attrs["oversample"] = int(oversample)
        f.attrs["units"] = units
        for i, packed in enumerate(positions):
            g = f.create_group(f"p{i:05d}")
            for key in ("lenslet", "origin", "shape"):
                g.create_dataset(key, data=packed[key])
            g.create_dataset("data", data=packed["data"], compression="gzip", compression_opts=4, shuffle=True)
