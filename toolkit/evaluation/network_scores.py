"""Each shipped network's own figures on synthetic folders, side by side: is a look held out?

For every folder given (typically the benchmark ``data/bench`` and the same scenes in the
held-out look, ``dbh synth data/bench_heldout --look heldout`` with the same seed), the shipped
int8 models are scored by their training's evaluation hooks
(:func:`monodbh.models.training.common.evaluate_kind`), on the same samples for every folder:

- segmenter: ``roped_iou`` (the roped tree's mask IoU) and ``roped_detected``;
- depth: ``absrel`` and ``ms_absrel`` (median-scaled) at the network's input;
- tree: ``g_acc`` and ``g_within10`` (thickness within 10 %);
- stem_base: ``recall`` (bases found within 5 % of the strip) and ``precision``;
- stem_base_net: the same for the two stem-base networks as ``StemBaseFinder`` asks them (the
  second where the first's base is under the pipeline's threshold);
- stem_edge: ``score`` (patches whose width is within the training's tolerance) and
  ``width_median_pct``, on the exact patches of the folder's last 60 scenes;
- rope_finder: ``recall`` and ``tile_auc`` on a bank cut from the folder
  (:func:`monodbh.models.training.rope_finder_bank.cut_folder`, to a temporary file);
- trunk_head (the segmenter's): ``iou`` of the trunk pixels, on folders rendered with the
  ``stem`` label (:func:`monodbh.models.training.trunk_head.score_shipped`; ``-`` on others, e.g.
  ``data/trunk_val data/trunk_val_h``);
- trunk_net: ``iou`` of the trunk pixels of the trunk network in one pass, at the photo's
  resolution (:func:`monodbh.models.training.trunk_net.score_folder`; ``-`` likewise).

The last column gives each figure of the last folder over the first's (errors: how many times
larger; scores: how many times smaller), the ratio issue 26 bounds by 1.25.

Usage::

    python -m monodbh.toolkit.evaluation.network_scores data/bench data/bench_heldout [--n 120] [--json F]
        [--kinds stem_base,stem_edge] [--models-dir DIR]

Imported by nothing (a command); imports the training package's evaluation hooks and onnxruntime.
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Optional, Sequence

__all__ = ["FIGURES", "score_folder", "ratio", "main"]

#: (network, metric, lower is better) printed for each folder
FIGURES = (("segmenter", "roped_iou", False), ("segmenter", "roped_detected", False),
           ("depth", "absrel", True), ("depth", "ms_absrel", True),
           ("tree", "g_acc", False), ("tree", "g_within10", False),
           ("stem_base", "recall", False), ("stem_base", "precision", False),
           ("stem_base_net", "recall", False), ("stem_base_net", "precision", False),
           ("stem_edge", "score", False), ("stem_edge", "width_median_pct", True),
           ("rope_finder", "recall", False), ("rope_finder", "tile_auc", False),
           ("trunk_head", "iou", False), ("trunk_net", "iou", False))


def _look(folder: Path) -> str:
    """The ``look`` of a folder's first sample (``default`` for folders written before looks)."""
    js = sorted(folder.glob("*.json"))
    return json.loads(js[0].read_text()).get("look", "default") if js else "?"


def score_folder(folder: str | Path, n: int = 120, seed: int = 0, models_dir: Optional[Path] = None,
                 kinds: Sequence[str] = ("segmenter", "depth", "tree", "stem_base", "stem_base_net", "stem_edge",
                                         "rope_finder", "trunk_head", "trunk_net")) -> dict:
    """Each shipped network's evaluation metrics on the samples of ``folder``.

    Parameters
    ----------
    folder : a ``dbh synth`` folder (either look).
    n : samples (strips, crops, tiles) each hook evaluates; the same ones for every folder of the
        same scenes, since they are picked by ``seed`` and the sample count.
    models_dir : the ONNX models and their ``manifest.json`` (default: the shipped ones).

    Returns
    -------
    dict: ``{kind: {metric: value}}`` and ``look``.
    """
    from monodbh.models.export.cli_impl import MODELS_DIR, shipped_spec
    from monodbh.models.export.onnx_io import make_session, run_session
    from monodbh.models.modeling.registry import get_spec
    from monodbh.models.runtime.common import load_manifest
    from monodbh.models.training.common import BankSource, evaluate_kind, make_source

    folder = Path(folder)
    mdir = Path(models_dir) if models_dir else MODELS_DIR
    entries = load_manifest(mdir / "manifest.json")["models"]
    out: dict = {"look": _look(folder)}
    src = make_source(folder, allow_heldout=True)
    for kind in kinds:
        if kind == "trunk_head":
            from monodbh.models.training.trunk_head import score_shipped
            out[kind] = score_shipped(folder, n, mdir)
            continue
        if kind == "trunk_net":
            from monodbh.models.runtime.trunk_net import TrunkNet
            from monodbh.models.training.trunk_net import score_folder as score_trunk_net
            try:
                out[kind] = score_trunk_net(TrunkNet(mdir / entries[kind]["file"]), folder, None, n)
            except ValueError:                      # rendered before the stem label
                out[kind] = {}
            continue
        if kind == "stem_base_net":
            out[kind] = _base_pair_scores(mdir, entries, n, seed, src) if kind in entries else {}
            continue
        path = mdir / entries[kind]["file"]
        spec = shipped_spec(get_spec(kind), path)          # the file's own conventions
        sess = make_session(path, threads=2)
        if kind == "rope_finder":
            from monodbh.models.training.rope_finder_bank import cut_folder
            with tempfile.TemporaryDirectory() as tmp:
                bank = Path(tmp) / "bank.npz"
                cut_folder(folder, bank, seed=seed, allow_heldout=True)
                data = BankSource([str(bank)])
                out[kind] = evaluate_kind(kind, lambda f: run_session(sess, f), n, seed, spec, data)
        else:
            out[kind] = evaluate_kind(kind, lambda f: run_session(sess, f), n, seed, spec, src)
    return out


def _base_pair_scores(mdir: Path, entries: dict, n: int, seed: int, src) -> dict:
    """The stem-base hook's metrics of the first network's logits, or the second's where the
    first's base probability is under the pipeline's threshold and the second's is not."""
    from monodbh.models.export.cli_impl import shipped_spec
    from monodbh.models.export.onnx_io import make_session, run_session
    from monodbh.models.modeling.registry import get_spec
    from monodbh.models.runtime.stem_base import decode_base_logits
    from monodbh.models.training.common import evaluate_kind

    first = make_session(mdir / entries["stem_base"]["file"], threads=2)
    second = make_session(mdir / entries["stem_base_net"]["file"], threads=2)
    thr = float((entries["stem_base"].get("extra") or {}).get("p_threshold", 0.7))

    def pair(feed):
        z = run_session(first, feed)
        if decode_base_logits(z["logits"][0])[1] >= thr:
            return z
        z2 = run_session(second, feed)
        return z2 if decode_base_logits(z2["logits"][0])[1] >= thr else z
    spec = shipped_spec(get_spec("stem_base"), mdir / entries["stem_base"]["file"])
    return evaluate_kind("stem_base", pair, n, seed, spec, src)


def ratio(a: float, b: float, lower_is_better: bool) -> float:
    """How many times worse ``b`` is than ``a`` (> 1: worse; errors b / a, scores a / b).

    Examples
    --------
    >>> ratio(0.2, 0.3, True), ratio(0.8, 0.4, False)
    (1.5, 2.0)
    """
    if lower_is_better:
        return b / a if a else float("inf")
    return a / b if b else float("inf")


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--n", type=int, default=120, help="samples each network is scored on")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--models-dir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--kinds", default="segmenter,depth,tree,stem_base,stem_base_net,stem_edge,rope_finder,trunk_head,trunk_net",
                    help="comma-separated networks to score")
    a = ap.parse_args(argv)
    kinds = [k for k in a.kinds.split(",") if k]
    bad = sorted(set(kinds) - {k for k, _, _ in FIGURES})
    if bad:
        ap.error(f"unknown network(s): {', '.join(bad)}")
    for f in a.folders:
        if not f.is_dir():
            ap.error(f"{f}: not a folder")
    res = {str(f): score_folder(f, a.n, a.seed, a.models_dir, kinds) for f in a.folders}
    names = list(res)
    head = f"{'network':<14}{'metric':<16}" + "".join(f"{Path(k).name + ' (' + res[k]['look'] + ')':>28}" for k in names)
    if len(names) > 1:
        head += f"{'worse by':>10}"
    print(head)
    for kind, m, low in FIGURES:
        if kind not in kinds:
            continue
        vals = [res[k].get(kind, {}).get(m) for k in names]
        row = f"{kind:<14}{m:<16}" + "".join(f"{v:>28.3f}" if v is not None else f"{'-':>28}" for v in vals)
        if len(names) > 1 and None not in (vals[0], vals[-1]):
            row += f"{ratio(vals[0], vals[-1], low):>10.2f}"
        print(row)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
