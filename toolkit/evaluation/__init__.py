"""Evaluation, benchmark and fitting tools: how well the measuring library does, and its fits.

Everything here needs ground truth (``dbh synth`` folders) or measures the library from outside:
``dbh eval`` (:mod:`.synth_eval`) and ``dbh bench`` (:mod:`.speed_bench`), ground-truth
perception (:mod:`.ground_truth`), simulated user taps (:mod:`.taps`), the sample records
(:mod:`.synth_samples`), the depth network's scores (:mod:`.depth_eval`), the rope benchmarks
(:mod:`.rope_bench`, :mod:`.real_rope_bench`), the real photos' outlines (:mod:`.real_trunk_bench`,
:mod:`.real_width_bench`), the error model (:mod:`.error_model`) and the
weight fitters (:mod:`.fit_rope_stem`, :mod:`.fit_rope_finder`).

Imported by ``monodbh.cli`` and by these tools themselves; never by the measuring library
(``monodbh.toolkit`` outside this package, ``monodbh.calib``, ``monodbh.models.runtime``). It
may import the library, the training code and the scene generator. Submodules are imported
explicitly (this package imports nothing at import time).
"""
__all__: list[str] = []
