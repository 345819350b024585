"""One synthetic sample: emitters → volume → crosstalk-free images → measurement → views, patches.

1. draw the emitters (:mod:`cm2optics.synth.emitters`);
2. rasterise them on the grid (5× finer, averaged down: :mod:`cm2optics.synth.raster`);
3. image them with the 3D-LSV model lenslet by lenslet — the sum is the noise-free measurement,
   the parts are the ground-truth demixed views;
4. normalise to a peak of 1 (``image_scale`` = model units per normalised unit), add sensor noise;
5. crop the nine views at the chief rays (noisy measurement, and each lenslet's clean image),
   cut training patches with their volume targets.

Every random number of sample ``index`` comes from generators seeded by ``(seed, index)``, so
a sample is the same whichever worker makes it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cm2optics.synth.config import SynthConfig
from cm2optics.synth.emitters import EmitterDraw, sample_emitters, sample_rng
from cm2optics.synth.imaging import Imaging
from cm2optics.synth.noise import add_noise
from cm2optics.synth.raster import rasterize_balls
from cm2optics.synth.views import crop_views, patch_origins, volume_patch

__all__ = ["Sample", "synthesize_sample"]

STREAM_EMITTERS, STREAM_NOISE, STREAM_PATCHES = 0, 1, 2


@dataclass
class Sample:
    """One sample's arrays (float32) and numbers; absent parts are None."""

    index: int
    seed: int
    draw: EmitterDraw
    measurement: np.ndarray
    image_scale: float
    volume: np.ndarray | None = None
    clean: np.ndarray | None = None
    views: np.ndarray | None = None
    demixed: np.ndarray | None = None
    patches: dict[str, np.ndarray] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "n_emitters": len(self.draw.emitters),
            "fov_mm": round(self.draw.fov_mm, 6),
            "density_per_mm2": round(self.draw.density_per_mm2, 6),
            "image_scale": self.image_scale,
            "n_patches": int(len(self.patches.get("origin", []))),
            "seconds": {k: round(v, 4) for k, v in self.seconds.items()},
        }


def synthesize_sample(
    config: SynthConfig,
    imaging: Imaging,
    index: int,
    seed: int,
    *,
    keep_clean: bool = False,
    need_volume: bool | None = None,
) -> Sample:
    """Make sample ``index`` of data set ``seed`` (see the module docstring).

    keep_clean: keep the noise-free normalised measurement. need_volume: rasterise the volume
    even when neither the renderer nor the files need it (default: when they do).
    """
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    grid = config.grid
    draw = sample_emitters(config, sample_rng(seed, index, STREAM_EMITTERS))
    seconds["emitters"] = time.perf_counter() - t0

    want_patches = bool(config.patch_px and config.patches_per_volume and config.view_px)
    want_volume = (config.store_volume or imaging.needs_volume or want_patches) if need_volume is None else need_volume
    volume = None
    if want_volume:
        t = time.perf_counter()
        volume = rasterize_balls(draw.emitters, grid, supersample=config.supersample)
        seconds["volume"] = time.perf_counter() - t

    t = time.perf_counter()
    if config.view_px:  # the demixed views need each lenslet's image; they add up to the measurement
        per_lenslet = np.maximum(
            imaging.image(draw.emitters, volume, per_lenslet=True), 0.0
        )  # no negative light (ringing)
        clean = per_lenslet.sum(axis=0, dtype=np.float32)
    else:
        per_lenslet = None
        clean = np.maximum(imaging.image(draw.emitters, volume), 0.0)
    seconds["imaging"] = time.perf_counter() - t

    t = time.perf_counter()
    peak = float(clean.max())
    scale = peak if peak > 0 else 1.0
    clean /= scale
    if per_lenslet is not None:
        per_lenslet /= scale
    measurement = add_noise(clean, config, sample_rng(seed, index, STREAM_NOISE))
    seconds["noise"] = time.perf_counter() - t

    sample = Sample(
        index, seed, draw, measurement, scale, volume if config.store_volume else None, clean if keep_clean else None
    )
    if config.view_px:
        t = time.perf_counter()
        rays = imaging.chief_rays_px()
        sample.views = crop_views(measurement, rays, config.view_px)
        sample.demixed = crop_views(per_lenslet, rays, config.view_px)
        seconds["views"] = time.perf_counter() - t
    del per_lenslet
    if want_patches and sample.views is not None:
        t = time.perf_counter()
        sample.patches = _patches(config, imaging, sample, volume, sample_rng(seed, index, STREAM_PATCHES))
        seconds["patches"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t0
    sample.seconds = seconds
    return sample


def _patches(
    config: SynthConfig, imaging: Imaging, sample: Sample, volume: np.ndarray | None, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    p, V = config.patch_px, config.view_px
    origins = patch_origins(rng, V, p, config.patches_per_volume)
    out: dict[str, np.ndarray] = {
        "origin": origins.astype(np.int32),
        "views": np.stack([sample.views[:, r : r + p, c : c + p] for r, c in origins]),
        "demixed": np.stack([sample.demixed[:, r : r + p, c : c + p] for r, c in origins]),
    }
    scale = imaging.pixels_per_voxel()
    if volume is not None and scale is not None:
        blocks, starts = zip(*(volume_patch(volume, o, V, p, scale) for o in origins), strict=True)
        out["volume"] = np.stack(blocks)
        out["voxel_origin"] = np.stack(starts).astype(np.int32)
    return out
