"""Emitter lists on disk: one type, one reader, one writer (no torch here).

An emitter list is a CSV with columns ``x_um,y_um,z_um,diameter_um,intensity`` (DESIGN.md), in
the volumes' physical coordinates (µm; x, y from the central lenslet's axis, z from the nominal
focal plane, +z towards the device); ``diameter_um`` is the diameter of a uniform ball (0: a
point); ``intensity`` its total emission (any linear unit, ≥ 0).

The reader is lenient about layout and strict about values: lines starting with ``#`` are
comments, blank lines are skipped, the columns may come in any order (further columns are
ignored); a missing column, a value that is not a finite number or a negative diameter or
intensity raises :class:`~cm2optics.formats.volume.VolumeError` naming the file and line.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cm2optics.formats.atomic import write_text_atomic
from cm2optics.formats.volume import VolumeError

__all__ = ["EMITTER_COLUMNS", "Emitters", "read_emitters", "write_emitters"]

EMITTER_COLUMNS = ("x_um", "y_um", "z_um", "diameter_um", "intensity")


@dataclass(frozen=True)
class Emitters:
    """Uniform balls: centres (µm, object space), diameters (µm, 0 = point), total intensities."""

    x_um: np.ndarray
    y_um: np.ndarray
    z_um: np.ndarray
    diameter_um: np.ndarray
    intensity: np.ndarray

    def __post_init__(self) -> None:
        arrays = [np.atleast_1d(np.asarray(getattr(self, c), dtype=np.float64)) for c in EMITTER_COLUMNS]
        n = len(arrays[0])
        for name, array in zip(EMITTER_COLUMNS, arrays, strict=True):
            if array.ndim != 1 or len(array) != n:
                raise VolumeError(f"emitters: {name} must be a 1-D array of length {n}")
            if not np.all(np.isfinite(array)):
                raise VolumeError(f"emitters: {name} contains NaN or infinite values")
            object.__setattr__(self, name, array)
        if np.any(self.diameter_um < 0):
            raise VolumeError("emitters: diameter_um must be ≥ 0")
        if np.any(self.intensity < 0):
            raise VolumeError("emitters: intensity must be ≥ 0")

    @classmethod
    def from_positions_um(cls, positions_um: np.ndarray, diameter_um: np.ndarray, intensity: np.ndarray) -> Emitters:
        """Emitters from (N, 3) centres as (x, y, z), µm, and (N,) diameters (µm) and intensities."""
        positions = np.asarray(positions_um, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise VolumeError(f"emitters: positions_um has shape {positions.shape}: must be (N, 3)")
        return cls(positions[:, 0], positions[:, 1], positions[:, 2], diameter_um, intensity)

    def __len__(self) -> int:
        return len(self.x_um)

    @property
    def positions_um(self) -> np.ndarray:
        """(N, 3) positions as (x, y, z), µm."""
        return np.stack([self.x_um, self.y_um, self.z_um], axis=1)

    def positions_mm(self) -> np.ndarray:
        """(N, 3) positions as (x, y, z), mm."""
        return self.positions_um / 1000.0

    def subset(self, index: np.ndarray) -> Emitters:
        return Emitters(*(getattr(self, c)[index] for c in EMITTER_COLUMNS))


def read_emitters(path: str | Path) -> Emitters:
    """Read an emitter CSV (columns :data:`EMITTER_COLUMNS` in any order, ``#`` comments)."""
    path = Path(path)
    if not path.is_file():
        raise VolumeError(f"{path}: no such emitter file")
    columns: dict[str, list[float]] = {c: [] for c in EMITTER_COLUMNS}
    index: dict[str, int] | None = None
    with path.open(newline="") as handle:
        for line, text in enumerate(handle, start=1):
            if not text.strip() or text.lstrip().startswith("#"):
                continue
            cells = [c.strip() for c in next(csv.reader([text]))]
            if index is None:
                missing = [c for c in EMITTER_COLUMNS if c not in cells]
                if missing:
                    raise VolumeError(
                        f"{path} line {line}: columns must be {','.join(EMITTER_COLUMNS)} in any order "
                        f"(missing {', '.join(missing)}; found {','.join(cells)})"
                    )
                index = {c: cells.index(c) for c in EMITTER_COLUMNS}
                continue
            for column in EMITTER_COLUMNS:
                cell = cells[index[column]] if index[column] < len(cells) else ""
                try:
                    value = float(cell)
                except ValueError:
                    raise VolumeError(f"{path} line {line}: {column} = {cell!r} is not a number") from None
                if not math.isfinite(value):
                    raise VolumeError(f"{path} line {line}: {column} = {cell!r} is not finite")
                columns[column].append(value)
            if columns["diameter_um"][-1] < 0 or columns["intensity"][-1] < 0:
                raise VolumeError(f"{path} line {line}: diameter_um and intensity must be ≥ 0")
    if index is None:
        raise VolumeError(f"{path}: no header (columns {','.join(EMITTER_COLUMNS)})")
    return Emitters(*(np.asarray(columns[c]) for c in EMITTER_COLUMNS))


def write_emitters(path: str | Path, emitters: Emitters) -> Path:
    """Write an emitter CSV atomically."""
    buffer = io.StringIO()
    buffer.write(",".join(EMITTER_COLUMNS) + "\n")
    for row in zip(*(getattr(emitters, c) for c in EMITTER_COLUMNS), strict=True):
        buffer.write(",".join(f"{v:.6g}" for v in row) + "\n")
    return write_text_atomic(Path(path), buffer.getvalue())
