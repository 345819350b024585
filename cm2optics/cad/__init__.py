"""Parametric CadQuery parts of a CM² device, their assembly and export.

Each part module exposes ``build_<part>(design) -> cadquery.Workplane`` holding one solid in
the part's documented local frame; :mod:`cm2optics.cad.assembly` places them in the device
frame. CadQuery is imported only inside this subpackage.
"""
