"""Reconstruction: model-based baselines now, CM²Net later.

- :mod:`~cm2optics.recon.operators`: the operator of a model file (3D-LSV or depth-wise LSI);
  the protocol is :class:`cm2optics.formats.operator.VolumeOperator`.
- :mod:`~cm2optics.recon.regularizers`, :mod:`~cm2optics.recon.solvers`: FISTA, ADMM (general and
  closed-form LSI), Richardson–Lucy with non-negativity, ℓ1 and 3-D TV; stopping rule.
- :mod:`~cm2optics.recon.reconstruct`: one measurement → one volume, memory checked.
- :mod:`~cm2optics.recon.compare`: LSV against LSI on a synthetic test set.
- :mod:`~cm2optics.cli.reconstruct`: ``cm2 reconstruct``; :mod:`~cm2optics.reports.recon`: the demo section.
"""
