"""Close the loop with measured data: compare a model with a measurement, find the residual,
name the physical effect the model lacks, add it, and report the error before and after.

- :mod:`.noise`: the sensor's noise model (read noise, conversion gain) estimated from the data;
- :mod:`.register`: model-to-data registration (flux scale, dark level, leakage, one sub-pixel offset);
- :mod:`.features`: per-focus features (energy, centroid, width) in matching windows;
- :mod:`.residual`: the residual analysis of a scan against its model, as one document;
- :mod:`.effects`: the effect library (named physical parameters with units, ranges, defaults)
  and the sensor-side effects applied to any simulator's images;
- :mod:`.simulate`: the simulators the loop can drive and the analytic CM²-like model;
- :mod:`.tracer`: the emission tracer as a simulator, the effects written into the design's
  ``as_built`` section (:class:`cm2optics.design.AsBuilt`) so a fitted effect is a design value;
- :mod:`.attribute`: which effects explain the residual (finite-difference Jacobians of the
  features, greedy selection under the BIC, joint Gauss–Newton refits, uncertainties);
- :mod:`.unexplained`: the signature of what the fitted effects leave above the noise (which
  lenslets, field, depths, share of the energy, shape) instead of a forced physical fit;
- :mod:`.lowrank_correction`: the data-driven, non-physical low-rank correction of the foci fitted
  to that residual, with its error on positions held out of its fit;
- :mod:`.scan`: ``cm2 calibrate scan``'s loop on a PSF scan;
- :mod:`.image`: ``cm2 calibrate image``'s loop on a beads frame with its reference emitters, and
  the reconstruction's scores with the nominal and the corrected model.
"""
