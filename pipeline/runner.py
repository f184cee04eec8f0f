"""Decide which stages are stale and run them, atomically, recording fingerprints.

A stage's fingerprint is its code version (declared version + hash of its module source),
its validated params and the content digests of its inputs (upstream stages' outputs plus
the external files it declares). Outputs are written to `.pipeline/staging/<key>/` and moved
into the scene workspace only after the stage returns; the fingerprint record is deleted just
before that move and written after it, so a run killed at any point is seen as "missing" or
"stale" next time, never "up to date".
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import inspect
import json
import logging
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from gst.atomic import atomic_write_text, remove_path, replace_path
from gst.param_types import names_file
from pipeline.config import (
    PipelineConfig,
    format_error_line,
    parse_override,
    scene_key_parts,
    validate_strictly,
)
from pipeline.dag import topological_order, upstream_closure
from pipeline.errors import (
    PROJECT_ROOT,
    TRACEBACK_LOGGER,
    ConfigError,
    PipelineError,
    StageFailed,
    is_input_error,
)
from pipeline.fingerprint import HashCache, code_digests, stage_fingerprint
from pipeline.stage import Stage, StageContext

log = logging.getLogger("pipeline")

UP_TO_DATE, STALE, MISSING, SKIPPED = "up to date", "stale", "missing", "not needed"
KEPT = "kept"  # stale, but an upstream stage nobody asked to run: its existing outputs are used


@dataclass
class StageStatus:
    stage: str
    key: str
    state: str
    reason: str
    fingerprint: str | None = None

    @property
    def needs_run(self) -> bool:
        return self.state in (STALE, MISSING)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def is_report(rel: str) -> bool:
    """Outputs under `reports/` are written for people (markdown, plots, timings): downstream
    stages never read them, so they do not enter downstream fingerprints."""
    return Path(rel).parts[:1] == ("reports",)


def _relative_paths(obj, base: Path | None):
    """Every absolute path string in a JSON-like object, made relative to `base`."""
    if base is None:
        return obj
    if isinstance(obj, dict):
        return {k: _relative_paths(v, base) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_relative_paths(v, base) for v in obj]
    if isinstance(obj, str) and os.path.isabs(obj):
        return os.path.relpath(obj, base)
    return obj


def _same_numbers(obj):
    """`obj` with every float of an integer value as that integer (`1.0` as `1`), in lists and
    mappings too. For the values of untyped mappings (a synthetic scene's `overrides`, a
    calibration's `options`, extract's `association`), which keep the type the YAML gave: `fps:
    30` and `fps: 30.0` say the same and must not make every stage stale."""
    if isinstance(obj, dict):
        return {k: _same_numbers(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_same_numbers(v) for v in obj]
    if isinstance(obj, float) and obj.is_integer():
        return int(obj)
    return obj


def _shown(path: Path) -> str:
    """`path` as error messages name it: relative to the current folder where it is inside it."""
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def _absolute(value, base: Path, texts: bool = False):
    """`value` with every relative Path in it (also inside dicts, lists, tuples) made absolute
    against `base`; with `texts` (a param marked `gst.param_types.NAMES_FILE`: a built-in name
    or a file of the user's), also a relative text that names a file there (a `body_model` that
    is a path to the user's SMPL file). Any other text param (a method, a preset, a device) is
    never a path, even when a file of that name lies in the config's folder."""
    if isinstance(value, Path):
        value = value.expanduser()  # `~/...`: the user's home, as in a shell
        return value if value.is_absolute() else Path(os.path.normpath(base / value))
    if (
        texts
        and isinstance(value, str)
        and value
        and (os.path.isabs(os.path.expanduser(value)) or (base / value).is_file())
    ):
        # `~/models/x.json`: the user's home, as in a shell; else the config's folder
        return os.path.normpath(base / os.path.expanduser(value))
    if isinstance(value, dict):
        return {k: _absolute(v, base, texts) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_absolute(v, base, texts) for v in value)
    return value


def _param_files(params) -> list[Path]:
    """The files and folders a stage's params name (absolute by then, see `_absolute`): a
    Path-valued param (also in a list or a dict), or a text param naming an existing file
    (`body_model: my_smpl.pkl`). Their content is part of the stage's inputs, as a declared
    input's is."""
    from gst.body import body_model_file

    found = []
    for key in type(params).model_fields:
        value = getattr(params, key)
        if key == "body_model" and isinstance(value, str):
            # 'smpl', 'smpl:female', '~/models/...': the file it reads, wherever it lies (a
            # swapped SMPL file left fuse and train 'up to date')
            file = body_model_file(value)
            found += [file] if file is not None else []
            continue
        if isinstance(value, dict):
            value = list(value.values())
        for v in value if isinstance(value, (list, tuple)) else [value]:
            named = isinstance(v, Path) or (isinstance(v, str) and os.path.isabs(v))
            if named and Path(v).exists():
                found.append(Path(v))
    return found


FAILED_MARKER = ".failed"  # in a stage's staging folder: the error its last run stopped on


def _record_failure(staging: Path, exc: BaseException) -> None:
    """Leave the error beside the failed run's staging folder, so that `status` says the stage
    failed (and why) instead of 'a previous run was interrupted'."""
    with contextlib.suppress(OSError):  # a full disk must not hide the stage's own error
        text = " ".join(f"{type(exc).__name__}: {exc}".split())
        (staging / FAILED_MARKER).write_text(text[:300])


def _failure(staging: Path) -> str | None:
    """The error a stage's last run failed with (`_record_failure`), None if it did not fail."""
    try:
        return (staging / FAILED_MARKER).read_text().strip() or "(no message)"
    except UnicodeDecodeError:  # cut short inside a character (killed while writing it)
        return (staging / FAILED_MARKER).read_bytes().decode(errors="replace").strip()
    except OSError:
        return None


def _load_record(path: Path) -> tuple[dict | None, str | None]:
    """(a state record, None) or (None, why it cannot be read); (None, None) when there is none.
    A record cut short (a full disk), not text or not an object crashed `status` and `run` with a
    traceback (UnicodeDecodeError, AttributeError), or was said to be 'never run'."""
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return None, None
    except (OSError, ValueError) as exc:  # ValueError: not JSON, or not UTF-8 text
        return None, f"{type(exc).__name__}: {exc}"
    if not isinstance(record, dict):
        return None, f"it holds {json.dumps(record)[:40]}, not a JSON object"
    return record, None


def _lock_owner(fh) -> str:
    """The pid a scene's lock file records (`Runner._lock`), '?' when it records none."""
    fh.seek(0)
    return fh.read().strip() or "?"


_MAX_KEY_CHARS = 120  # file names may hold 255 bytes: room for the hash and `.json`


def _safe_key(key: str) -> str:
    """A variant key as a file name: characters other than letters, digits and `_.@-` become
    `_`, and a short hash of the key keeps apart keys that map to the same name (`track@a b`,
    `track@a_b`). A long key (`--video` of 30 clips: their names joined) is cut to
    `_MAX_KEY_CHARS`, the hash keeping it apart from the others that share its start."""
    safe = re.sub(r"[^A-Za-z0-9_.@-]+", "_", key)
    if safe == key and len(key) <= _MAX_KEY_CHARS:
        return key
    return f"{safe[:_MAX_KEY_CHARS]}.{hashlib.sha256(key.encode()).hexdigest()[:8]}"


def stage_code(stage: Stage) -> tuple[str, dict[str, str]]:
    """(code version, per-file digests) of what a stage runs: its declared version and the
    source of its module plus every project module it imports, transitively. Editing a library
    module a stage uses makes that stage stale; editing an unrelated one does not."""
    src = inspect.getsourcefile(stage.run)
    if src is None:
        return f"{stage.version}:unknown", {}
    files = code_digests(stage.run.__module__, Path(src), PROJECT_ROOT)
    digest = hashlib.sha256(json.dumps(files, sort_keys=True).encode()).hexdigest()[:16]
    return f"{stage.version}:{digest}", files


def _diff_params(old: dict, new: dict, prefix: str = "") -> list[str]:
    changes = []
    for k in sorted(set(old) | set(new)):
        if (k not in new and old[k] is None) or (k not in old and new[k] is None):
            continue  # None and absent say the same (an older record kept every key)
        a, b = old.get(k, "<unset>"), new.get(k, "<unset>")
        if isinstance(a, dict) and isinstance(b, dict):
            changes += _diff_params(a, b, f"{prefix}{k}.")
        elif a != b:
            changes.append(f"{prefix}{k}: {a!r} -> {b!r}")
    return changes


@contextlib.contextmanager
def _same_torch_threads():
    """torch's intra-op thread count as it was before a stage, after it: it is process-wide, and
    a stage that sets it must not decide it for the stages after it in one `run` (their results
    would depend on which stages ran before them in the same process). Only when torch is
    already loaded: a stage that does not use it does not pay for the import."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    try:
        yield
    finally:
        if before is not None:
            torch.set_num_threads(before)


class Runner:
    """Runs the stages of one scene."""

    def __init__(
        self,
        cfg: PipelineConfig,
        scene_name: str,
        stages: dict[str, Stage],
        *,
        options: dict[str, Any] | None = None,
        executor=None,
        progress=None,
    ):
        if scene_name not in cfg.scenes:
            raise ConfigError(
                f"--scene: unknown scene '{scene_name}' (scenes: {sorted(cfg.scenes)})"
            )
        self.cfg, self.scene_name, self.scene = cfg, scene_name, cfg.scenes[scene_name]
        self.stages = stages
        self.options = options or {}
        self.executor, self.progress = executor, progress
        self.workspace = cfg.scene_workspace(scene_name)
        self.meta = self.workspace / ".pipeline"
        self.hashes = HashCache(cfg.workspace / ".pipeline" / "hashcache.json")
        self.needs = {name: list(sc.needs) for name, sc in cfg.stages.items()}
        self._params = {name: self._validate_params(name) for name in cfg.stages}
        self._code_cache: dict[str, tuple[str, dict[str, str]]] = {}

    # -- context and bookkeeping -------------------------------------------------------------
    def _validate_params(self, name: str):
        model = self.stages[name].params_model
        try:
            params = validate_strictly(
                model, {**self.cfg.stages[name].params, **self.scene.params.get(name, {})}
            )
        except ValidationError as exc:
            # Locations as YAML paths of the params block(s), in the file actually loaded, and
            # which of the bad values came from --set.
            # (its path, not its name alone: `--config other/pipeline.yaml` was blamed on
            # "pipeline.yaml", the one in the folder run from)
            source = _shown(self.cfg.source) if self.cfg.source is not None else "pipeline.yaml"
            own = self.scene.params.get(name, {})
            scene_block = f"scenes.{self.scene_name}.params.{name}"
            lines = []
            for err in exc.errors():
                key = ".".join(str(x) for x in err["loc"])
                top = str(err["loc"][0]) if err["loc"] else None
                if top is None:  # a check across keys: the keys it names, where each is set
                    named = [k for k in {**self.cfg.stages[name].params, **own}
                             if re.search(rf"\b{re.escape(k)}\b", err["msg"])]  # fmt: skip
                    where = (
                        " / ".join(
                            f"{scene_block if k in own else f'stages.{name}.params'}.{k}"
                            for k in named
                        )
                        or f"stages.{name}.params"
                    )
                    body = format_error_line(err, source).split(": ", 2)[2]
                    line = f"{source}: {where}: {body}"
                else:  # the block that holds the key (the scene's wins)
                    where = scene_block if top in own else f"stages.{name}.params"
                    line = format_error_line(err, source, model).replace(
                        f"{source}: ", f"{source}: {where}.", 1
                    )
                    named = [key]
                given = [
                    t
                    for k in named
                    for t in (
                        self.cfg.overrides.get(f"{name}.{k}"),
                        self.cfg.overrides.get(f"{scene_block}.{k}"),
                    )
                    if t
                ]
                lines.append(line + (f" (set by --set {', '.join(given)})" if given else ""))
            raise ConfigError("\n".join(lines)) from None
        if self.cfg.base_dir is None:
            return params
        # relative paths in parameters (background clips, supplied boxes, a checkpoint to
        # reuse) are the config folder's, as every other path of the config, not the shell's
        return params.model_copy(
            update={
                k: _absolute(getattr(params, k), self.cfg.base_dir, names_file(f))
                for k, f in type(params).model_fields.items()
            }
        )

    def _scene_record(self, stage: Stage) -> dict:
        # Scene-level stage params reach each stage through its merged params; leaving them out
        # here keeps a change for one stage from invalidating the others. Paths are recorded
        # relative to the config's folder (see `_shown`). A stage that reads nothing of the
        # scene (`Stage.reads_scene`) records nothing of it.
        if not stage.reads_scene:
            return {}
        record = self.scene.model_dump(mode="json", exclude={"params"})
        for block, key in (("synthetic", "overrides"), ("calibration", "options")):
            if record.get(block):  # untyped: as YAML typed them
                record[block][key] = _same_numbers(record[block][key])
        return _relative_paths(record, self.cfg.base_dir)

    def _params_record(self, ctx: StageContext) -> dict:
        """The stage's validated params as fingerprints and records keep them (paths relative
        to the config's folder, as `status` compares them)."""
        record = ctx.params.model_dump(mode="json")
        # a mapping's values may keep the type the YAML gave (extract's `association: {...:
        # 1}` against `1.0`); typed fields are already one type
        record = {k: _same_numbers(v) if isinstance(v, dict) else v for k, v in record.items()}
        return _relative_paths(record, self.cfg.base_dir)

    def context(self, name: str) -> StageContext:
        ctx = StageContext(
            stage=name,
            scene_name=self.scene_name,
            scene=self.scene,
            config=self.cfg,
            workspace=self.workspace,
            staging=self.meta / "staging" / name,
            params=self._params[name],
            options=self.options,
            executor=self.executor,
            log=logging.getLogger(f"pipeline.{name}"),
            progress=self.progress,
        )
        key = self.key(name, ctx)
        if key == name:
            return ctx
        # one staging folder per variant: `track --video b.mp4` would delete the resumable
        # progress of an interrupted `track --video a.mp4` (another fingerprint, same folder)
        return dataclasses.replace(ctx, staging=self.meta / "staging" / _safe_key(key))

    def key(self, name: str, ctx: StageContext | None = None) -> str:
        variant = self.stages[name].variant(ctx or self.context(name))
        return name if variant is None else f"{name}@{variant}"

    def _code(self, name: str) -> tuple[str, dict[str, str]]:
        """The stage's code version and per-file digests, computed once per runner (the code
        does not change during a run)."""
        if name not in self._code_cache:
            self._code_cache[name] = stage_code(self.stages[name])
        return self._code_cache[name]

    def _record_path(self, key: str) -> Path:
        return self.meta / "state" / f"{_safe_key(key)}.json"

    def _read_record(self, key: str) -> dict | None:
        """The stage variant's record, None when it has none or none that can be read
        (`_load_record`): its outputs are then not trusted, and the stage reruns."""
        return _load_record(self._record_path(key))[0]

    def applies(self, name: str) -> bool:
        return self.stages[name].applies(self.scene)

    def _inputs(self, name: str, ctx: StageContext) -> dict[str, str | None]:
        """Digests of upstream outputs and declared external inputs. Upstream is every stage
        `name` needs, directly or not: stages read their ancestors' outputs too (extract reads
        synth's videos, train the calibration), and an ancestor can change while the stage in
        between writes the same bytes (a new synth render, the same rig.json)."""
        digests: dict[str, str | None] = {}
        for dep in upstream_closure(self.needs, [name])[:-1]:  # the stage itself comes last
            if not self.applies(dep):
                continue
            dep_ctx = self.context(dep)
            for rel in self.stages[dep].outputs(dep_ctx):
                if is_report(rel):
                    continue  # for people to read (timings change every run), never an input
                digests[f"{dep}:{rel}"] = self.hashes.digest(self.workspace / rel)
        for path in self.stages[name].inputs(ctx):
            digests[self._shown(path)] = self.hashes.digest(Path(path))
        for path in _param_files(ctx.params):
            digests.setdefault(self._shown(path), self.hashes.digest(path))  # e.g. track.boxes
        return digests

    def _shown(self, path: str | Path) -> str:
        """A path as fingerprints record it: relative to the config's folder, so a project
        copied elsewhere (config, workspace and inputs together) keeps its fingerprints."""
        base = self.cfg.base_dir
        return os.path.relpath(Path(path).absolute(), base) if base is not None else str(path)

    def _missing_inputs(self, name: str, ctx: StageContext) -> list[str]:
        return [str(p) for p in self.stages[name].inputs(ctx) if not Path(p).exists()]

    # -- status ------------------------------------------------------------------------------
    def status_of(self, name: str, upstream: dict[str, StageStatus]) -> StageStatus:
        stage = self.stages[name]
        if not stage.applies(self.scene):
            return StageStatus(name, name, SKIPPED, "does not apply to this scene")
        ctx = self.context(name)
        key = self.key(name, ctx)
        pending = [d for d in self.needs[name] if d in upstream and upstream[d].needs_run]
        params = self._params_record(ctx)
        record, problem = _load_record(self._record_path(key))
        if pending:
            state = MISSING if record is None else STALE
            return StageStatus(name, key, state, f"upstream {', '.join(pending)} will run first")
        missing = self._missing_inputs(name, ctx)
        if missing:
            return StageStatus(name, key, MISSING, f"input file is missing: {', '.join(missing)}")
        inputs = self._inputs(name, ctx)
        code, files = self._code(name)
        scene = self._scene_record(stage)
        fp = stage_fingerprint(code, {"params": params, "scene": scene}, inputs)
        failed = _failure(ctx.staging)
        if record is None:
            interrupted = ctx.staging.exists()
            why = "a previous run was interrupted" if interrupted else "never run"
            if failed is not None:
                why = f"its last run failed: {failed}"
            running = self._running_pid() if interrupted else None
            if running is not None:
                why = f"being written by the run now in progress (pid {running})"
            if not interrupted and not stage.in_all:
                why += f" (on demand: `run {name}`; `run all` skips it)"
            if problem is not None and running is None:
                why = (
                    f"its record {self._record_path(key)} cannot be read ({problem}); its "
                    "outputs are not trusted and it reruns"
                )
            return StageStatus(name, key, MISSING, why, fp)
        for rel in stage.outputs(ctx):  # declared now (e.g. track --with-gaussians' splats)
            if rel not in record.get("outputs", {}):
                # on disk or not, the recorded run did not make it (an earlier run's splats
                # from an older model were taken for this one's)
                made = (self.workspace / rel).exists()
                why = "was not made by its last run" if made else "is absent"
                return StageStatus(name, key, MISSING, f"output {rel} {why}", fp)
        for rel, digest in record.get("outputs", {}).items():
            now = self.hashes.digest(self.workspace / rel)
            if now is None:
                return StageStatus(name, key, MISSING, f"output {rel} is absent", fp)
            if now != digest:
                return StageStatus(name, key, STALE, f"output {rel} was modified since the run", fp)
        if record.get("fingerprint") == fp:
            return StageStatus(name, key, UP_TO_DATE, f"ran {record.get('finished', '?')}", fp)
        reasons = []
        if record.get("code") != code:
            old = record.get("code_files") or {}
            edited = sorted(f for f in set(old) | set(files) if old.get(f) != files.get(f))
            shown = ", ".join(edited[:3]) + (
                f" and {len(edited) - 3} more" if len(edited) > 3 else ""
            )
            reasons.append(f"code changed: {shown}" if old and edited else "code changed")
        reasons += [f"param {c}" for c in _diff_params(record.get("params", {}), params)]
        old_scene = record.get(
            "scene_config", record.get("scene")
        )  # records before 2026-11-21: "scene"
        reasons += [
            f"scene {c}"
            for c in _diff_params(old_scene if isinstance(old_scene, dict) else {}, scene)
        ]
        old_inputs = record.get("inputs", {})
        changed = [
            k for k in sorted(set(old_inputs) | set(inputs)) if old_inputs.get(k) != inputs.get(k)
        ]
        # an input outside the config's folder by its own path ("../../../work/..." said little);
        # a key only the old record has is relative to the folder the config was in then
        base = self.cfg.base_dir

        def shown(k: str) -> str:
            if base is not None and k.startswith("..") and k in inputs:
                return os.path.normpath(base / k)
            return k

        reasons += [f"input changed: {shown(k)}" for k in changed[:5]]
        if len(changed) > 5:
            reasons.append(f"... and {len(changed) - 5} more inputs")
        if failed is not None:
            reasons.append(f"its last run failed: {failed}")
        return StageStatus(name, key, STALE, "; ".join(reasons) or "fingerprint changed", fp)

    def status(self, targets: list[str] | None = None) -> list[StageStatus]:
        names = upstream_closure(self.needs, targets) if targets else topological_order(self.needs)
        result: dict[str, StageStatus] = {}
        for name in names:
            result[name] = self.status_of(name, result)
        out = list(result.values())
        if not targets:
            out += self._variant_statuses({st.key for st in out}, result)
        # a cache for the next look, in a workspace that is there: `status` of a workspace that
        # never ran made its folder (and failed where the workspace cannot be written)
        with contextlib.suppress(OSError):
            self.hashes.save(create=False)
        return out

    def _recorded_options(self, name: str) -> dict:
        """The CLI options a stage reads (e.g. track's --video), as a record keeps them to let
        `status` show that variant later; paths relative to the config's folder."""
        opts = {k: self.options.get(k) for k in self.stages[name].cli_options}
        return _relative_paths(json.loads(json.dumps(opts, default=str)), self.cfg.base_dir)

    def _variant_statuses(self, shown: set[str], upstream: dict) -> list[StageStatus]:
        """Statuses of the stage variants recorded earlier (e.g. `track@match` from a run with
        --video match.mp4), re-evaluated with the options they ran with."""
        out = []
        state_dir = self.meta / "state"
        for path in sorted(state_dir.glob("*@*.json")) if state_dir.is_dir() else []:
            record, problem = _load_record(path)
            if record is None:  # unreadable: its variant's options are unknown
                name = path.stem.split("@", 1)[0]
                if name in self.stages and path.stem not in {_safe_key(k) for k in shown}:
                    why = f"its record {path} cannot be read ({problem}); run that variant again"
                    out.append(StageStatus(name, path.stem, MISSING, why))
                continue
            name, key = record.get("stage"), record.get("key")
            if name not in self.stages or key in shown or "options" not in record:
                continue
            base = self.cfg.base_dir or Path.cwd()
            options = {
                k: [base / v for v in vals] if isinstance(vals, list) else vals
                for k, vals in record["options"].items()
            }
            other = Runner(self.cfg, self.scene_name, self.stages, options=options)
            try:
                out.append(other.status_of(name, upstream))
            except (FileNotFoundError, ConfigError) as exc:  # e.g. the video was moved since
                out.append(StageStatus(name, key, MISSING, f"its input is gone: {exc}", None))
        # Variants that never finished have no record, only their staging folder (with the
        # error a failed run stopped on): `track --video x.mp4` failed or killed was not listed.
        listed = {_safe_key(st.key) for st in out} | {_safe_key(k) for k in shown}
        staging_dir = self.meta / "staging"
        for folder in sorted(staging_dir.glob("*@*")) if staging_dir.is_dir() else []:
            name = folder.name.split("@", 1)[0]
            if folder.name in listed or name not in self.stages or not folder.is_dir():
                continue
            failure = _failure(folder)
            why = f"its last run failed: {failure}" if failure else "a run was interrupted"
            out.append(
                StageStatus(name, folder.name, MISSING, f"{why} (never finished; no record)")
            )
        return out

    def _running_pid(self) -> str | None:
        """The pid of another process's run that holds this scene's lock now (see `_lock`), or
        None when nobody does."""
        path = self.meta / "lock"
        if not path.is_file():
            return None
        with open(path, "a+") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = _lock_owner(fh)
                return None if owner == str(os.getpid()) else owner
            fcntl.flock(fh, fcntl.LOCK_UN)
        return None

    # -- running -----------------------------------------------------------------------------
    @contextlib.contextmanager
    def _lock(self):
        """Hold the scene's lock for the run (runs on other scenes are not held back). The file
        records the owner's pid: the kernel drops the lock when its owner dies, and a run that
        finds a dead owner's pid there says it took over."""
        self.meta.mkdir(parents=True, exist_ok=True)
        path = self.meta / "lock"
        with open(path, "a+") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = _lock_owner(fh)
                raise PipelineError(
                    f"another pipeline run (pid {owner}) holds the workspace lock {path}; wait "
                    "for it to finish"
                ) from None
            fh.seek(0)
            previous = fh.read().strip()
            if previous.isdigit() and int(previous) != os.getpid() and not _alive(int(previous)):
                log.warning(
                    "took over the workspace lock of run pid %s, which is gone (killed?); "
                    "its unfinished stages resume or rerun",
                    previous,
                )
            fh.seek(0)
            fh.truncate()
            fh.write(str(os.getpid()))
            fh.flush()
            # old outputs a commit parked in the trash, left there by a run stopped in the
            # middle of one (a model of a pretraining, kept for ever): no run commits here now
            remove_path(self.meta / "trash")
            try:
                yield
            finally:
                fh.seek(0)
                fh.truncate()
                fh.flush()

    def run(
        self,
        targets: list[str],
        *,
        force: bool = False,
        force_all: bool = False,
        dry_run: bool = False,
        upstream: bool = False,
    ) -> list[StageStatus]:
        """Run the targets and the upstream stages they need. Returns the statuses as planned.

        An upstream stage (not a target) that is stale but has its outputs is KEPT: the targets
        run against those outputs and the log says what is stale and how long the stage took
        last time, so an expensive rerun (a pretraining) never starts unasked. `upstream=True`
        reruns such stages too; missing upstream outputs are always produced."""
        names = upstream_closure(self.needs, targets)
        named_by_set = self._set_on_command_line()
        planned: dict[str, StageStatus] = {}
        for name in names:
            st = self.status_of(name, planned)
            if (
                st.state != SKIPPED
                and (force_all or (force and name in targets))
                and not st.needs_run
            ):
                st = StageStatus(name, st.key, STALE, "forced", st.fingerprint)
            elif (
                st.state == STALE
                and name not in targets
                and not (upstream or force_all or self._after_a_set(name, named_by_set))
                and self._read_record(st.key) is not None
            ):
                st = self._kept(name, st)
            planned[name] = st
        # A target that does not apply to the scene (bench on a scene without truth) needs
        # nothing upstream: `run bench --scene lab` ran extract, then skipped bench.
        skipped = [t for t in targets if t in planned and planned[t].state == SKIPPED]
        if skipped:
            needed = set(upstream_closure(self.needs, [t for t in targets if t not in skipped]))
            for name in names:
                st = planned[name]
                if name not in needed and st.needs_run:
                    why = f"only for {', '.join(skipped)}, which the scene does not need"
                    planned[name] = StageStatus(name, st.key, SKIPPED, why, st.fingerprint)
        if dry_run:  # writes nothing, the hash cache included (it made a never-run workspace)
            return list(planned.values())
        self.hashes.save()
        first = [f"{n} ({planned[n].reason})" for n in names
                 if n not in targets and planned[n].needs_run]  # fmt: skip
        if first:  # said before a pretraining nobody named starts (`track` in a new workspace)
            log.info(
                "%s: running first what %s needs: %s (`--dry-run` shows the plan)",
                self.scene_name, ", ".join(targets), ", ".join(first),
            )  # fmt: skip
        with self._lock():
            done: dict[str, StageStatus] = {}
            ran: set[str] = set()
            for name in names:
                st = planned[name]
                ancestors = upstream_closure(self.needs, [name])[:-1]
                upstream_ran = bool(ran.intersection(ancestors))
                if st.state not in (SKIPPED, KEPT) and (
                    upstream_ran or (st.needs_run and st.fingerprint is None)
                ):
                    # an ancestor ran since planning (maybe behind a kept stage, so the plan's
                    # fingerprint was computed from its old or absent outputs): recompute, for
                    # a stage planned up to date too (after a kill between an upstream's record
                    # and its outputs, the plan saw the old outputs and called it current)
                    st = self.status_of(name, done)
                    if not st.needs_run and not (force_all or (force and name in targets)):
                        # the upstream rerun wrote the same outputs (e.g. a comment edited)
                        why = "; its upstream ran" if upstream_ran else ""
                        log.info("%s: %s (%s%s)", name, st.state, st.reason, why)
                        done[name] = st
                        continue
                elif not st.needs_run:
                    log.info("%s: %s (%s)", name, st.state, st.reason)
                    done[name] = st
                    continue
                self._execute(name, st)
                ran.add(name)
                done[name] = StageStatus(name, st.key, UP_TO_DATE, "just ran", st.fingerprint)
        return list(planned.values())

    def _set_on_command_line(self) -> set[str]:
        """Stages a `--set` of this command gives a parameter (`S.K`, `stages.S...`,
        `scenes.<this scene>.params.S.K` or `scenes.<this scene>.params={S: ...}`), or a scene
        setting they read (`scenes.<this scene>.fps`, `.synthetic.seed`, ...: every stage that
        reads the scene; those were kept stale while the target took the new value)."""
        named = set()
        for key, text in self.cfg.overrides.items():
            parts = scene_key_parts(key.split("."), self.cfg.scenes)  # `take.1`: one part
            if parts[:3] == ["scenes", self.scene_name, "params"]:
                if len(parts) > 3:
                    named.add(parts[3])
                else:
                    value = parse_override(text)[1]
                    named |= set(value) if isinstance(value, dict) else set()
            elif parts[:2] == ["scenes", self.scene_name] and len(parts) > 2:
                named |= {n for n, st in self.stages.items() if st.reads_scene}
            elif parts[0] == "stages" and len(parts) > 1:
                named.add(parts[1])
            elif parts[0] in self.stages:
                named.add(parts[0])
        return named & set(self.stages)

    def _after_a_set(self, name: str, named: set[str]) -> bool:
        """Whether a stale upstream stage reruns rather than being kept: a `--set` of this
        command names it or a stage it depends on (`named`, `_set_on_command_line`; kept, the
        value typed on this very command line was dropped, or reached the target through a
        stage that still held the old one)."""
        return bool(named) and bool(named & set(upstream_closure(self.needs, [name])))

    def _kept(self, name: str, st: StageStatus) -> StageStatus:
        """An upstream stage that is stale but not rerun (see `run`), with the log line that
        says so. Its downstream stages see its current outputs."""
        record = self._read_record(st.key) or {}
        took = record.get("seconds")
        took_text = f"; its last run took {_duration(took)}" if took is not None else ""
        reason = st.reason  # e.g. "upstream synth will run first": it runs, this one is kept
        log.warning(
            "%s is stale (%s)%s; using its existing outputs. Run it, or pass --upstream, to "
            "update it",
            name,
            reason,
            took_text,
        )
        return StageStatus(name, st.key, KEPT, f"stale ({reason}), outputs kept{took_text}")

    def _execute(self, name: str, st: StageStatus) -> None:
        stage = self.stages[name]
        ctx = self.context(name)
        missing = self._missing_inputs(name, ctx)
        if missing:
            raise StageFailed(
                name,
                self.scene_name,
                FileNotFoundError(f"input file is missing: {', '.join(missing)}"),
            )
        staging = ctx.staging
        marker = staging / ".fingerprint"
        if staging.exists() and not (
            stage.resumable and marker.is_file() and marker.read_text() == st.fingerprint
        ):
            remove_path(staging)
        ctx.resumed = staging.exists()
        staging.mkdir(parents=True, exist_ok=True)
        marker.write_text(st.fingerprint or "")
        (staging / FAILED_MARKER).unlink(missing_ok=True)  # a resumed failed run tries again
        log.info("%s: running (%s)", name, st.reason)
        t0 = time.perf_counter()
        try:
            with _same_torch_threads():
                stage.run(ctx)
        except PipelineError as exc:
            _record_failure(staging, exc)  # `status` said "interrupted" after these
            raise
        except BaseException as exc:
            if isinstance(exc, KeyboardInterrupt):
                raise
            if is_input_error(exc):  # the message says it all; the traceback is for the file
                logging.getLogger(TRACEBACK_LOGGER).error("%s failed", name, exc_info=exc)
            else:
                log.exception("%s failed", name)
            _record_failure(staging, exc)
            raise StageFailed(name, self.scene_name, exc) from exc
        outputs = stage.outputs(ctx)
        absent = [rel for rel in outputs if not (staging / rel).exists()]
        if absent:
            err = RuntimeError(f"the stage did not write its declared outputs {absent}")
            _record_failure(staging, err)
            raise StageFailed(name, self.scene_name, err)
        # Commit: forget the old record, move outputs into place, then record the new one.
        self._record_path(st.key).unlink(missing_ok=True)
        trash = self.meta / "trash"
        for rel in outputs:
            replace_path(staging / rel, self.workspace / rel, trash)
        digests = {rel: self.hashes.digest(self.workspace / rel) for rel in outputs}
        self.hashes.save()
        record = {
            "stage": name,
            "key": st.key,
            "scene": self.scene_name,
            "fingerprint": st.fingerprint,
            "code": self._code(name)[0],
            "code_files": self._code(name)[1],
            "params": self._params_record(ctx),
            "scene_config": self._scene_record(stage),
            "options": self._recorded_options(name),
            "inputs": self._inputs(name, ctx),
            "outputs": digests,
            "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
            "seconds": round(time.perf_counter() - t0, 3),
        }
        atomic_write_text(self._record_path(st.key), json.dumps(record, indent=2))
        remove_path(staging)
        log.info("%s: done in %.1f s", name, record["seconds"])
