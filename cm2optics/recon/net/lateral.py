"""The network's lateral calibration: where its output planes put an emitter, and the way back.

A convolutional network is translation-equivariant: it moves light seen at view position ``q`` to
the volume at ``q`` plus an offset that may depend on the depth, never on the position in the
field. But a source at (x, y, z) is seen at ``q = A(z)·(x, y)`` (+ a depth-wise shift): the
magnification of each lenslet changes with depth (≈ 1 % per 100 µm for cm2-v2), so a target
rasterised at (x, y) sits ``(A(z)/A(0) − 1)·(x, y)`` away from its light — up to ~15 µm at the
edge of a 2-mm field for the deepest planes. Trained on patches from all over the field, the
network learns the mean displacement and leaves a radial error ∝ field radius that grows with
|z| (measured on test set (a) with the shipped CPU weights: the per-depth scale error runs from
−6·10⁻³ to +1.9·10⁻² over the depth range; with this correction the lateral RMSE fell from 9.2 to
3.6 µm, see reconstruction/cm2net-cpu/MODEL_CARD.md).

The network's output plane at depth z is therefore a laterally scaled and shifted copy of the
object plane::

    û = s(z)·u + b(z),   s(z) = 1 + c₀ + c₁·z + c₂·z²,   b(z) = (b_y(z), b_x(z)) quadratic in z

(u, û: (y, x) µm from the optical axis, in the training targets' frame; z in mm). The
coefficients are fitted by least squares on matched detections in full-field validation
volumes (the training recipe and the validation seed: never the test set's), stored with the
weights (safetensors metadata, under the SHA-256), and the inference resamples each output plane
onto the object grid (linear interpolation, one pass) — the reconstruction is then in object
coordinates at every depth.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["METADATA_KEY", "LateralCorrection", "calibrate_weights", "fit_lateral_correction", "volume_on_grid"]

#: Metadata key of the correction in ``model.safetensors``.
METADATA_KEY = "lateral_correction"


@dataclass(frozen=True)
class LateralCorrection:
    """scale: (c₀, c₁, c₂) of s(z) − 1; shift_um: (2, 3) the (y, x) shift's coefficients
    (1, z, z²), µm; z in mm (see the module docstring)."""

    scale: tuple[float, float, float] = (0.0, 0.0, 0.0)
    shift_um: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))

    def at(self, z_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """s(z) (n,) and b(z) (n, 2) µm at depths ``z_mm``."""
        z = np.asarray(z_mm, float)
        powers = np.stack([np.ones_like(z), z, z * z], axis=-1)
        return 1.0 + powers @ np.asarray(self.scale), powers @ np.asarray(self.shift_um).T

    def to_json(self) -> str:
        return json.dumps({"scale": list(self.scale), "shift_um": [list(row) for row in self.shift_um]})

    @classmethod
    def from_json(cls, text: str) -> LateralCorrection:
        data = json.loads(text)
        scale = tuple(float(v) for v in data["scale"])
        shift = tuple(tuple(float(v) for v in row) for row in data["shift_um"])
        if len(scale) != 3 or len(shift) != 2 or any(len(row) != 3 for row in shift):
            raise ValueError(f"lateral correction {text!r}: need 3 scale and 2 × 3 shift coefficients")
        return cls(scale, shift)  # type: ignore[arg-type]


def volume_on_grid(
    raw: np.ndarray,
    z_mm: np.ndarray,
    voxel_um: tuple[float, float],
    orientation: np.ndarray,
    correction: LateralCorrection | None = None,
    *,
    out_shape: tuple[int, int] | None = None,
    out_voxel_um: tuple[float, float] | None = None,
) -> np.ndarray:
    """The network's raw output (P, V, V) (views' orientation, pixels of ``voxel_um`` (y, x) at
    the object) resampled onto the object grid: (P, *out_shape) on (y, x) voxels of
    ``out_voxel_um`` (default: the raw shape and pitch) centred on the axis (index (n − 1)/2).

    Raw pixel i of an output plane holds the target at ``sign·(i − V//2)·voxel`` (the views are
    cropped with the chief ray at pixel V//2; ``orientation``: the signs (y, x) of the model's
    pixels per voxel, −1 where the lenslet image is inverted); ``correction`` moves each plane by
    its s(z), b(z). Linear interpolation, zeros outside; float32."""
    raw = np.asarray(raw, np.float32)
    P, H, W = raw.shape
    correction = correction or LateralCorrection()
    s, b = correction.at(z_mm)
    sign = np.sign(np.asarray(orientation, float))
    vy, vx = (float(v) for v in voxel_um)
    ny, nx = out_shape or (H, W)
    oy, ox = (float(v) for v in (out_voxel_um or voxel_um))
    u_y = (np.arange(ny) - (ny - 1) / 2.0) * oy
    u_x = (np.arange(nx) - (nx - 1) / 2.0) * ox
    # raw index of the object position u in plane p: V//2 + sign·(s_p·u + b_p)/voxel
    iy = H // 2 + sign[0] * (s[:, None] * u_y[None] + b[:, 0:1]) / vy  # (P, ny)
    ix = W // 2 + sign[1] * (s[:, None] * u_x[None] + b[:, 1:2]) / vx  # (P, nx)
    out = np.empty((P, ny, nx), np.float32)
    for p in range(P):  # separable: rows, then columns (two taps each)
        out[p] = _resampled(_resampled(raw[p], iy[p], axis=0), ix[p], axis=1)
    return out


def _resampled(image: np.ndarray, index: np.ndarray, axis: int) -> np.ndarray:
    """``image`` linearly interpolated along ``axis`` at fractional indices ``index`` (zeros beyond)."""
    n = image.shape[axis]
    low = np.floor(index).astype(np.int64)
    t = (index - low).astype(np.float32)
    padded = np.pad(image, [(1, 1) if a == axis else (0, 0) for a in range(image.ndim)])
    lo = np.clip(low, -1, n) + 1  # −1 and n land in the zero padding
    hi = np.clip(low + 1, -1, n) + 1
    a, b = np.take(padded, lo, axis=axis), np.take(padded, hi, axis=axis)
    shape = [-1 if ax == axis else 1 for ax in range(image.ndim)]
    return a * (1.0 - t).reshape(shape) + b * t.reshape(shape)


def fit_lateral_correction(
    truth_yx_um: np.ndarray, truth_z_mm: np.ndarray, found_yx_um: np.ndarray
) -> LateralCorrection:
    """Least-squares s(z), b(z) from matched pairs: true (y, x) µm and depth (mm), and where the
    uncorrected network put them (n, 2), µm."""
    u = np.asarray(truth_yx_um, float)
    z = np.asarray(truth_z_mm, float)
    found = np.asarray(found_yx_um, float)
    n = len(u)
    if n < 9:
        raise ValueError(f"{n} matched emitters: need at least 9 to fit the lateral correction")
    powers = np.stack([np.ones(n), z, z * z], axis=1)
    zeros = np.zeros_like(powers)
    # unknowns: c (3), b_y (3), b_x (3); û − u = u·(c·p) + b·p
    rows_y = np.hstack([u[:, :1] * powers, powers, zeros])
    rows_x = np.hstack([u[:, 1:] * powers, zeros, powers])
    design = np.vstack([rows_y, rows_x])
    target = np.concatenate([found[:, 0] - u[:, 0], found[:, 1] - u[:, 1]])
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    return LateralCorrection(tuple(coef[:3]), (tuple(coef[3:6]), tuple(coef[6:9])))  # type: ignore[arg-type]


def _moved_back(found: Any, correction: LateralCorrection) -> Any:
    """Detections ``found`` (on the uncorrected output) taken back to the object: u = (û − b)/s."""
    from cm2optics.formats.emitters import Emitters

    s, b = correction.at(found.z_um / 1000.0)
    y = (found.y_um - b[:, 0]) / s
    x = (found.x_um - b[:, 1]) / s
    return Emitters(x, y, found.z_um, found.diameter_um, found.intensity)


def calibrate_weights(
    folder: str | Path, *, n_volumes: int = 4, threshold: float = 0.3, rounds: int = 3, log=print
) -> tuple[LateralCorrection, dict[str, float]]:
    """Fit the lateral correction of the weights in ``folder`` on ``n_volumes`` full-field
    validation volumes and store it in its ``model.safetensors`` (the SHA-256 sums rewritten; the
    card and config untouched). ``rounds``: fits, each matching the detections moved back by the
    previous one (a large error can miss the matching gate). Returns the correction and the
    lateral RMSE (µm) of the matched pairs before and after."""
    from cm2optics.metrics.match import match_emitters
    from cm2optics.recon.net.data import validation_volumes
    from cm2optics.recon.net.infer import reconstruct_with_net
    from cm2optics.recon.net.weights import load_weights, store_metadata

    loaded = load_weights(folder)
    runs = []
    for index, (sample, imaging) in enumerate(validation_volumes(loaded.config, n_volumes)):
        result = reconstruct_with_net(
            sample.measurement, loaded, imaging.source, threshold=threshold, lateral=LateralCorrection()
        )
        runs.append((result.emitters, sample.draw.emitters, max(result.grid.voxel_um)))
        log(f"validation volume {index + 1}/{n_volumes}: {len(sample.draw.emitters)} emitters")
    correction = LateralCorrection()
    rmse: dict[str, float] = {}
    for round_ in range(rounds + 1):
        u, z, found = [], [], []
        for detected, truth, floor_um in runs:
            moved = _moved_back(detected, correction)
            m = match_emitters(truth, moved, min_gate_um=floor_um)
            t, d = m.true_index, m.detected_index
            u.append(np.stack([truth.y_um[t], truth.x_um[t]], axis=1))
            z.append(truth.z_um[t] / 1000.0)
            found.append(np.stack([detected.y_um[d], detected.x_um[d]], axis=1))
        u, z, found = np.concatenate(u), np.concatenate(z), np.concatenate(found)
        s, b = correction.at(z)
        error = float(np.sqrt(np.mean(np.sum(((found - b) / s[:, None] - u) ** 2, axis=1))))
        rmse["before" if round_ == 0 else "after"] = error
        log(f"round {round_}: {len(u)} matched, lateral RMSE {error:.2f} µm")
        if round_ == rounds:
            break
        correction = fit_lateral_correction(u, z, found)
    store_metadata(folder, {METADATA_KEY: correction.to_json()})
    return correction, rmse


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m cm2optics.recon.net.lateral", description=__doc__.split("\n\n")[0])
    parser.add_argument("weights", help="weights folder, e.g. reconstruction/cm2net-cpu (rewritten in place)")
    parser.add_argument("--n-volumes", type=int, default=4)
    parser.add_argument("--threshold", type=float, default=0.3)
    args = parser.parse_args(argv)
    correction, rmse = calibrate_weights(args.weights, n_volumes=args.n_volumes, threshold=args.threshold)
    print(json.dumps({"correction": json.loads(correction.to_json()), "rmse_lateral_um": rmse}, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
