"""A stage's fingerprint covers the library code it runs: its module and every project module
it imports, transitively. Editing a library module reruns exactly the stages that import it."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

import pipeline.fingerprint as fingerprint
import pipeline.runner as runner
from pipeline.cli import main
from pipeline.config import load_config
from pipeline.registry import load_stage, load_stages
from pipeline.runner import UP_TO_DATE, Runner, stage_code


def test_real_stages_cover_the_library_modules_they_use():
    _, train = stage_code(load_stage("train"))
    _, track = stage_code(load_stage("track"))
    _, calibrate = stage_code(load_stage("calibrate"))
    assert "gst/train/losses.py" in train and "stages/train.py" in train
    assert "gst/train/losses.py" not in track  # tracking never imports the training losses
    assert "gst/video.py" in calibrate and "gst/train/losses.py" not in calibrate
    assert not any(f.startswith("pipeline/") for f in train)  # orchestration is not stage code


LIB = {
    "fakelib/__init__.py": "",
    "fakelib/alpha.py": "def value():\n    return 1\n",
    "fakelib/beta.py": "from fakelib import gamma\n\ndef value():\n    return gamma.VALUE\n",
    "fakelib/gamma.py": "VALUE = 2\n",
    "fakestages/__init__.py": "",
}
STAGE_SRC = """
from pipeline.stage import Stage

def _run(ctx):
    {imports}
    ctx.out("{name}/value.txt").write_text(str(value()))

STAGE = Stage(name="{name}", run=_run, outputs=lambda ctx: ["{name}"])
"""


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A tiny project: stage `one` imports fakelib.alpha (inside its function), stage `two`
    imports fakelib.beta, which imports fakelib.gamma."""
    root = tmp_path / "project"
    for rel, text in LIB.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    for name, imports in (("one", "from fakelib.alpha import value"),
                          ("two", "from fakelib.beta import value")):  # fmt: skip
        (root / f"fakestages/{name}.py").write_text(STAGE_SRC.format(name=name, imports=imports))
    cfg = root / "pipeline.yaml"
    cfg.write_text(
        textwrap.dedent("""
        workspace: ws
        scenes: {demo: {synthetic: {preset: demo}}}
        stages:
          one: {module: "fakestages.one"}
          two: {module: "fakestages.two"}
        """)
    )
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setattr(runner, "PROJECT_ROOT", root)
    monkeypatch.setattr(fingerprint, "CODE_PACKAGES", ("fakelib", "fakestages"))
    yield root, cfg
    for mod in [m for m in sys.modules if m.split(".")[0] in ("fakelib", "fakestages")]:
        del sys.modules[mod]


def _states(cfg: Path) -> dict[str, tuple[str, str]]:
    c = load_config(cfg)
    return {s.stage: (s.state, s.reason) for s in Runner(c, "demo", load_stages(c)).status()}


def test_a_library_edit_reruns_exactly_the_stages_that_import_it(project):
    root, cfg = project
    assert main(["run", "all", "--config", str(cfg), "--quiet"]) == 0
    assert {s: st for s, (st, _) in _states(cfg).items()} == {"one": UP_TO_DATE, "two": UP_TO_DATE}

    (root / "fakelib/gamma.py").write_text("VALUE = 3\n")  # two imports it through beta
    states = _states(cfg)
    assert states["one"][0] == UP_TO_DATE
    assert states["two"][0] == "stale" and "fakelib/gamma.py" in states["two"][1]

    assert main(["run", "all", "--config", str(cfg), "--quiet"]) == 0
    (root / "fakelib/alpha.py").write_text("def value():\n    return 10\n")
    states = _states(cfg)
    assert states["one"][0] == "stale" and "fakelib/alpha.py" in states["one"][1]
    assert states["two"][0] == UP_TO_DATE

    (root / "fakelib/unused.py").write_text("X = 1\n")  # imported by no stage
    assert main(["run", "all", "--config", str(cfg), "--quiet"]) == 0
    assert all(st == UP_TO_DATE for st, _ in _states(cfg).values())


def test_imports_inside_functions_and_relative_imports_are_followed(tmp_path):
    pkg = tmp_path / "fakelib"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from . import b\n    return b\n")
    (pkg / "b.py").write_text("from .c import X\n")
    (pkg / "c.py").write_text("X = 1\n")
    (pkg / "d.py").write_text("Y = 2\n")
    import pipeline.fingerprint as fp

    old = fp.CODE_PACKAGES
    fp.CODE_PACKAGES = ("fakelib",)
    try:
        files = fp.code_digests("fakelib.a", pkg / "a.py", tmp_path)
    finally:
        fp.CODE_PACKAGES = old
    assert sorted(files) == ["fakelib/__init__.py", "fakelib/a.py", "fakelib/b.py", "fakelib/c.py"]


def test_data_files_beside_the_modules_count_as_code(tmp_path):
    """A module's own data file (gst/body/markers_blazepose.json for the fuse stage) is part of
    what its stages compute: its digest is in the code files, and an edit changes it."""
    pkg = tmp_path / "fakelib"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(
        "import json, pathlib\nT = pathlib.Path(__file__).with_name('t.json')\n"
    )
    (pkg / "t.json").write_text('{"offset": 1}')
    (pkg / "notes.md").write_text("not data")
    (pkg / "sub" / "u.json").write_text("{}")  # another folder, no module of it imported
    import pipeline.fingerprint as fp

    old = fp.CODE_PACKAGES
    fp.CODE_PACKAGES = ("fakelib",)
    try:
        before = fp.code_digests("fakelib.a", pkg / "a.py", tmp_path)
        (pkg / "t.json").write_text('{"offset": 2}')
        after = fp.code_digests("fakelib.a", pkg / "a.py", tmp_path)
    finally:
        fp.CODE_PACKAGES = old
    assert sorted(before) == ["fakelib/a.py", "fakelib/t.json"]  # not notes.md, not sub/
    assert before["fakelib/t.json"] != after["fakelib/t.json"]
    assert {k: v for k, v in before.items() if k != "fakelib/t.json"} == {
        k: v for k, v in after.items() if k != "fakelib/t.json"
    }


def test_a_user_stage_package_counts_as_its_code_wherever_it_lives(tmp_path, monkeypatch):
    """`module: mylab.stages.gait`: the stage's own package is not one of CODE_PACKAGES and lies
    outside the project, yet editing the helper it imports makes it stale; a module of that
    package which it does not import does not."""
    lab = tmp_path / "elsewhere"
    files = {
        "mylab/__init__.py": "",
        "mylab/helpers.py": "def value():\n    return 1\n",
        "mylab/unused.py": "X = 1\n",
        "mylab/stages/__init__.py": "",
        "mylab/stages/gait.py": STAGE_SRC.format(
            name="gait", imports="from mylab.helpers import value"
        ),
    }
    for rel, text in files.items():
        (lab / rel).parent.mkdir(parents=True, exist_ok=True)
        (lab / rel).write_text(text)
    cfg = tmp_path / "project" / "pipeline.yaml"
    cfg.parent.mkdir()
    cfg.write_text(
        "workspace: ws\nscenes: {demo: {synthetic: {preset: demo}}}\n"
        'stages:\n  gait: {module: "mylab.stages.gait"}\n'
    )
    monkeypatch.syspath_prepend(str(lab))
    try:
        _, code = stage_code(load_stage("gait", "mylab.stages.gait"))
        # keyed by the path in the folder holding the package: a project copied elsewhere
        # stayed 'stale, code changed' by every file of it when they were absolute paths
        assert {"mylab/helpers.py", "mylab/stages/gait.py", "mylab/__init__.py"} <= set(code)
        assert main(["run", "all", "--config", str(cfg), "--quiet"]) == 0
        assert _states(cfg)["gait"][0] == UP_TO_DATE
        (lab / "mylab/unused.py").write_text("X = 2\n")
        assert _states(cfg)["gait"][0] == UP_TO_DATE
        (lab / "mylab/helpers.py").write_text("def value():\n    return 2\n")
        state, reason = _states(cfg)["gait"]
        assert state == "stale" and "helpers.py" in reason
    finally:
        for mod in [m for m in sys.modules if m.split(".")[0] == "mylab"]:
            del sys.modules[mod]


def test_a_single_file_user_stage_counts_the_modules_beside_it_that_it_imports(
    tmp_path, monkeypatch
):
    """`module: solo` (solo.py) importing `solohelper` beside it: editing the helper left the
    stage up to date and its old output was served. A module beside it that it does not import
    still does not count."""
    lab = tmp_path / "elsewhere"
    lab.mkdir()
    (lab / "solohelper.py").write_text("K = 1\n")
    (lab / "unrelated.py").write_text("X = 1\n")
    (lab / "solo.py").write_text(STAGE_SRC.format(name="solo", imports="import solohelper"))
    monkeypatch.syspath_prepend(str(lab))
    try:
        _, code = stage_code(load_stage("solo", "solo"))
        assert {"solo.py", "solohelper.py"} <= set(code) and "unrelated.py" not in code
    finally:
        for mod in ("solo", "solohelper"):
            sys.modules.pop(mod, None)


def test_a_stage_file_beside_pipeline_yaml_does_not_count_the_runner(tmp_path):
    """A single-file stage in the project's root imports pipeline.stage: the runner's source
    (and, through it, calibration/) became its code, so editing pipeline/ made it stale."""
    from pipeline.fingerprint import code_roots

    (tmp_path / "pipeline").mkdir()
    (tmp_path / "pipeline" / "__init__.py").write_text("")
    (tmp_path / "helper.py").write_text("K = 1\n")
    (tmp_path / "locked").mkdir(mode=0o000)  # an unreadable folder holds no module
    try:
        roots = code_roots("gait", tmp_path / "gait.py", tmp_path)
    finally:
        (tmp_path / "locked").chmod(0o755)
    assert "pipeline" not in roots and roots["helper"] == tmp_path.resolve()
