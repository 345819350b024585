"""Illumination: the LED → collimator → excitation filter → sample-plane light path.

Modules, one idea each:

* :mod:`.source` — the LED: emitter, angular profile, spectrum, ray sampling (NumPy);
* :mod:`.excitation` — the excitation filter's T(λ, θ) as the tracer applies it;
* :mod:`.geometry` — the scene as triangle meshes with optical roles (collimator from the CAD
  part or any STL, filter, housings, sample plane), in the device frame;
* :mod:`.scene` — that scene in Mitsuba;
* :mod:`.tracer` — the vectorised wavefront tracer (Fresnel, Snell, TIR, filter, absorbers);
* :mod:`.reference_numpy` — the same tracer in plain NumPy, for tests and the benchmark;
* :mod:`.metrics` — figures of merit with Monte Carlo standard errors, irradiance maps;
* :mod:`.compare` — several designs in one setup; :mod:`.optimize` — the Dask design sweep;
* :mod:`.report` — the demo's section; :mod:`.cli` — ``cm2 illum``.

Importing this package points ``DRJIT_LIBLLVM_PATH`` at a suitable LLVM (see :mod:`cm2optics.optics.backend`, the Mitsuba variant choice shared with the emission tracer).
"""

from cm2optics.optics import backend as backend  # noqa: F401  (sets DRJIT_LIBLLVM_PATH first)
