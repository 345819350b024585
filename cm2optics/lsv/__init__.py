"""The 3D linear-shift-variant (3D-LSV) forward model of a CM² (Xue et al., Optica 2022).

Built from a sparse PSF calibration scan (:mod:`cm2optics.formats.scan`): foci cropped around
their chief rays and registered (axial shear undone), a truncated SVD into K basis PSFs and
coefficient volumes, the coefficients interpolated in x, y and z, and the basis PSFs placed
back with the shear. Modules:

- :mod:`~cm2optics.lsv.preprocess`: dark/background/exposure, foci, imaging geometry, crops.
- :mod:`~cm2optics.lsv.decompose`: truncated SVD and the error against K.
- :mod:`~cm2optics.lsv.interpolate`: trilinear interpolation along the chief rays.
- :mod:`~cm2optics.lsv.model`: :class:`LSVModel`, one HDF5 file with its provenance.
- :mod:`~cm2optics.lsv.operators`: torch forward/adjoint (dense, batched, per lenslet);
  :mod:`~cm2optics.lsv.sparse`: sparse emitters without a volume; :mod:`~cm2optics.lsv.reference`:
  the naive per-(k, z) evaluation the fast one is checked and timed against;
  :mod:`~cm2optics.lsv.kernels`: the Keys cubic sub-pixel shifts.
- :mod:`~cm2optics.lsv.lsi`: the depth-wise shift-invariant baseline of the V1 paper (FFT operator).
- :mod:`~cm2optics.lsv.build`, :mod:`~cm2optics.lsv.validate`, :mod:`~cm2optics.reports.lsv`,
  :mod:`~cm2optics.cli.lsv`: the ``cm2 lsv`` and ``cm2 simulate`` commands.
- :mod:`~cm2optics.lsv.toy`: toy models for tests, demos and fast fall-backs (a closed-form
  CM²-like PSF, its scans and LSV models, a Gaussian depth-wise LSI operator).
"""
