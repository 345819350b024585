"""Registered crops too large for memory: kept on disk, read in chunks of positions.

A dense scan's crops (N × J × h × w float32; 18,491 positions of nine 224² ePSF crops are 33 GB)
need not fit in memory: :func:`crop_array` gives a plain array when they fit within
``memory_bytes`` and otherwise a :class:`CropStore`, an HDF5 dataset in an anonymous temporary
file (gone when closed, also after a crash) that every build step reads ``chunk`` positions at a
time (:func:`position_chunks`). Indexing a store by position (``store[n]``, ``store[a:b]``,
``store[n, j]``) returns a NumPy array, as indexing the in-memory array does.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from typing import Any

import numpy as np

__all__ = ["CropStore", "crop_array", "crop_bytes", "position_chunks"]

#: Crops held in memory up to this size (bytes) by default; larger ones are streamed from disk.
DEFAULT_MEMORY_BYTES = 4 * 1024**3


def crop_bytes(shape: tuple[int, ...]) -> int:
    """Bytes of float32 crops of ``shape`` (N, J, h, w)."""
    return int(np.prod(shape, dtype=np.int64)) * 4


class CropStore:
    """(N, J, h, w) float32 crops in a temporary HDF5 file, read ``chunk`` positions at a time;
    ``window`` (rows, cols) cuts every crop as it is read (the trimmed basis's margins)."""

    def __init__(
        self, dataset: Any, chunk: int, window: tuple[slice, slice] = (slice(None), slice(None)), owner: Any = None
    ) -> None:
        self.dataset, self.chunk, self.window = dataset, int(chunk), window
        self.owner = owner  # the temporary file and its HDF5 handle: deleted when no store refers to them
        h, w = dataset.shape[2:]
        rows, cols = (range(n)[s] for s, n in zip(window, (h, w), strict=True))
        self.shape = (dataset.shape[0], dataset.shape[1], len(rows), len(cols))
        self.dtype = np.dtype(np.float32)
        self.ndim = 4

    @classmethod
    def create(cls, shape: tuple[int, int, int, int], chunk: int) -> CropStore:
        """An empty store of ``shape`` (N, J, h, w) in an anonymous temporary file."""
        import h5py

        handle = tempfile.TemporaryFile(prefix="cm2optics-crops-")
        file = h5py.File(handle, "w")
        dataset = file.create_dataset("crops", shape=shape, dtype=np.float32, chunks=(1, *shape[1:]))
        return cls(dataset, chunk, owner=(handle, file))

    def __len__(self) -> int:
        return self.shape[0]

    def __setitem__(self, n: int, value: np.ndarray) -> None:
        self.dataset[n] = value

    def __getitem__(self, key: Any) -> np.ndarray:
        rows, cols = self.window
        if isinstance(key, tuple):
            return np.asarray(self.dataset[key + (slice(None),) * (2 - len(key))][..., rows, cols])
        if isinstance(key, np.ndarray | list):  # fancy indexing: h5py wants increasing indices
            order = np.asarray(key)
            if order.dtype == bool:
                order = np.flatnonzero(order)
            unique, inverse = np.unique(order, return_inverse=True)
            return np.asarray(self.dataset[unique][..., rows, cols])[inverse]
        return np.asarray(self.dataset[key][..., rows, cols])

    def windowed(self, rows: slice, cols: slice) -> CropStore:
        """The same crops cut to ``rows``, ``cols`` (of the current window's samples)."""
        current_rows, current_cols = (range(n)[s] for s, n in zip(self.window, self.dataset.shape[2:], strict=True))
        window = (_compose(current_rows, rows), _compose(current_cols, cols))
        return CropStore(self.dataset, self.chunk, window, self.owner)


def _compose(outer: range, inner: slice) -> slice:
    """The slice of the full axis that ``inner`` of the ``outer`` range selects (unit steps)."""
    picked = outer[inner]
    return slice(picked.start, picked.stop) if len(picked) else slice(0, 0)


def crop_array(shape: tuple[int, int, int, int], memory_bytes: int = DEFAULT_MEMORY_BYTES) -> np.ndarray | CropStore:
    """Zeroed crops of ``shape`` (N, J, h, w): in memory if they take at most ``memory_bytes``,
    else a :class:`CropStore` read in chunks of about a quarter of ``memory_bytes``."""
    if crop_bytes(shape) <= memory_bytes:
        return np.zeros(shape, np.float32)
    chunk = max(1, memory_bytes // 4 // crop_bytes((1, *shape[1:])))
    return CropStore.create(shape, chunk)


def position_chunks(crops: np.ndarray | CropStore) -> Iterator[tuple[int, np.ndarray]]:
    """(first position, crops of a chunk of positions): the whole array at once if it is in memory."""
    if isinstance(crops, np.ndarray):
        yield 0, crops
        return
    for start in range(0, len(crops), crops.chunk):
        yield start, crops[start : start + crops.chunk]
