"""The tiny CM²Net configuration the network and training tests share (seconds per run)."""

from __future__ import annotations

from cm2optics.recon.net.config import NetConfig
from cm2optics.synth.config import SynthConfig

SYNTH = SynthConfig.scaled(20, voxel_um=(100.0, 8.0, 8.0), view_px=64, patch_px=32, patches_per_volume=4)


def tiny(**changes) -> NetConfig:
    """8 channels, 1 block, the toy Gaussian model, two training volumes, one epoch; ``changes``
    override any field."""
    values = dict(
        channels=8,
        blocks=1,
        n_planes=SYNTH.grid.shape[0],
        forward_model="toy:gaussian",
        synth=SYNTH,
        train_volumes=2,
        val_volumes=1,
        epochs=1,
        threads=1,
        progress=False,
    )
    values.update(changes)
    return NetConfig(**values)
