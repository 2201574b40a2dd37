"""What a measurement writes for the user: overlay pictures, point-cloud files, atomic writing.

:mod:`.overlay` (the overlay PNG of a measurement), :mod:`.cloud_io` (PLY/LAS/LAZ point clouds),
:mod:`.results_file` (a batch's JSON lines, CSV and summary, written as the rows come),
:mod:`.stand` (the stand summary of results CSVs: DBH, basal area, per hectare, classes),
:mod:`.geo` (the stem's bearing, the tree's WGS 84 position, GeoJSON), :mod:`.report` (the
self-contained HTML report), :mod:`.paths` (output paths that clash with inputs) and :mod:`.atomic`
(the one atomic file writer they and every other output use). Imported by ``monodbh.cli``,
``monodbh.toolkit.batch`` and the evaluation tools; imports ``monodbh.calib`` and
``monodbh.toolkit.result`` only (:mod:`.geo` optionally pyproj). Submodules are imported
explicitly (nothing at import time).
"""
__all__: list[str] = []
