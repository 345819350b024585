"""Close the loop with measured data: compare a model with a measurement, find the residual,
name the physical effect the model lacks, add it, and report the error before and after.

- :mod:`.noise`: the sensor's noise model (read noise, conversion gain) estimated from the data;
- :mod:`.register`: model-to-data registration (flux scale, dark level, leakage, one sub-pixel offset);
- :mod:`.features`: per-focus features (energy, centroid, width) in matching windows;
- :mod:`.residual`: the residual analysis of a scan against its model, as one document.
"""
