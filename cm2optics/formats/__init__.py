"""One reader and one writer per file format; imports no stage (numpy, tifffile, h5py, yaml).

- :mod:`~cm2optics.formats.atomic`: atomic writes (temporary name, then rename).
- :mod:`~cm2optics.formats.scan`: PSF calibration scan folders (measured or synthetic).
- :mod:`~cm2optics.formats.volume`: volumes (ImageJ TIFF, ``.npy``) and their grid.
- :mod:`~cm2optics.formats.emitters`: emitter CSVs.
- :mod:`~cm2optics.formats.measurement`: measurement TIFF + YAML sidecar.
- :mod:`~cm2optics.formats.lsv_model`: the 3D-LSV model file (HDF5 or NPZ).
- :mod:`~cm2optics.formats.psf_stack`: the depth-wise LSI PSF stack file.
- :mod:`~cm2optics.formats.models`: :func:`~cm2optics.formats.models.load_forward_model`.
- :mod:`~cm2optics.formats.outputs`: the output policy (never overwrite what a command did not create).
- :mod:`~cm2optics.formats.operator`: the :class:`~cm2optics.formats.operator.VolumeOperator` protocol.

Every error a file can cause is a :class:`~cm2optics.formats.errors.FormatError` (a
``ValueError``) naming the file and the line or field.
"""
