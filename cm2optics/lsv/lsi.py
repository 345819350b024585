"""The depth-wise shift-invariant (LSI) baseline of the V1 paper (Xue et al., Sci. Adv. 2020).

Every depth plane is convolved with one PSF, the on-axis PSF at that depth (its nine foci with
their axial shear), and the object is mapped onto the sensor with the in-focus magnification
at every depth. It is an :class:`~cm2optics.lsv.model.LSVModel` with a single lateral node (the
on-axis stack, interpolated in z) and a depth-independent ``A``, so the same operators run it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cm2optics.lsv.model import LSVModel
from cm2optics.lsv.preprocess import Geometry, _polyfit

__all__ = ["lsi_model"]


def lsi_model(model: LSVModel) -> LSVModel:
    """The depth-wise LSI baseline made from ``model``'s on-axis PSF stack."""
    x0, y0 = model.provenance.get("geometry", {}).get("axis_position_mm", (0.0, 0.0))
    zs = model.grid_z_mm
    on_axis = model.coefficients_at(np.full(len(zs), x0), np.full(len(zs), y0), zs)  # (nz, K)
    coefficients = np.ascontiguousarray(on_axis.T[:, :, None, None], dtype=np.float32)
    geometry = model.geometry
    A0 = geometry.A(0.0)
    # the on-axis source lands where the LSV model puts it: r0_LSI(z) + A0·(x0, y0) = r0(z) + A(z)·(x0, y0)
    r_axis = geometry.r0(zs) + np.einsum("zab,b->za", geometry.A(zs) - A0[None], np.array([x0, y0]))
    degree = len(geometry.r0_poly) - 1
    lsi_geometry = Geometry(
        r0_poly=_polyfit(zs, r_axis, degree) if len(zs) > 1 else geometry.r0_poly,
        A_poly=A0[None].copy(),
        o_poly=geometry.o_poly,
        rows=geometry.rows,
        cols=geometry.cols,
    )
    provenance = dict(model.provenance)
    provenance["baseline"] = "depth-wise LSI (V1): the on-axis PSF stack, in-focus magnification at every depth"
    return replace(
        model,
        coefficients=coefficients,
        grid_x_mm=np.array([float(x0)]),
        grid_y_mm=np.array([float(y0)]),
        geometry=lsi_geometry,
        provenance=provenance,
    )
