"""Validation helpers of the design's dataclasses: :class:`DesignError` names the dotted field,
the value and what is allowed.
"""

from __future__ import annotations

import math
from typing import Any

from cm2optics.errors import UserError

__all__ = ["DesignError", "check", "in_range", "non_negative", "positive"]


class DesignError(UserError):
    """A design value that is missing, misspelled, mistyped or physically impossible.

    ``field`` is the dotted path of the offending field (``mla.radius_mm``).
    """

    def __init__(self, field_path: str, value: Any, allowed: str):
        self.field = field_path
        self.value = value
        self.allowed = allowed
        super().__init__(f"{field_path} = {value!r}: {allowed}")


def check(name: str, value: Any, ok: bool, allowed: str) -> None:
    if not ok:
        raise DesignError(name, value, allowed)


def positive(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        check(name, value, math.isfinite(value) and value > 0, "must be a finite number > 0")


def non_negative(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        check(name, value, math.isfinite(value) and value >= 0, "must be a finite number ≥ 0")


def in_range(obj: Any, name: str, low: float, high: float, unit: str = "") -> None:
    value = getattr(obj, name)
    check(name, value, math.isfinite(value) and low <= value <= high, f"must lie within {low}–{high}{unit}")
