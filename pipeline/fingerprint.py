"""Content hashes of files and folders, cached by (path, size, mtime) so a bare `touch`
(or an unchanged file) costs a stat, and a stage fingerprint built from them."""

from __future__ import annotations

import ast
import hashlib
import json
import os
from functools import lru_cache
from pathlib import Path
from typing import Any

from gst.atomic import atomic_write_text

_CHUNK = 1 << 20


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class HashCache:
    """sha256 of files, remembered by (size, mtime_ns). A touched file whose content did not
    change is re-hashed once and gives the same digest, so it never triggers a rerun."""

    def __init__(self, path: Path | None):
        self.path = path
        self._entries: dict[str, list] = {}
        self._dirty = False
        if path is not None and path.is_file():
            try:
                entries = json.loads(path.read_text())
            except (ValueError, OSError):  # not JSON, or not text (UnicodeDecodeError)
                entries = {}  # a corrupt cache only costs re-hashing
            # entries of another shape (a list, an entry that is no list) are dropped: they
            # crashed every `status` and `run` with a TypeError
            if isinstance(entries, dict):
                self._entries = {
                    k: v for k, v in entries.items() if isinstance(v, list) and len(v) == 5
                }

    def file_digest(self, path: Path) -> str:
        st = path.stat()
        key = str(path.resolve())
        # size and modification time alone missed a same-size file copied in with its mtime
        # (cp -p, rsync -a, tar x): the inode and the change time (which no tool sets) see it
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns]
        hit = self._entries.get(key)
        if hit and hit[:-1] == stamp:
            return hit[-1]
        digest = _sha256_file(path)
        self._entries[key] = [*stamp, digest]
        self._dirty = True
        return digest

    def digest(self, path: Path) -> str | None:
        """Digest of a file, or of a folder (relative names and file digests), None if absent."""
        path = Path(path)
        if path.is_file():
            return self.file_digest(path)
        if path.is_dir():
            h = hashlib.sha256()
            # into linked folders too (a `masks` folder of links to each camera's: their files
            # are read through the links, and an edit there left the stage 'up to date'); each
            # real folder once, so a link to a folder above ends the walk
            seen: set[str] = set()
            for root, dirs, files in os.walk(path, followlinks=True):
                real = os.path.realpath(root)
                if real in seen:
                    dirs.clear()
                    continue
                seen.add(real)
                dirs.sort()
                for name in sorted(files):
                    f = Path(root) / name
                    h.update(f.relative_to(path).as_posix().encode())
                    h.update(self.file_digest(f).encode())
            return "dir:" + h.hexdigest()
        return None

    def save(self, create: bool = True) -> None:
        """Write the cache if it changed; `create=False`: only into a folder that exists."""
        if self.path is not None and self._dirty:
            if not create and not self.path.parent.is_dir():
                return
            self.path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.path, json.dumps(self._entries))
            self._dirty = False


def stage_fingerprint(code: str, params: dict[str, Any], inputs: dict[str, str | None]) -> str:
    """One hash over the code version, the params and the input digests."""
    blob = json.dumps(
        {"code": code, "params": params, "inputs": inputs}, sort_keys=True, default=str
    )
    return hashlib.sha256(blob.encode()).hexdigest()


# -- the code a stage runs --------------------------------------------------------------------

# Packages whose source counts as a stage's code. `pipeline/` is the orchestration around every
# stage, not what a stage computes, so editing it reruns nothing.
CODE_PACKAGES = ("calibration", "gst", "synth", "stages")
ORCHESTRATION = "pipeline"


def _module_file(roots: dict[str, Path], name: str) -> Path | None:
    """The source file of a project module `name` (a module or a package's __init__), if its
    top-level package is one of `roots` (package name -> the folder that holds it)."""
    parts = name.split(".")
    root = roots.get(parts[0])
    if root is None:
        return None
    base = root.joinpath(*parts)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def code_roots(module: str, path: Path, root: Path) -> dict[str, Path]:
    """Where the packages whose source counts as code live: `CODE_PACKAGES` under `root`, and
    the top-level package of the stage module itself wherever it lives (a user's stage,
    `module: mylab.stages.gait`, runs its own helpers in `mylab/`: editing them must make the
    stage stale too). A top-level single-file module (`module: gait`, gait.py) runs the
    modules and packages beside it that it imports (`import gaithelpers`): its folder's, unless
    that is an installed packages folder (site-packages: libraries there are no project code)."""
    roots = {pkg: root for pkg in CODE_PACKAGES}
    parts = module.split(".")
    if len(parts) > 1 and parts[0] not in roots:
        depth = len(parts) - 1 + (path.name == "__init__.py")  # folders from the file up
        roots[parts[0]] = path.resolve().parents[depth]
    elif len(parts) == 1 and parts[0] not in roots:
        folder = path.resolve().parent
        if not {"site-packages", "dist-packages"} & set(folder.parts):
            roots.update({name: folder for name in _modules_in(folder) if name not in roots})
    return roots


def _modules_in(folder: Path) -> list[str]:
    """The modules and packages in `folder`, but `ORCHESTRATION` (a stage file beside
    pipeline.yaml imports pipeline.stage, and editing the runner reruns no stage)."""
    names = [f.stem for f in folder.glob("*.py")]
    for d in folder.iterdir():
        try:
            if (d / "__init__.py").is_file():
                names.append(d.name)
        except OSError:  # an unreadable folder holds no module of the stage's
            continue
    return [n for n in names if n != ORCHESTRATION]


def imported_names(path: Path, name: str) -> set[str]:
    """The names every import statement in `path` (module `name`) names, anywhere in the file
    (function-level and TYPE_CHECKING imports included), relative imports resolved: `import
    a.b` gives a.b, `from a import b` gives a and a.b (b may be a submodule)."""
    is_package = path.name == "__init__.py"
    package = name.split(".") if is_package else name.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            found.add(base)
            found |= {f"{base}.{a.name}" for a in node.names}
    return found


def _imports_of(path: Path, name: str) -> set[str]:
    """Every module name an import statement in `path` may load (function-level imports
    included: they run when the stage runs), parents and `from X import y` submodules too."""
    st = path.stat()
    return set(_imports_of_version(path, name, st.st_mtime_ns, st.st_size))


@lru_cache(maxsize=4096)
def _imports_of_version(path: Path, name: str, mtime_ns: int, size: int) -> frozenset[str]:
    # One parse per file version and process: every stage's closure shares most modules, and
    # the file's stat in the key makes an edit between two calls parse again.
    found = imported_names(path, name)
    # Importing a.b.c runs a/__init__.py and a/b/__init__.py first.
    return frozenset(".".join(m.split(".")[:k]) for m in found for k in range(1, m.count(".") + 2))


def code_closure(
    module: str, path: Path, root: Path, roots: dict[str, Path] | None = None
) -> dict[str, Path]:
    """The project modules that module `module` (source file `path`) imports, transitively,
    itself included, by name. `root` holds the project packages (`code_roots`)."""
    roots = code_roots(module, path, root) if roots is None else roots
    seen: dict[str, Path] = {module: path}
    todo = sorted(_imports_of(path, module))
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        file = _module_file(roots, name)
        if file is None:
            continue
        seen[name] = file
        todo += sorted(_imports_of(file, name) - seen.keys())
    return seen


# Data that modules read from their own folder (gst/body/markers_blazepose.json, the lift's
# noise tables) are part of what a stage computes: editing one must make its stages stale.
DATA_SUFFIXES = (".json", ".yaml", ".yml", ".csv", ".npz", ".npy")


def _data_beside(sources: list[Path]) -> list[Path]:
    """The data files in the folders of `sources` (not in subfolders)."""
    folders = sorted({f.parent for f in sources})
    return [
        f
        for d in folders
        for f in sorted(d.iterdir())
        if f.is_file() and f.suffix.lower() in DATA_SUFFIXES
    ]


def code_digests(module: str, path: Path, root: Path) -> dict[str, str]:
    """sha256 (16 hex digits) of every source file in the closure and of the data files beside
    them (`DATA_SUFFIXES`), keyed by the path relative to `root`, or outside it relative to the
    folder that holds its package (`mylab/stages.py`: a project copied elsewhere is still up to
    date; absolute paths made every file of a user's package 'changed')."""
    roots = code_roots(module, path, root)  # listed once: it reads the stage's folder
    folders = [root.resolve(), *sorted({f.resolve() for f in roots.values()})]

    def key(file: Path) -> str:
        for folder in folders:
            try:
                return file.resolve().relative_to(folder).as_posix()
            except ValueError:
                continue
        return file.resolve().as_posix()

    sources = sorted(code_closure(module, path, root, roots).values())
    return {
        key(file): hashlib.sha256(file.read_bytes()).hexdigest()[:16]
        for file in sorted({*sources, *_data_beside(sources)})
    }
