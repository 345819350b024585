"""Per-focus features: energy, centroid and width of every focus in matching windows.

Every image holds one focus per lenslet. A focus is measured in a circular window around its
predicted position: its energy (sum of the signal above dark, counts), its centroid (row, col
px) and its RMS radius (px, the square root of the second central moment). Data and model are
measured in the same windows, so their ratios and differences isolate what differs between them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FocusFeatures:
    """Features of J foci in N images (NaN where a window falls off the frame or holds no light).

    energy: (N, J) counts.
    centroid_px: (N, J, 2) (row, col).
    width_px: (N, J) RMS radius.
    """

    energy: np.ndarray
    centroid_px: np.ndarray
    width_px: np.ndarray


def _windows(shape: tuple[int, int], centres: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row indices (N, J, w, 1) and col indices (N, J, 1, w) of square windows (they broadcast to
    the windows' pixels), and which pixels lie on the frame (N, J, w, w)."""
    offsets = np.arange(-half, half + 1)
    base = np.rint(centres).astype(int)
    rows = base[..., 0, None, None] + offsets[:, None]
    cols = base[..., 1, None, None] + offsets[None, :]
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    return np.clip(rows, 0, shape[0] - 1), np.clip(cols, 0, shape[1] - 1), inside


def circular_windows(
    shape: tuple[int, int], centres: np.ndarray, radius_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Row indices (N, J, w, 1) and col indices (N, J, 1, w) of windows around ``centres``
    (N, J, 2) px, which of their pixels (N, J, w, w) lie within ``radius_px`` (N, J) and on the
    frame, and whether each whole circle does."""
    half = int(np.ceil(np.nanmax(radius_px)))
    rows, cols, on_frame = _windows(shape, centres, half)
    distance = np.hypot(rows - centres[..., 0, None, None], cols - centres[..., 1, None, None])
    within = distance <= radius_px[..., None, None]
    complete = np.all(on_frame | ~within, axis=(-2, -1))
    return rows, cols, within & on_frame, complete


def away_from_foci(shape: tuple[int, int], centres: np.ndarray, radius_px: np.ndarray) -> np.ndarray:
    """(N, y, x) pixels farther than ``radius_px`` (N, J) from every focus centre (N, J, 2) px
    (each disc cleared within its bounding box; an image with a NaN centre or radius has none)."""
    out = np.ones((len(centres),) + tuple(shape), bool)
    for n, j in np.ndindex(*centres.shape[:2]):  # N·J small boxes, not N·J full frames
        (row, col), radius = centres[n, j], radius_px[n, j]
        if not np.isfinite([row, col, radius]).all():
            out[n] = False
            continue
        r0, r1 = max(int(np.floor(row - radius)), 0), min(int(np.ceil(row + radius)) + 1, shape[0])
        c0, c1 = max(int(np.floor(col - radius)), 0), min(int(np.ceil(col + radius)) + 1, shape[1])
        if r0 < r1 and c0 < c1:
            rows, cols = np.arange(r0, r1)[:, None], np.arange(c0, c1)[None, :]
            out[n, r0:r1, c0:c1] &= np.hypot(rows - row, cols - col) > radius
    return out


def focus_features(signal: np.ndarray, centres: np.ndarray, radius_px: np.ndarray) -> FocusFeatures:
    """Measure the foci of ``signal`` (N, y, x) (counts above dark).

    centres: (N, J, 2) window centres (row, col) px.
    radius_px: (N, J) window radii, px.
    """
    rows, cols, weight, complete = circular_windows(signal.shape[-2:], centres, radius_px)
    image_index = np.arange(len(centres))[:, None, None, None]
    values = np.where(weight, signal[image_index, rows, cols].astype(np.float64), 0.0)
    return window_features(values, rows, cols, complete)


#: Width of the ring at each window's edge that gives the window's own background, px.
RING_PX = 1.5
#: Frames whose windows are held at once by :func:`local_centroids`.
CENTROID_BLOCK = 16


def local_centroids(signal: np.ndarray, centres: np.ndarray, radius_px: np.ndarray) -> np.ndarray:
    """(N, J, 2) centroids (row, col) px of the foci of ``signal`` (N, y, x) in the windows of
    :func:`focus_features`, each window's own background removed first: a plane fitted to its
    outermost :data:`RING_PX` (a background that changes across the sensor, room light or a
    gradient, pulls the plain centroid of a dim focus towards its bright side); NaN where
    :func:`focus_features` has none."""
    if len(signal) > CENTROID_BLOCK:  # a block of frames at a time: the windows' memory
        return np.concatenate(
            [
                local_centroids(
                    signal[b : b + CENTROID_BLOCK], centres[b : b + CENTROID_BLOCK], radius_px[b : b + CENTROID_BLOCK]
                )
                for b in range(0, len(signal), CENTROID_BLOCK)
            ]
        )
    rows, cols, weight, complete = circular_windows(signal.shape[-2:], centres, radius_px)
    image_index = np.arange(len(centres))[:, None, None, None]
    values = signal[image_index, rows, cols].astype(np.float64)
    dr = np.broadcast_to(rows - centres[..., 0, None, None], values.shape)
    dc = np.broadcast_to(cols - centres[..., 1, None, None], values.shape)
    ring = (weight & (np.hypot(dr, dc) > radius_px[..., None, None] - RING_PX)).astype(np.float64)
    basis = np.stack([np.ones_like(dr), dr, dc], axis=-1)  # (N, J, w, w, 3): a + b·Δrow + c·Δcol
    gram = np.einsum("...yxi,...yxk,...yx->...ik", basis, basis, ring)
    rhs = np.einsum("...yxi,...yx->...i", basis, ring * values)
    solvable = np.linalg.det(gram) > 1e-9
    gram[~solvable] = np.eye(3)
    plane = np.linalg.solve(gram, np.where(solvable[..., None], rhs, 0.0)[..., None])[..., 0]
    values = np.where(weight, values - np.einsum("...yxi,...i->...yx", basis, plane), 0.0)
    return window_features(values, rows, cols, complete).centroid_px


def window_features(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, complete: np.ndarray) -> FocusFeatures:
    """The features of :func:`focus_features` from the window pixels themselves: ``values``
    (N, J, w, w) signal above dark, 0 outside each circle; ``rows`` (N, J, w, 1), ``cols``
    (N, J, 1, w) their pixel indices and ``complete`` (N, J) whether each circle lies on the
    frame (:func:`circular_windows`). The moments are taken on the window's row and column sums."""
    along_rows = values.sum(axis=-1)  # (N, J, w): the signal of each of the window's rows
    along_cols = values.sum(axis=-2)
    row_index, col_index = rows[..., :, 0], cols[..., 0, :]
    energy = along_rows.sum(axis=-1)
    # moments of the signal as it is (noise below zero included), so that noise averages out
    # and data and model are measured alike
    with np.errstate(invalid="ignore", divide="ignore"):
        row_c = (along_rows * row_index).sum(axis=-1) / energy
        col_c = (along_cols * col_index).sum(axis=-1) / energy
        spread = (along_rows * (row_index - row_c[..., None]) ** 2).sum(axis=-1)
        second = (spread + (along_cols * (col_index - col_c[..., None]) ** 2).sum(axis=-1)) / energy
    second = np.where(second > 0, second, np.nan)
    dark = ~complete | (energy <= 0)
    energy = np.where(complete, energy, np.nan)
    centroid = np.where(dark[..., None], np.nan, np.stack([row_c, col_c], axis=-1))
    width = np.where(dark, np.nan, np.sqrt(second))
    return FocusFeatures(energy, centroid, width)


def window_radii(model_signal: np.ndarray, centres: np.ndarray, pitch_px: float) -> np.ndarray:
    """Window radii (N, J) px that hold each model focus: 3× its RMS radius plus 2 px, at most
    0.45 of the lenslet pitch (so neighbouring lenslets' foci stay out), at least 3 px."""
    limit = max(3.0, 0.45 * pitch_px)
    first = focus_features(model_signal, centres, np.full(centres.shape[:2], limit))
    radii = 3.0 * np.nan_to_num(first.width_px, nan=limit) + 2.0
    return np.clip(radii, 3.0, limit)


def focus_windows(model_signal: np.ndarray, centres_px: np.ndarray, pitch_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Window centres (N, J, 2) and radii (N, J), px, for measuring data and model alike: each
    predicted centre moved to the model focus's own centroid (where it has light), each radius
    sized to hold the model focus (:func:`window_radii`)."""
    wide = np.full(centres_px.shape[:2], max(3.0, 0.45 * pitch_px))
    refined = focus_features(model_signal, centres_px, wide).centroid_px
    centres = np.where(np.isnan(refined), centres_px, refined)
    return centres, window_radii(model_signal, centres, pitch_px)


def focus_patches(values: np.ndarray, centres: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Square patches (N, J, 2·half + 1, 2·half + 1) of ``values`` (N, y, x) centred on the pixel
    nearest each focus centre (N, J, 2) (row, col) px, and (N, J) whether the patch lies whole on
    the frame (False also for a NaN centre; its patch is zeros)."""
    n, h, w = values.shape
    known = np.isfinite(centres).all(axis=-1)
    centre = np.rint(np.where(known[..., None], centres, 0.0)).astype(int)
    inside = known & (centre[..., 0] >= half) & (centre[..., 0] < h - half)
    inside &= (centre[..., 1] >= half) & (centre[..., 1] < w - half)
    offsets = np.arange(-half, half + 1)
    rows = np.clip(centre[..., 0, None, None] + offsets[:, None], 0, h - 1)
    cols = np.clip(centre[..., 1, None, None] + offsets[None, :], 0, w - 1)
    patches = values[np.arange(n)[:, None, None, None], rows, cols]
    return np.where(inside[..., None, None], patches, 0.0), inside
