"""Pictures of parts and assemblies, rendered off-screen with PyVista (EGL, no display needed)."""

from __future__ import annotations

import os
from pathlib import Path

if not os.environ.get("DISPLAY"):
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np
import pyvista as pv
import trimesh

from cm2optics.formats.atomic import write_atomic

#: Colours by material family, so a picture reads like the device.
_COLOURS = {
    "black resin": "#3a3a3a",
    "clear-resin": "#9fd3ff",
    "pmma": "#b8e6ff",
    "n-bk7": "#ffd27f",
    "gelatin": "#ffb000",
    "black shim": "#111111",
    "LED": "#f4f4f4",
    "FR-4": "#1f6b3a",
    "ceramic": "#c9b89a",
}


def _to_pyvista(mesh: trimesh.Trimesh) -> pv.PolyData:
    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    return pv.PolyData(np.asarray(mesh.vertices), faces)


def render_meshes(
    meshes: list[tuple[trimesh.Trimesh, str]],
    path: Path,
    title: str = "",
    section_normal: tuple[float, float, float] | None = None,
    size: tuple[int, int] = (1000, 800),
) -> Path:
    """Render ``(mesh, material)`` pairs to a PNG at ``path``; with ``section_normal``, cut
    everything by the plane through the origin with that normal (a cross-section view)."""
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    plotter.set_background("white")
    for mesh, material in meshes:
        poly = _to_pyvista(mesh)
        if section_normal is not None:
            poly = poly.clip(normal=section_normal, origin=(0.0, 0.0, 0.0), invert=False)
            if poly.n_points == 0:
                continue
        plotter.add_mesh(poly, color=_COLOURS.get(material, "#8899aa"), smooth_shading=False, specular=0.2)
    if title:
        plotter.add_text(title, font_size=10, color="black")
    plotter.show_axes()
    if section_normal is not None:
        plotter.view_vector((0.0, -1.0, 0.15), viewup=(0.0, 0.0, 1.0))
    else:
        plotter.view_isometric()
    plotter.camera.zoom(1.2)
    write_atomic(Path(path), lambda tmp: plotter.screenshot(str(tmp)))
    plotter.close()
    return Path(path)


def render_part(
    mesh: trimesh.Trimesh, material: str, path: Path, title: str, size: tuple[int, int] = (1400, 700)
) -> Path:
    """Two panels: the part seen from above at an angle, and its section through the centre
    of its bounding box (plane y = const, seen along −y)."""
    poly = _to_pyvista(mesh)
    centre = mesh.bounds.mean(axis=0)
    plotter = pv.Plotter(off_screen=True, window_size=list(size), shape=(1, 2))
    colour = _COLOURS.get(material, "#8899aa")
    plotter.subplot(0, 0)
    plotter.set_background("white")
    plotter.add_mesh(poly, color=colour, specular=0.2)
    plotter.add_text(title, font_size=10, color="black")
    plotter.view_isometric()
    plotter.show_axes()
    plotter.subplot(0, 1)
    plotter.set_background("white")
    plotter.add_mesh(poly.clip(normal=(0.0, 1.0, 0.0), origin=tuple(centre), invert=False), color=colour, specular=0.2)
    plotter.add_text("section through the centre", font_size=10, color="black")
    plotter.view_vector((0.0, -1.0, 0.0), viewup=(0.0, 0.0, 1.0))
    plotter.show_axes()
    write_atomic(Path(path), lambda tmp: plotter.screenshot(str(tmp)))
    plotter.close()
    return Path(path)
