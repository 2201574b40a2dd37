"""Training (torch): shared harness in ``common`` and one module per kind.

``common``: run folders, resumable loop, data sources, augmentation, export hooks.
``segmenter``: :func:`~monodbh.models.training.segmenter.train_segmenter`.
``depth`` / ``tree``: the CDEN depth and tree-silhouette networks; ``stem_base``: the stem-base
finder; ``rope_verifier``: the rope-band verifier; ``rope_finder`` (+ ``rope_finder_bank``, its
example tiles): the mask-free rope finder.
Submodules are imported explicitly (this package imports nothing heavy at import time).
"""
__all__: list[str] = []
