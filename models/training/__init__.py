"""Training (torch): shared harness in ``common`` and one module per kind.

``common``: run folders, resumable loop, data sources, augmentation, export hooks.
``segmenter``: :func:`~monodbh.models.training.segmenter.train_segmenter`.
``depth`` / ``trees``: CDEN and tree-silhouette networks; ``basenet``: the stem-base finder;
``ropenet``: the rope-band verifier; ``ropeseg`` (+ ``ropeseg_bank``, its example tiles): the
mask-free rope finder.
Submodules are imported explicitly (this package imports nothing heavy at import time).
"""
__all__: list[str] = []
