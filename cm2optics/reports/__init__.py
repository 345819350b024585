"""Figures, tables and reports of every stage, and the demo: no physics, only presentation.

:mod:`.document` (the HTML/Markdown :class:`~cm2optics.reports.document.Report`), one module per
stage (:mod:`.spectra`, :mod:`.illumination`, :mod:`.emission`, :mod:`.lsv`, :mod:`.recon`,
:mod:`.design`) and :mod:`.demo`. Stages never import this package.
"""
