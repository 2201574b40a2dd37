"""Output paths checked before anything is written: never an input, folders that can be made,
names that fit the file system and print on any terminal.

Imported by the CLI commands and :mod:`monodbh.toolkit.batch`; imports only the standard library
and :mod:`monodbh.calib.errors`. Every check raises :class:`OutputPathError` (a
:class:`~monodbh.calib.errors.MonodbhError`) with a one-line message naming the path.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Iterable, Optional

from monodbh.calib.errors import MonodbhError

__all__ = ["OutputPathError", "InputClash", "printable", "same_file", "check_not_input", "ensure_folder",
           "check_file_target", "fit_name", "first_clash", "NAME_MAX_BYTES"]

#: longest file name (bytes) of the usual file systems (ext4, APFS, NTFS in UTF-16 units)
NAME_MAX_BYTES = 255


class OutputPathError(MonodbhError):
    """An output path cannot be used: a file is in the way, it is a folder, or it cannot be made."""


class InputClash(OutputPathError):
    """An output would be written over one of the inputs (a usage error: exit status 2)."""


def printable(text: object) -> str:
    """``text`` with the bytes of a non-UTF-8 file name written as ``\\xNN`` escapes.

    Python keeps such bytes as lone surrogates (``os.fsdecode``); they cannot be encoded to a
    terminal, a UTF-8 CSV or JSON. Other text is returned unchanged.

    Examples
    --------
    >>> printable(os.fsdecode(b"tr\\xe9e.jpg"))
    'tr\\\\xe9e.jpg'
    >>> printable("épicéa.jpg")
    'épicéa.jpg'
    """
    s = str(text)
    try:
        s.encode("utf-8")
        return s
    except UnicodeEncodeError:
        return s.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Do ``a`` and ``b`` name the same existing file (by device and inode: hard links, ``..``
    and symbolic links included)?"""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_not_input(output: str | os.PathLike, inputs: Iterable[str | os.PathLike], what: str) -> None:
    """Refuse ``output`` when it is one of ``inputs`` (a usage error, :class:`InputClash`).

    Parameters
    ----------
    output : path
        A file the command is about to write.
    inputs : iterable of paths
        The photos, the camera file, ...
    what : str
        How the user named the output (``"--csv out.csv"``, ``"the overlay a_overlay.png"``).
    """
    if not os.path.lexists(output):
        return
    for p in inputs:
        if same_file(output, p):
            raise InputClash(f"{printable(what)} is one of the inputs ({printable(p)}); "
                             f"choose another output")


def ensure_folder(folder: str | os.PathLike, option: str = "") -> Path:
    """Create ``folder`` (and its parents) or raise a one-line :class:`OutputPathError`.

    Examples
    --------
    >>> ensure_folder(tmp / "a" / "b")          # doctest: +SKIP
    """
    p = Path(folder)
    label = f"{option} {printable(p)}".strip() if option else printable(p)
    if p.is_dir():
        return p
    if p.exists() or p.is_symlink():
        raise OutputPathError(f"{label}: not a folder (a file of that name exists)")
    blocker = _file_on_the_way(p)
    if blocker is not None:
        raise OutputPathError(f"{label}: not a folder ({printable(blocker)} is a file)")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputPathError(f"{label}: cannot create the folder ({exc.strerror or exc})") from None
    return p


def check_file_target(path: str | os.PathLike, option: str = "") -> Path:
    """An output file's path checked: not a folder, its folder made (:func:`ensure_folder`)."""
    p = Path(path)
    label = f"{option} {printable(p)}".strip() if option else printable(p)
    if p.is_dir():
        raise OutputPathError(f"{label}: is a folder, not a file")
    blocker = _file_on_the_way(p)
    if blocker is not None:
        raise OutputPathError(f"{label}: not a folder on the way ({printable(blocker)} is a file)")
    ensure_folder(p.parent if str(p.parent) else ".", option)
    return p


def _file_on_the_way(p: Path) -> Optional[Path]:
    """The nearest existing ancestor of ``p`` when it is not a folder (a file in the way), else None."""
    for parent in p.parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def fit_name(stem: str, suffix: str, limit: int = NAME_MAX_BYTES - 24) -> str:
    """``stem + suffix`` cut so the name fits ``limit`` bytes (room left for the atomic writer's
    temporary name); a cut stem ends with 8 hex digits of its digest, so names stay unique.

    Examples
    --------
    >>> fit_name("IMG_0001", "_overlay.png")
    'IMG_0001_overlay.png'
    >>> len(fit_name("t" * 300, "_overlay.png").encode()) <= 231
    True
    """
    if len(os.fsencode(stem + suffix)) <= limit:
        return stem + suffix
    tag = "~" + hashlib.sha1(os.fsencode(stem)).hexdigest()[:8]
    keep = max(1, limit - len(os.fsencode(suffix + tag)))
    cut = stem
    while len(os.fsencode(cut)) > keep:        # by characters: a UTF-8 character is never split
        cut = cut[:-1]
    return cut + tag + suffix


def first_clash(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike]) -> Optional[tuple[str, str]]:
    """The first ``(output, input)`` pair naming the same existing file, or None."""
    inputs = list(inputs)
    for o in outputs:
        if os.path.lexists(o):
            for p in inputs:
                if same_file(o, p):
                    return str(o), str(p)
    return None
