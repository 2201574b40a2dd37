"""On-disk dataset format of ``dbh synth`` (see ``docs/ARCHITECTURE.md``).

Per sample ``NNNNNN``: ``NNNNNN.jpg`` (the photo), ``NNNNNN.npz`` (ground-truth arrays) and
``NNNNNN.json`` (record). Files are written atomically (temporary name, then rename), so an
interrupted run never leaves a half-written sample, and a re-run skips finished samples.
"""
from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np

__all__ = ["write_sample", "read_sample", "list_samples", "GT_KEYS", "OPTIONAL_GT_KEYS", "sample_done"]

GT_KEYS = ("depth", "semantic", "instance", "rope", "z1", "z2", "stem")
#: arrays that data sets rendered before they existed do not have
OPTIONAL_GT_KEYS = ("stem",)


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def _npz_bytes(arrays: dict) -> bytes:
    """Deterministic compressed npz (fixed zip timestamps, fixed order)."""
    buf = io.BytesIO()
    # level 1: about half the time of the default 6 for 8 % larger files (measured on 512x512 samples)
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for k in GT_KEYS:
            b = io.BytesIO()
            np.lib.format.write_array(b, np.ascontiguousarray(arrays[k]), allow_pickle=False)
            zi = zipfile.ZipInfo(k + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            zi.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(zi, b.getvalue(), compresslevel=1)
    return buf.getvalue()


def _json_bytes(meta: dict) -> bytes:
    """The record as JSON: one top-level key per line, one tree (list item) per line.

    Written with the C encoder (``indent`` would select json's pure-Python one: 35 ms of a
    512x512 sample's 1.1 s, for a 200-tree record); keys sorted, so the bytes are fixed.
    """
    enc = json.JSONEncoder(sort_keys=True, separators=(", ", ": "))
    lines = []
    for k in sorted(meta):
        v = meta[k]
        if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            body = "[\n  " + ",\n  ".join(enc.encode(x) for x in v) + "\n ]"
        else:
            body = enc.encode(v)
        lines.append(f" {enc.encode(k)}: {body}")
    return ("{\n" + ",\n".join(lines) + "\n}\n").encode()


def sample_done(folder: str | os.PathLike, index: int) -> bool:
    stem = Path(folder) / f"{index:06d}"
    return all((stem.with_suffix(s)).exists() for s in (".jpg", ".npz", ".json"))


def write_sample(folder: str | os.PathLike, index: int, sample: dict) -> None:
    """Write one sample (dict from :func:`generate_sample`) as ``{index:06d}.{jpg,npz,json}``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"{index:06d}"
    _atomic_write(stem.with_suffix(".npz"), _npz_bytes(sample))
    _atomic_write(stem.with_suffix(".jpg"), sample["jpeg"])
    _atomic_write(stem.with_suffix(".json"), _json_bytes(sample["meta"]))


def list_samples(folder: str | os.PathLike) -> list[int]:
    """Indices of the complete samples in ``folder``, sorted."""
    folder = Path(folder)
    return sorted(int(p.stem) for p in folder.glob("[0-9]" * 6 + ".json")
                  if p.with_suffix(".npz").exists() and p.with_suffix(".jpg").exists())


def read_sample(folder: str | os.PathLike, index: int, *, arrays: bool = True) -> dict:
    """Read a sample back: ``rgb`` (H, W, 3) uint8, the ground-truth arrays and ``meta``."""
    import cv2
    stem = Path(folder) / f"{index:06d}"
    bgr = cv2.imread(str(stem.with_suffix(".jpg")), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"{stem.with_suffix('.jpg')}: missing or unreadable")
    out = {"rgb": cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), "path": str(stem.with_suffix(".jpg"))}
    if arrays:
        with np.load(stem.with_suffix(".npz")) as z:
            for k in GT_KEYS:
                if k in z.files or k not in OPTIONAL_GT_KEYS:
                    out[k] = z[k]
    out["meta"] = json.loads(stem.with_suffix(".json").read_text())
    return out
