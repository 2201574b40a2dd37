"""Write the shipped segmenter's tree masks beside the samples of ``dbh synth`` folders.

The depth network sees the union of the segmenter's tree instances at run time, not the
ground truth's; training it on these masks (``DepthTrainConfig.segmask_prob``) teaches it the
masks it will get. Each sample ``NNNNNN.jpg`` gets ``NNNNNN.segmask.png`` (uint8 0/255, the
photo's resolution and frame: segmented as read, with its lens distortion, so that the
training's undistortion remaps it with the other arrays)::

    python -m monodbh.models.training.segmasks data/base_train data/tex_train [--force]

Training-only (imports the runtime segmenter, onnxruntime).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

__all__ = ["segmask_path", "read_segmask", "write_segmasks", "main"]


def segmask_path(folder: str | Path, index: int) -> Path:
    """``folder/NNNNNN.segmask.png``."""
    return Path(folder) / f"{index:06d}.segmask.png"


def read_segmask(folder: str | Path, index: int) -> np.ndarray | None:
    """(H, W) bool segmenter tree mask of a sample, or None when it was not written."""
    import cv2

    p = segmask_path(folder, index)
    if not p.is_file():
        return None
    m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    return None if m is None else m > 127


def write_segmasks(folder: str | Path, *, force: bool = False, threads: int = 2,
                   progress: bool = True) -> int:
    """Segment every sample of ``folder`` with the shipped segmenter; returns how many were written."""
    import cv2

    from monodbh.models.runtime import Segmenter
    from monodbh.models.synthetic.io import list_samples

    seg = Segmenter(threads=threads)        # the manifest's shipped model
    idx = list_samples(folder)
    n = 0
    for k, i in enumerate(idx):
        out = segmask_path(folder, i)
        if out.exists() and not force:
            continue
        bgr = cv2.imread(str(Path(folder) / f"{i:06d}.jpg"), cv2.IMREAD_COLOR)
        if bgr is None:
            print(f"{folder}/{i:06d}.jpg: unreadable, skipped", file=sys.stderr)
            continue
        m = seg.predict(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).instance > 0
        tmp = out.with_name(out.name + ".tmp.png")
        cv2.imwrite(str(tmp), (m * 255).astype(np.uint8))
        tmp.replace(out)
        n += 1
        if progress and (k + 1) % 50 == 0:
            print(f"{folder}: {k + 1}/{len(idx)}", file=sys.stderr, flush=True)
    return n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="+")
    ap.add_argument("--force", action="store_true", help="rewrite existing masks")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    for f in a.folder:
        n = write_segmasks(f, force=a.force, threads=a.threads)
        print(f"{f}: {n} masks written")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
