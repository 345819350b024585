"""A collimator's section swept into a watertight triangle mesh, without CAD: for tracing,
design sweeps and STL export of candidates (the CAD part comes from :mod:`cm2optics.cad.collimator`).
A freeform lens sag (:mod:`cm2optics.optics.freeform`) is applied to the swept vertices, as the
CAD part applies it to its tessellation; a non-revolved TIR wall (``tir_cos2``, ``tir_cos4``:
:func:`cm2optics.optics.collimator.tir_wall_scale`) scales the wall's rings about the entry ring."""

from __future__ import annotations

import numpy as np
import trimesh

from cm2optics.optics.collimator import CollimatorProfile, tir_wall_scale
from cm2optics.optics.freeform import displace_lens

__all__ = ["revolve_profile"]


def _square_ring(half: float, z: float, angles: np.ndarray) -> np.ndarray:
    c, s = np.cos(angles), np.sin(angles)
    k = half / np.maximum(np.abs(c), np.abs(s))
    return np.column_stack([k * c, k * s, np.full_like(angles, z)])


def revolve_profile(
    profile: CollimatorProfile,
    segments: int = 256,
    lens_freeform_um: tuple[float, ...] = (),
    tir_azimuthal: tuple[float, float] = (0.0, 0.0),
) -> trimesh.Trimesh:
    """A watertight mesh of the collimator: the section's rings swept about the axis
    (``segments`` per turn, a multiple of 8 so that the flange's corners are vertices), from the
    exit face's centre round the flange, down the outer wall, in through the cavity to the
    lens vertex, with the lens sag of Zernike coefficients ``lens_freeform_um`` (µm) and the
    outer wall's radial departure from its entry ring scaled by ``1 + c₂ cos 2φ + c₄ cos 4φ``
    (``tir_azimuthal`` = (c₂, c₄), :attr:`cm2optics.design.Collimator.tir_cos2`). Outward normals."""
    if segments % 8:
        raise ValueError(f"segments = {segments}: must be a multiple of 8")
    angles = 2 * np.pi * np.arange(segments) / segments
    half = profile.footprint_mm / 2
    ring_list: list[np.ndarray | tuple[float, float]] = [(0.0, profile.exit_z_mm)]  # pole
    ring_list.append(_square_ring(half, profile.exit_z_mm, angles))
    ring_list.append(_square_ring(half, profile.flange_bottom_z_mm, angles))
    r_end, z_end = profile.tir_r_mm[-1], profile.tir_z_mm[-1]
    section: list[tuple[float, float]] = [(r_end, profile.flange_bottom_z_mm)]
    if profile.flange_bottom_z_mm - z_end > 1e-6:
        section.append((r_end, z_end))
    section += list(zip(profile.tir_r_mm[::-1][1:], profile.tir_z_mm[::-1][1:], strict=True))
    wall_rings = len(section)  # the wall and its step to the flange, top first (the entry ring after)
    section += [(profile.outer_radius_entry_mm, profile.entry_z_mm), (profile.cavity_radius_mm, profile.entry_z_mm)]
    section += list(zip(profile.lens_r_mm[::-1], profile.lens_z_mm[::-1], strict=True))[:-1]
    scale = tir_wall_scale(*tir_azimuthal, angles)
    for i, (r, z) in enumerate(section):
        if i < wall_rings and any(c != 0.0 for c in tir_azimuthal):
            r = profile.outer_radius_entry_mm + (r - profile.outer_radius_entry_mm) * scale
        ring_list.append(np.column_stack([r * np.cos(angles), r * np.sin(angles), np.full(segments, z)]))
    ring_list.append((0.0, float(profile.lens_z_mm[0])))  # pole at the lens vertex
    vertices: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    offsets = []
    count = 0
    for ring in ring_list:
        if isinstance(ring, tuple):
            vertices.append(np.array([[0.0, 0.0, ring[1]]]))
            offsets.append((count, 1))
            count += 1
        else:
            vertices.append(ring)
            offsets.append((count, segments))
            count += segments
    k = np.arange(segments)
    k1 = (k + 1) % segments
    for (a0, na), (b0, nb) in zip(offsets[:-1], offsets[1:], strict=True):
        if na == 1:
            faces.append(np.column_stack([np.full(segments, a0), b0 + k, b0 + k1]))
        elif nb == 1:
            faces.append(np.column_stack([a0 + k, np.full(segments, b0), a0 + k1]))
        else:
            faces.append(np.column_stack([a0 + k, b0 + k, b0 + k1]))
            faces.append(np.column_stack([a0 + k, b0 + k1, a0 + k1]))
    points = np.vstack(vertices)
    if any(c != 0.0 for c in lens_freeform_um):
        points = displace_lens(points, profile, lens_freeform_um)
    mesh = trimesh.Trimesh(points, np.vstack(faces), process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh
