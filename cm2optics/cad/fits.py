"""Fits between a part and the seat that holds it, reported by each housing module."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Fit:
    """One seated part: ``clearance_mm`` is the gap per side between part and seat, mm."""

    part: str
    seat: str
    clearance_mm: float

    def as_dict(self) -> dict[str, object]:
        return {"part": self.part, "seat": self.seat, "clearance_mm": round(self.clearance_mm, 4)}
