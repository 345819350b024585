"""The array-backend shim: the few element-wise operations the optics core needs, for NumPy
arrays and for Dr.Jit arrays (Mitsuba's JIT variants), under the same names."""

from __future__ import annotations

from typing import Any

import numpy as np

from cm2optics.optics.backend import mitsuba

__all__ = ["DrJitOps", "NumpyOps", "drjit_ops", "numpy_ops"]


class NumpyOps:
    """Element-wise operations on NumPy arrays (and Python floats)."""

    sqrt = staticmethod(np.sqrt)
    abs = staticmethod(np.abs)
    select = staticmethod(np.where)
    maximum = staticmethod(np.maximum)
    minimum = staticmethod(np.minimum)

    @staticmethod
    def full(value: float, like: np.ndarray) -> np.ndarray:
        return np.full(np.shape(like), value, dtype=float)


class DrJitOps:
    """The same operations on Dr.Jit arrays of the chosen Mitsuba variant (float64)."""

    def __init__(self) -> None:
        import drjit as dr

        mi = mitsuba()
        self.dr = dr
        self.sqrt = dr.sqrt
        self.abs = dr.abs
        self.select = dr.select
        self.maximum = dr.maximum
        self.minimum = dr.minimum
        self.Float64 = mi.Float64

    def full(self, value: float, like: Any) -> Any:
        return self.dr.full(self.Float64, value, self.dr.width(like))


def numpy_ops() -> NumpyOps:
    """The NumPy operations."""
    return NumpyOps()


def drjit_ops() -> DrJitOps:
    """The Dr.Jit operations (sets the Mitsuba variant on first use)."""
    return DrJitOps()
