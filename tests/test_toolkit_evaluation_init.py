"""toolkit.evaluation: the measuring library never imports it (nor training, export or the scene
generator), at module level or inside a function."""
import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: the library's source folders and the package each maps to (pyproject's package-dir)
LIBRARY = {"toolkit": "monodbh.toolkit", "calib": "monodbh.calib"}
FORBIDDEN = ("monodbh.toolkit.evaluation", "monodbh.models.synthetic", "monodbh.models.training",
             "monodbh.models.export", "monodbh.cli")


def _library_files():
    for folder, pkg in LIBRARY.items():
        for p in sorted((REPO / folder).rglob("*.py")):
            rel = p.relative_to(REPO / folder).with_suffix("").parts
            if rel[:1] == ("evaluation",):
                continue
            yield p, ".".join((pkg,) + rel[:-1])     # the package the module lives in
    for p in sorted((REPO / "models" / "runtime").glob("*.py")):
        yield p, "monodbh.models.runtime"


def _imports(path: Path, package: str):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            yield mod
            yield from (f"{mod}.{a.name}" for a in node.names)   # ``from pkg import submodule``


def test_the_library_imports_no_evaluation_training_or_scene_generator():
    files = list(_library_files())
    assert any(p.name == "batch.py" for p, _ in files) and any(p.name == "atomic.py" for p, _ in files)
    assert any(p.name == "segmenter.py" for p, _ in files)
    bad = [f"{p.relative_to(REPO)}: {m}" for p, pkg in files for m in _imports(p, pkg)
           if any(m == f or m.startswith(f + ".") for f in FORBIDDEN)]
    assert not bad, bad


def test_the_check_sees_relative_and_lazy_imports(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("def f():\n    from .evaluation import synth_eval\n    from ..models.synthetic.io import read_sample\n")
    got = set(_imports(p, "monodbh.toolkit"))
    assert {"monodbh.toolkit.evaluation.synth_eval", "monodbh.models.synthetic.io"} <= got
