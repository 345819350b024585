"""Which Mitsuba variant the ray tracers (illumination and emission) run on, and the LLVM library
it needs. One process has one Mitsuba variant; ``CM2_ILLUM_VARIANT`` forces it for both.

Mitsuba 3.9 / Dr.Jit 1.5 compile their CPU kernels with LLVM at run time, loading
``libLLVM`` as a shared library. Dr.Jit's own search picks the first library it finds, and on
Debian/Ubuntu that can be LLVM 14 or 15, which abort the whole process on the first kernel
("LLVM ERROR: Cannot select … fmaximum"). So, before Dr.Jit is imported, this module looks for
an LLVM ≥ :data:`MIN_LLVM_MAJOR` and points ``DRJIT_LIBLLVM_PATH`` at it.

Variant choice (:func:`variant`), first match wins:

1. ``CM2_ILLUM_VARIANT`` in the environment (e.g. ``scalar_rgb``): used as given;
2. a CUDA device: ``cuda_ad_rgb``;
3. an LLVM ≥ 17 library (``DRJIT_LIBLLVM_PATH`` if the user set it, else the newest found in
   the usual library folders, or in ``CM2_LIBLLVM_DIRS``, a ``os.pathsep``-separated list):
   ``llvm_ad_rgb`` — vectorised wavefronts on every CPU core;
4. otherwise ``scalar_rgb``, with ONE :class:`RuntimeWarning` per process saying so: the
   tracer still runs, one ray at a time (≈ 10³ rays/s instead of ≈ 10⁶).

Mitsuba and Dr.Jit are imported only through :func:`mitsuba` here, in :mod:`cm2optics.illumination`
and in :mod:`cm2optics.emission` (as the project's architecture test requires).
"""

from __future__ import annotations

import glob
import os
import re
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

__all__ = [
    "MIN_LLVM_MAJOR",
    "Backend",
    "find_libllvm",
    "is_jit",
    "mitsuba",
    "variant",
]

#: Oldest LLVM whose x86-64 backend selects every instruction Dr.Jit 1.5 emits (LLVM 15
#: aborts on ``fmaximum``; 14 is not even loaded).
MIN_LLVM_MAJOR = 17

_DEFAULT_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/usr/lib/llvm-*/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)

_NAME = re.compile(r"^libLLVM(?:-(\d+)(?:\.\d+)*)?\.(?:so|dylib)(?:\.(\d+)(?:\.\d+)*)?$")


def _llvm_major(path: Path) -> int | None:
    """Major version of an LLVM library from its file name (``libLLVM.so.19.1``,
    ``libLLVM-19.so``, ``/usr/lib/llvm-19/lib/libLLVM.so``), or None when it does not say."""
    match = _NAME.match(path.name)
    if match is None:
        return None
    for group in match.groups():
        if group is not None:
            return int(group)
    folder = re.search(r"llvm-(\d+)", str(path))
    return int(folder.group(1)) if folder else None


def find_libllvm(min_major: int = MIN_LLVM_MAJOR) -> Path | None:
    """The newest ``libLLVM`` shared library with major version ≥ ``min_major``, or None.

    Searches the folders in ``CM2_LIBLLVM_DIRS`` (``os.pathsep``-separated, globs allowed)
    when set, else the usual system and Homebrew folders and ``$CONDA_PREFIX/lib``.
    """
    if "CM2_LIBLLVM_DIRS" in os.environ:
        patterns = [p for p in os.environ["CM2_LIBLLVM_DIRS"].split(os.pathsep) if p]
    else:
        patterns = list(_DEFAULT_DIRS)
        if os.environ.get("CONDA_PREFIX"):
            patterns.append(str(Path(os.environ["CONDA_PREFIX"]) / "lib"))
    found: list[tuple[int, str]] = []
    for pattern in patterns:
        for folder in glob.glob(pattern):
            for candidate in glob.glob(os.path.join(folder, "libLLVM*")):
                path = Path(candidate)
                major = _llvm_major(path)
                if major is not None and major >= min_major and path.is_file():
                    found.append((major, str(path.resolve())))
    return Path(max(found)[1]) if found else None


@dataclass(frozen=True)
class Backend:
    """The chosen Mitsuba variant and why.

    variant: Mitsuba variant name (``llvm_ad_rgb``, ``cuda_ad_rgb``, ``scalar_rgb`` …).
    libllvm: the LLVM library Dr.Jit was pointed at (None for CUDA/scalar).
    reason: one line for logs and reports.
    """

    variant: str
    libllvm: str | None
    reason: str


_BACKEND: Backend | None = None
_WARNED = False


def _choose() -> Backend:
    forced = os.environ.get("CM2_ILLUM_VARIANT")
    if forced:
        return Backend(forced, os.environ.get("DRJIT_LIBLLVM_PATH"), "CM2_ILLUM_VARIANT set")
    explicit = os.environ.get("DRJIT_LIBLLVM_PATH")
    if explicit:
        path = Path(explicit)
        major = _llvm_major(path)
        if path.is_file() and (major is None or major >= MIN_LLVM_MAJOR):
            return Backend("llvm_ad_rgb", str(path), f"DRJIT_LIBLLVM_PATH = {path}")
        why = "does not exist" if not path.is_file() else f"is LLVM {major} (< {MIN_LLVM_MAJOR})"
        return Backend("scalar_rgb", None, f"DRJIT_LIBLLVM_PATH = {path} {why}")
    found = find_libllvm()
    if found is not None:
        return Backend("llvm_ad_rgb", str(found), f"found {found}")
    return Backend("scalar_rgb", None, f"no LLVM ≥ {MIN_LLVM_MAJOR} shared library found")


def _prepare_llvm(backend: Backend) -> None:
    """Point ``DRJIT_LIBLLVM_PATH`` at the chosen LLVM (before Dr.Jit is imported, if it is not yet)."""
    if not (backend.variant.startswith("llvm") and backend.libllvm):
        return
    if "drjit" in sys.modules and os.environ.get("DRJIT_LIBLLVM_PATH") != backend.libllvm:
        warnings.warn(
            "Dr.Jit was imported before cm2optics.optics.backend could point DRJIT_LIBLLVM_PATH at "
            f"{backend.libllvm}; if its own choice is LLVM < {MIN_LLVM_MAJOR} kernels will fail",
            RuntimeWarning,
            stacklevel=3,
        )
    os.environ["DRJIT_LIBLLVM_PATH"] = backend.libllvm


def variant() -> Backend:
    """Choose the variant once per process (see the module docstring) and prepare the
    environment for it."""
    global _BACKEND
    if _BACKEND is not None:
        return _BACKEND
    backend = _choose()
    _prepare_llvm(backend)
    if not os.environ.get("CM2_ILLUM_VARIANT") and not backend.variant.startswith("scalar"):
        # CUDA beats the CPU when a device is there (checking it never touches LLVM).
        try:
            import drjit as dr

            if dr.has_backend(dr.JitBackend.CUDA):
                backend = Backend("cuda_ad_rgb", None, "CUDA device found")
        except Exception:  # noqa: BLE001 - no CUDA driver: stay on the CPU
            pass
    _BACKEND = backend
    return backend


def is_jit() -> bool:
    """Whether the tracer runs vectorised (LLVM or CUDA) rather than one ray at a time."""
    return not variant().variant.startswith("scalar")


def mitsuba() -> ModuleType:
    """Mitsuba with the chosen variant set; warns once per process on the scalar fallback."""
    global _WARNED
    backend = variant()
    import mitsuba as mi

    if mi.variant() != backend.variant:
        mi.set_variant(backend.variant)
    if backend.variant.startswith("scalar") and not os.environ.get("CM2_ILLUM_VARIANT") and not _WARNED:
        _WARNED = True
        warnings.warn(
            f"ray tracing: {backend.reason}; tracing on Mitsuba's scalar variant, one ray at a time "
            f"(≈ 10³ rays/s). Install LLVM ≥ {MIN_LLVM_MAJOR} (Debian/Ubuntu: apt install libllvm19) or set "
            "DRJIT_LIBLLVM_PATH to its libLLVM for ≈ 10⁶ rays/s.",
            RuntimeWarning,
            stacklevel=2,
        )
    return mi


# Point Dr.Jit at a good LLVM as soon as this module is imported, before anything else in
# the process can import Dr.Jit with its own (possibly broken) choice. (Cheap: file names only;
# Dr.Jit itself is imported when a variant is first needed.)
_prepare_llvm(_choose())
