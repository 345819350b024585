"""The Mitsuba variant and LLVM library of the emission tracer: the illumination tracer's choice.

One process has one Mitsuba variant, so the emission path reuses
:mod:`cm2optics.illumination.backend` (which points Dr.Jit at an LLVM ≥ 17 before Dr.Jit is
imported, prefers CUDA, and falls back to the scalar variant with a warning). Set
``CM2_ILLUM_VARIANT`` to force a variant for both.
"""

from __future__ import annotations

from cm2optics.illumination.backend import Backend, find_libllvm, is_jit, mitsuba, variant

__all__ = ["Backend", "find_libllvm", "is_jit", "mitsuba", "variant"]
