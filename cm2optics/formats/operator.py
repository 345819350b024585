"""The protocol every forward model's operator follows (no torch here: arrays are duck-typed).

An operator maps a volume ``(z, y, x)`` on its :class:`~cm2optics.formats.volume.VolumeGrid` to
a sensor image ``(y, x)`` and back: ``forward(volume)`` and its adjoint ``adjoint(image)``, with
⟨A x, y⟩ = ⟨x, Aᵀ y⟩. Both take a numpy array (and give one back) or a torch tensor (and give a
tensor), with optional leading batch dimensions. The 3D-LSV operator
(:class:`cm2optics.lsv.operators.LSVOperator`) is one, the depth-wise LSI operator
(:class:`cm2optics.lsv.lsi.DepthwiseConvOperator`) another, and so is any small operator a test
writes. Optional extras: ``forward(volume, per_lenslet=True)`` (the J crosstalk-free images)
and ``chief_rays_px()`` ((J, 2) focus of each lenslet for a source at the centre of the focal
plane), which the synthesiser uses.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from cm2optics.formats.volume import VolumeGrid

__all__ = ["VolumeOperator"]


@runtime_checkable
class VolumeOperator(Protocol):
    """What a solver needs from a forward model (see the module docstring).

    grid: the volume grid (z, y, x). sensor_shape: (rows, cols) of the image, px.
    """

    grid: VolumeGrid
    sensor_shape: tuple[int, int]

    def forward(self, volume: Any) -> Any:
        """Sensor image(s) (…, y, x) of volume(s) (…, z, y, x)."""
        ...

    def adjoint(self, image: Any) -> Any:
        """Volume(s) (…, z, y, x) from sensor image(s) (…, y, x): the adjoint of :meth:`forward`."""
        ...
