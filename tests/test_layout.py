"""The house rules, checked by parsing every import (docs/layout.md): libraries never import
orchestration, no import cycles between modules or gst packages, stages stay thin, and the
synthetic scene format has one reader and writer."""

from __future__ import annotations

import ast
from pathlib import Path

from pipeline.fingerprint import imported_names

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "stages", "calibration", "gst", "synth")
LIBRARIES = ("calibration", "gst", "synth")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*.py"):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """Project modules imported anywhere in the file (function-level and TYPE_CHECKING
    imports included: they tie the files together all the same)."""
    return {m for m in imported_names(path, name) if m in MODULES and m != name}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_libraries_never_import_orchestration():
    offenders = [
        f"{m} imports {t}"
        for m, targets in GRAPH.items()
        if m.split(".")[0] in LIBRARIES
        for t in targets
        if t.split(".")[0] in ("pipeline", "stages")
    ]
    assert offenders == []


def test_no_import_cycles_between_modules():
    assert _cycles(GRAPH) == []


def test_no_import_cycles_between_gst_packages():
    def pkg(m: str) -> str | None:
        parts = m.split(".")
        return ".".join(parts[:2]) if parts[0] == "gst" and len(parts) > 2 else None

    packages: dict[str, set[str]] = {}
    for m, targets in GRAPH.items():
        a = pkg(m)
        if a is None:
            continue
        packages.setdefault(a, set())
        packages[a] |= {b for t in targets if (b := pkg(t)) is not None and b != a}
    assert _cycles(packages) == []


def test_the_cycle_check_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_every_stage_is_a_thin_adapter():
    """Under 80 lines, and the work happens in a library: a stage module defines no classes
    but its params and at most a few small helpers."""
    for path in sorted((REPO / "stages").glob("*.py")):
        if path.name == "__init__.py":
            continue
        lines = path.read_text().count("\n")
        assert lines < 80, f"{path.name} has {lines} lines; move the recipe into a library"
        tree = ast.parse(path.read_text())
        assert any(
            isinstance(n, ast.Assign) and any(getattr(t, "id", "") == "STAGE" for t in n.targets)
            for n in tree.body
        ), f"{path.name} defines no STAGE"


def _string_constants(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    docstrings = {
        id(n.body[0].value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Module | ast.ClassDef | ast.FunctionDef)
        and n.body
        and isinstance(n.body[0], ast.Expr)
        and isinstance(n.body[0].value, ast.Constant)
    }
    return {
        n.value
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docstrings
    }


def test_the_synthetic_scene_format_has_one_reader():
    """Only synth/truth.py names the truth tables; evaluation, training and tracking import
    their readers from it."""
    tables = ("people.parquet", "views.parquet")
    owners = [
        name
        for name, path in MODULES.items()
        if any(s.endswith(tables) and " " not in s for s in _string_constants(path))
    ]
    assert owners == ["synth.truth"], owners
    for consumer in ("gst.train.scene_truth", "gst.train.synthetic_crops", "gst.track.evaluate"):
        assert "synth.truth" in GRAPH[consumer], consumer
    readers = {"gst.eval", "gst.train", "gst.track"}
    for m, targets in GRAPH.items():
        if ".".join(m.split(".")[:2]) in readers:
            truth_sources = {
                t for t in targets if t.endswith("truth") and t != "gst.train.scene_truth"
            }
            assert truth_sources <= {"synth.truth"}, (m, truth_sources)
