"""The optics core shared by every tracer and by CAD: pure functions of a design.

* :mod:`~.interfaces` — Snell refraction, reflection, Fresnel (s, p, unpolarised) and TIR at one
  interface, written once for NumPy and Dr.Jit arrays through the shim :mod:`~.arrays`;
* :mod:`~.first_order` — derived first-order optics of a design (focal length, paraxial and
  best-focus object plane, magnification, object pixel, working distance, NA), cached per design;
* :mod:`~.focus` — the exact on-axis trace whose wavefront finds the plane of best focus;
* :mod:`~.lenslets`, :mod:`~.layout`, :mod:`~.housing` — geometry of the lenslet cells, the
  device's parts and the MLA housing's bore and tabs, for CAD and tracers alike;
* :mod:`~.checks` — plausibility of a design that needs derived optics (a real image, filters
  in the emission band);
* :mod:`~.backend` — the Mitsuba variant (and LLVM library) every tracer runs on.

Imports only :mod:`cm2optics.design`; Mitsuba and Dr.Jit only through :mod:`~.backend`.
"""
