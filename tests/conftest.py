"""Shared pytest fixtures (keep minimal: several test modules use these)."""
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Root of the shared data sets: ``$MONODBH_SHARED_DATA``, default ``<repo>/../shared/data``."""
    root = Path(os.environ.get("MONODBH_SHARED_DATA", REPO.parent / "shared" / "data"))
    if not root.is_dir():
        pytest.skip(f"shared data not found at {root} (set MONODBH_SHARED_DATA)")
    return root


@pytest.fixture
def drop_npz_member():
    """``drop(path, name)``: rewrite an ``.npz`` without its member ``name`` (e.g. ``"stem.npy"``,
    as a data set rendered before that array existed)."""
    import zipfile

    def drop(path: Path, name: str) -> None:
        with zipfile.ZipFile(path) as z:
            kept = {n: z.read(n) for n in z.namelist() if n != name}
        with zipfile.ZipFile(path, "w") as z:
            for n, b in kept.items():
                z.writestr(n, b)
    return drop
