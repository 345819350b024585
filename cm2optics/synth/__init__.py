"""Synthetic training and test data made the paper's way (Xue et al., Optica 2022, Section 2.4).

- :mod:`~cm2optics.synth.config`: :class:`SynthConfig`, every size a field; the paper's recipe and scaled-down sets.
- :mod:`~cm2optics.synth.emitters`: random emitters (field, density, diameter, intensity ∝ d²).
- :mod:`~cm2optics.synth.raster`: balls on a 5× finer grid averaged down, vectorised.
- :mod:`~cm2optics.synth.noise`: Poisson + Gaussian, or variance = a·I + b.
- :mod:`~cm2optics.synth.imaging`, :mod:`~cm2optics.synth.views`, :mod:`~cm2optics.synth.generate`:
  measurement, demixed views, views at the chief rays, patches.
- :mod:`~cm2optics.synth.dataset`: HDF5 files + manifest, made on Dask. :mod:`~cm2optics.cli.synth`: ``cm2 synth``.
"""

from cm2optics.synth.config import SynthConfig
from cm2optics.synth.emitters import sample_emitters, sample_rng
from cm2optics.synth.noise import add_noise
from cm2optics.synth.raster import rasterize_balls, rasterize_balls_naive

__all__ = ["SynthConfig", "add_noise", "rasterize_balls", "rasterize_balls_naive", "sample_emitters", "sample_rng"]
