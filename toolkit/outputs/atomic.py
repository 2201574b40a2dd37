"""Atomic file writing: the one writer every output of monodbh goes through.

A file is written under a temporary name in its own folder and renamed over the target with
``os.replace`` (atomic on POSIX and Windows within one file system), so a reader or a crash never
sees a half-written file: the target is either the old file, untouched, or the new one, whole. On
any failure (exceptions and ``KeyboardInterrupt`` alike) the temporary file is removed and the
error re-raised.

The temporary file comes from :func:`tempfile.mkstemp` (name ``.<target name>.<random>.tmp``,
the target's name cut so the temporary name fits the file system); before the rename it gets the
mode of the file it replaces, or for a new file ``0o666`` less the process's umask, as ``open``
would give. Nothing is ``fsync``-ed. The target's folder is created when missing.

Imported by the library's writers (``toolkit.batch``, :mod:`.overlay`, :mod:`.cloud_io`) and by
the evaluation tools; imports only the standard library.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Iterator

__all__ = ["atomic_path", "atomic_open", "atomic_write_text", "atomic_write_bytes"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[str]:
    """A temporary path beside ``path`` that replaces ``path`` when the block succeeds.

    For writers that need a file name (``PIL.Image.save``, ``plyfile``); the temporary file
    exists (empty) when the block starts and may be opened, truncated or overwritten by name.

    Parameters
    ----------
    path : str or os.PathLike
        The target file; its folder is created.

    Yields
    ------
    str
        The temporary file's path, in the target's folder.

    Examples
    --------
    >>> with atomic_path(folder / "cloud.ply") as tmp:      # doctest: +SKIP
    ...     ply.write(tmp)
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=_tmp_prefix(p), suffix=".tmp", dir=p.parent)
    os.close(fd)
    try:
        yield tmp
        _set_mode(tmp, p)
        os.replace(tmp, p)
    except BaseException:
        _remove(tmp)
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w") -> Iterator[IO]:
    """An open temporary file that replaces ``path`` once the block succeeds and it is closed.

    Parameters
    ----------
    path : str or os.PathLike
        The target file; its folder is created.
    mode : {"w", "wb"}
        Text (UTF-8, newlines written as given) or binary.

    Yields
    ------
    file object

    Examples
    --------
    >>> with atomic_open(folder / "depth.npy", "wb") as f:    # doctest: +SKIP
    ...     np.save(f, depth)
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', not {mode!r}")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=_tmp_prefix(p), suffix=".tmp", dir=p.parent)
    try:
        with (os.fdopen(fd, "w", encoding="utf-8", newline="") if mode == "w" else os.fdopen(fd, "wb")) as f:
            yield f
        _set_mode(tmp, p)
        os.replace(tmp, p)
    except BaseException:
        _remove(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8, newlines as given) to ``path`` atomically; returns the path."""
    with atomic_open(path, "w") as f:
        f.write(text)
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_open(path, "wb") as f:
        f.write(data)
    return Path(path)


def _tmp_prefix(p: Path) -> str:
    """``.<name>.`` with the name cut to keep the temporary name (prefix, 8 random characters,
    ``.tmp``) within 255 bytes."""
    name = p.name
    while len(os.fsencode(name)) > 200:
        name = name[:-1]
    return f".{name}."


def _umask() -> int:
    """The process's umask (read from ``/proc`` on Linux; elsewhere set and restored)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _set_mode(tmp: str, target: Path) -> None:
    """The mode ``target`` has (when it exists) or a new file would get (``0o666 & ~umask``)."""
    try:
        mode = os.stat(target).st_mode & 0o7777
    except OSError:
        mode = 0o666 & ~_umask()
    os.chmod(tmp, mode)


def _remove(tmp: str) -> None:
    try:
        os.unlink(tmp)
    except OSError:
        pass
