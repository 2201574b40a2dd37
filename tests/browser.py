"""Headless Chromium for the report tests: find it, dump a page's DOM, take a screenshot.

Debian's ``chromium`` package (``.ci/run`` installs it when missing); ``MONODBH_CHROMIUM`` names
another binary. Tests skip, saying why, only where none is installed.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Optional

import numpy as np

__all__ = ["chromium", "require_chromium", "dump_dom", "body_data", "screenshot"]

_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
          "--disable-background-networking", "--disable-component-update", "--disable-sync",
          "--disable-extensions", "--hide-scrollbars", "--mute-audio")


def chromium() -> Optional[str]:
    """The browser binary, or None."""
    env = os.environ.get("MONODBH_CHROMIUM")
    if env:
        return env
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        p = shutil.which(name)
        if p:
            return p
    return None


def require_chromium() -> str:
    import pytest

    exe = chromium()
    if exe is None:
        pytest.skip("no Chromium here to open the report (Debian package chromium; .ci/run installs it "
                    "with apt-get where it can; MONODBH_CHROMIUM names another browser)")
    return exe


def _run(args: list[str], profile: Path) -> subprocess.CompletedProcess:
    exe = require_chromium()
    profile.mkdir(parents=True, exist_ok=True)
    return subprocess.run([exe, *_FLAGS, f"--user-data-dir={profile}", *args], capture_output=True,
                          text=True, timeout=120)


def dump_dom(page: Path, profile: Path, fragment: str = "") -> str:
    """The page's DOM after its load event (``--dump-dom``)."""
    out = _run(["--dump-dom", Path(page).resolve().as_uri() + fragment], profile)
    assert "<body" in out.stdout, out.stderr[-2000:]
    return out.stdout


def body_data(dom: str) -> dict:
    """The ``data-*`` attributes of ``<body>`` (names as in HTML: ``thumbs-loaded``)."""
    tag = re.search(r"<body([^>]*)>", dom).group(1)
    return dict(re.findall(r'data-([a-z-]+)="([^"]*)"', tag))


def screenshot(page: Path, profile: Path, size=(1280, 2000)) -> np.ndarray:
    """(H, W, 3) uint8 screenshot of the page's top ``size`` pixels."""
    from PIL import Image

    png = profile / "shot.png"
    out = _run([f"--window-size={size[0]},{size[1]}", f"--screenshot={png}", Path(page).resolve().as_uri()],
               profile)
    assert png.exists(), out.stderr[-2000:]
    return np.asarray(Image.open(png).convert("RGB"))
