"""`pipeline.yaml` schema (pydantic), loading, `--set` overrides and readable errors.

The file declares a workspace root, one or more scenes and the stages of the DAG:

    workspace: workspace            # relative paths resolve against this file's folder
    default_scene: demo
    executor: {kind: local, workers: 2}
    scenes:
      demo: {synthetic: {preset: demo, seed: 0}}
      lab:
        videos: ../shared/real/pose2sim-multiperson/cam*.mp4
        calibration: {file: ../shared/real/pose2sim-multiperson/Calib.qca.txt, format: qualisys}
    stages:
      calibrate: {needs: [synth], params: {...}}

Stage parameters are validated by each stage's own pydantic model (see `pipeline.stage`).
"""

from __future__ import annotations

import difflib
import glob
import json
import os
import re
import types
import typing
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, model_validator

from pipeline.dag import topological_order
from pipeline.errors import ConfigError


def validate_strictly(model: type[BaseModel], data: dict) -> BaseModel:
    """`model` from config data without pydantic's lax conversions: `lr: true` became 1.0 and
    `steps: "10"` 10 without a word. Through JSON, whose strict mode still takes integers for
    floats, lists for tuples and text for paths."""
    return model.model_validate_json(json.dumps(data, default=str), strict=True)


class Strict(BaseModel):
    # unknown keys are errors, and so are NaN and infinity (`fps: .inf` was taken)
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class ExecutorConfig(Strict):
    kind: Literal["local", "ray"] = "local"
    workers: int | None = Field(default=None, ge=1, description="default: number of CPU cores")
    ray_address: str | None = None


class SyntheticSource(Strict):
    preset: str = "demo"
    seed: int = Field(0, ge=0)
    overrides: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _a_scene_spec(self) -> SyntheticSource:
        """The preset and overrides make a scene spec: refused here, naming the key, before
        any stage runs (a misspelt preset or override key failed in the synth stage, with a
        traceback)."""
        from synth.spec import SceneSpec, preset_fields

        if "seed" in self.overrides:  # two seeds: preset() would take neither
            raise ValueError(f"overrides.seed: give the seed as 'seed' (now {self.seed})")
        try:
            fields = preset_fields(self.preset, seed=self.seed, **self.overrides)
        except KeyError as exc:
            raise ValueError(f"preset: {exc.args[0]}") from None
        except (TypeError, AttributeError) as exc:  # a `__` key under a value that is no mapping
            bad = [k for k in self.overrides if "__" in k or "." in k]
            raise ValueError(f"overrides: {bad or 'a nested key'}: {exc}") from None
        try:  # strictly, as the rest of the file: `n_frames: "10"` is an error, not 10
            spec = validate_strictly(SceneSpec, fields)
        except ValidationError as exc:
            raise ValueError(
                "; ".join(
                    format_error_line(err, "", SceneSpec, key_prefix="overrides")
                    for err in exc.errors(include_url=False)
                )
            ) from None
        # what the spec's own checks cannot see (motion names, the board's dictionary and
        # marker count, distortion terms, a lens that folds): the synth stage's setup, which
        # costs milliseconds and needs no body model
        from synth.people import check_programmes
        from synth.shares import SceneSetup

        try:
            check_programmes(spec.n_people, spec.motions)
            SceneSetup.build(spec)
        except ValueError as exc:
            raise ValueError(f"overrides: {exc}") from None
        return self


_UNION_BRANCHES = {"str", "int", "float", "bool", "none"}


def _keys(loc: tuple) -> list[str]:
    """The keys of a pydantic error location, without its union branches (`list[...]`,
    `literal[...]`, `str`): `videos.list[lax-or-strict[...]]` named no key the user wrote."""
    return [str(p) for p in loc if "[" not in str(p) and str(p) not in _UNION_BRANCHES]


class CalibrationSource(Strict):
    file: Path
    format: str | None = None  # auto-detected from the file when omitted
    options: dict[str, Any] = Field(default_factory=dict)


class BoardSource(Strict):
    videos: list[Path] | str  # one per camera, or a glob
    kind: Literal["charuco", "checkerboard"] = "charuco"
    squares_x: int = Field(ge=2)
    squares_y: int = Field(ge=2)
    square_size: float = Field(gt=0, description="metres")
    marker_size: float | None = Field(default=None, gt=0)
    dictionary: str = "DICT_5X5_100"

    @model_validator(mode="after")
    def _metres(self) -> BoardSource:
        from calibration.board import BoardSpec, check_square_metres

        check_square_metres(self.square_size)  # refused here, before any stage runs
        # the board's own checks (at least 3 x 3 squares, a ChArUco marker inside its square,
        # a dictionary that exists and holds enough markers): they failed in calibrate
        BoardSpec(
            self.kind, self.squares_x, self.squares_y, self.square_size, self.marker_size,
            self.dictionary,
        )  # fmt: skip
        return self


class SceneConfig(Strict):
    """Where a scene's footage comes from: a synthetic spec, or camera videos."""

    synthetic: SyntheticSource | None = None
    videos: list[Path] | str | None = None  # list of files, or a glob; camera name = file stem
    calibration: CalibrationSource | None = None
    board: BoardSource | None = None
    masks: Path | None = None  # externally supplied masks/boxes (see docs/formats)
    fps: float | None = Field(default=None, gt=0)
    # Decoded frames may be smaller than the calibration says by this many pixels (encoder
    # padding, e.g. 1080 rows in a 1088-row calibration); calibration.camera.fit_to_frames.
    frame_size_tolerance: int = Field(default=16, ge=0)
    # Stage parameters for this scene only: {stage: {key: value}}, over stages.STAGE.params.
    params: dict[str, dict[str, Any]] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _one_source(self):
        if (self.synthetic is None) == (self.videos is None):
            raise ValueError("a scene needs exactly one of 'synthetic' or 'videos'")
        return self

    @property
    def is_synthetic(self) -> bool:
        return self.synthetic is not None

    def video_files(self) -> list[Path]:
        """The scene's camera videos, sorted by name (empty for synthetic scenes)."""
        return _expand(self.videos)

    def board_videos(self) -> list[Path]:
        """The board footage's files (empty without a `board` block)."""
        return _expand(self.board.videos) if self.board is not None else []


class StageConfig(Strict):
    needs: list[str] = Field(default_factory=list)
    module: str | None = (
        None  # 'module' or 'module:ATTR' defining the Stage; default `stages.<name>`
    )
    params: dict[str, Any] = Field(default_factory=dict)


# '..', '/tmp/x', 'a/b' or '.pipeline' put a scene's outputs outside its own folder (a scene
# named '..' replaced the folders beside the workspace: the project's own packages)
SCENE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
ALL_SCENES = "all"


class PipelineConfig(Strict):
    workspace: Path = Path("workspace")
    default_scene: str | None = None
    executor: ExecutorConfig = Field(default_factory=ExecutorConfig)
    scenes: dict[str, SceneConfig] = Field(min_length=1)
    stages: dict[str, StageConfig] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check_graph(self):
        if not self.stages:  # ran nothing and said so with an empty table, exit 0
            raise ValueError(
                "stages: the file declares no stages; a config of your own needs the DAG too: "
                "copy the `stages:` block of the project's pipeline.yaml into it, or add your "
                "scene to pipeline.yaml (docs/pipeline.md)"
            )
        references = [(f"stages.{n}.needs", stage.needs) for n, stage in self.stages.items()]
        references += [(f"scenes.{n}.params", scene.params) for n, scene in self.scenes.items()]
        for where, names in references:
            for name in names:
                if name not in self.stages:
                    raise ValueError(
                        f"{where}: unknown stage '{name}' (declared stages: {sorted(self.stages)})"
                    )
        for name in self.scenes:  # a scene's name is its folder under the workspace
            if not SCENE_NAME.fullmatch(name) or name == ALL_SCENES:
                raise ValueError(
                    f"scenes: the scene name {name!r} cannot be a folder of the workspace: use "
                    "letters, digits, '_', '-' and '.', starting with a letter or digit, and "
                    f"not '{ALL_SCENES}' (which --scene reads as every scene)"
                )
        # a cycle among the needs is a config error, found before anything runs or is logged
        topological_order({n: list(stage.needs) for n, stage in self.stages.items()})
        if self.default_scene is not None and self.default_scene not in self.scenes:
            raise ValueError(
                f"default_scene: '{self.default_scene}' is not a scene (scenes: "
                f"{sorted(self.scenes)})"
            )
        return self

    # Where the config came from (set by `load_config`): relative paths resolve against its
    # folder, fingerprints record paths relative to it, errors name the file and the --set
    # options that changed a value.
    _source: Path | None = PrivateAttr(None)
    _overrides: dict[str, str] = PrivateAttr(default_factory=dict)

    @property
    def source(self) -> Path | None:
        return self._source

    @property
    def base_dir(self) -> Path | None:
        return self._source.parent if self._source is not None else None

    @property
    def overrides(self) -> dict[str, str]:
        """Dotted key (as `--set` wrote it) -> the `--set` text that set it."""
        return dict(self._overrides)

    def scene_workspace(self, scene: str) -> Path:
        path = self.workspace / scene
        if path.resolve().parent != self.workspace.resolve():  # names are checked above
            raise ConfigError(f"scene {scene!r}: its folder {path} is not in the workspace")
        return path


def _expand(spec: list[Path] | str | None) -> list[Path]:
    if spec is None:
        return []
    if isinstance(spec, str):
        return sorted(Path(p) for p in glob.glob(spec))
    return list(spec)


# files a video pattern should not take (data, text, images, calibration and marker files)
NOT_VIDEO_SUFFIXES = (
    ".txt", ".md", ".json", ".toml", ".yaml", ".yml", ".csv", ".xml", ".qca", ".npz", ".npy",
    ".h5", ".parquet", ".c3d", ".trc", ".png", ".jpg", ".jpeg", ".pdf", ".zip", ".py",
)  # fmt: skip


def scene_input_problems(name: str, scene: SceneConfig, needs_rig: bool = True) -> list[str]:
    """What is wrong with a scene's declared inputs, one line each naming the key: globs that
    match nothing, listed files that do not exist, an unknown calibration format, a folder or a
    non-video file among the videos, a file listed twice; with `needs_rig` (the run reaches
    `calibrate`), a video scene without exactly one of a calibration file and board footage."""
    from calibration.formats import FORMATS  # the library knows its formats

    problems = []

    def files(key: str, spec: list[Path] | str | None) -> None:
        matched = _expand(spec)  # (a glob is matched once)
        if isinstance(spec, str) and not matched:
            hint = " (brackets are glob syntax: write [[] for '[', or list the files)"
            problems.append(
                f"scenes.{name}.{key}: the pattern '{spec}' matches no file"
                + (hint if "[" in spec else "")
            )
        elif isinstance(spec, list):
            missing = [str(p) for p in spec if not Path(p).is_file() and not Path(p).is_dir()]
            if missing:
                problems.append(f"scenes.{name}.{key}: no such file: {', '.join(missing)}")
            elif not spec:
                problems.append(f"scenes.{name}.{key}: the list is empty (one file per camera)")
        if key == "videos":  # (board footage may be folders of images)
            folders = [str(p) for p in matched if Path(p).is_dir()]
            if folders:  # was read as one camera named after the folder
                problems.append(
                    f"scenes.{name}.{key}: {', '.join(folders)} is a folder, not a video; name "
                    "the videos in it, e.g. '<folder>/cam*.mp4'"
                )
            other = [str(p) for p in matched if Path(p).suffix.lower() in NOT_VIDEO_SUFFIXES]
            if other:  # `*` took the calibration file and the notes as cameras
                problems.append(
                    f"scenes.{name}.{key}: {', '.join(other)} are no videos; narrow the pattern "
                    "(e.g. 'cam*.mp4') or list the files"
                )
        # a camera is named by its file's stem: two files of one stem were one camera, the
        # last one listed (cam01.mp4 beside cam01.MOV)
        stems: dict[str, list[str]] = {}
        for path in matched:
            stems.setdefault(Path(path).stem, []).append(str(path))
        for stem, same in sorted(stems.items()):
            if len({os.path.realpath(p) for p in same}) < len(same):  # one file, two spellings too
                problems.append(
                    f"scenes.{name}.{key}: listed twice: {', '.join(sorted(set(same)))}; remove "
                    "the duplicate"
                )
            elif len(same) > 1:
                problems.append(
                    f"scenes.{name}.{key}: {len(same)} files would be camera '{stem}' (a camera "
                    f"is named by its file's stem): {', '.join(same)}"
                )

    files("videos", scene.videos)
    if (
        needs_rig
        and not scene.is_synthetic
        and (scene.calibration is None) == (scene.board is None)
    ):
        # found by the calibrate stage as a failure (exit 1, a .failed record), after the run
        problems.append(
            f"scenes.{name}: needs exactly one of a calibration file or board footage: add "
            "'calibration: {file: ..., format: ...}' or 'board: {...}' to the scene"
        )
    if scene.board is not None:
        files("board.videos", scene.board.videos)
    c = scene.calibration
    if c is not None:
        if not Path(c.file).exists():
            problems.append(f"scenes.{name}.calibration.file: no such file: {c.file}")
        if c.format is not None and c.format not in FORMATS:
            problems.append(
                f"scenes.{name}.calibration.format: unknown format '{c.format}' "
                f"(formats: {', '.join(sorted(FORMATS))}; omit it to detect it from the file)"
            )
    if scene.masks is not None and not Path(scene.masks).exists():
        problems.append(f"scenes.{name}.masks: no such folder: {scene.masks}")
    return problems


def _resolve_paths(cfg: PipelineConfig, base: Path) -> PipelineConfig:
    """Make every path relative to the config file's folder absolute."""

    def fix(p):
        if p is None:
            return None
        # `~/...` is the user's home, as in a shell (it was a folder named `~` in the config's)
        p = os.path.expanduser(p) if isinstance(p, str) else p.expanduser()
        if isinstance(p, str):  # a glob: the folders it starts from are no pattern ("take [2]")
            if Path(p).is_absolute():
                return p
            parts = Path(p).parts
            up = next((i for i, part in enumerate(parts) if part not in ("..", ".")), len(parts))
            start = os.path.normpath(base.joinpath(*parts[:up]))
            return os.path.join(glob.escape(start), *parts[up:])
        return p if Path(p).is_absolute() else Path(os.path.normpath(base / p))

    cfg.workspace = fix(cfg.workspace)
    for name, scene in cfg.scenes.items():
        body = scene.synthetic.overrides.get("body_model") if scene.synthetic else None
        if isinstance(body, str) and body != "anny" and body.split(":")[0] != "smpl":
            # a file: beside the config, as every other path here (it was looked up from the
            # shell's folder, by the synth stage, after the config had passed)
            path = fix(Path(body))
            if not path.exists():
                raise ConfigError(
                    f"scenes.{name}.synthetic.overrides.body_model: {path} does not exist "
                    "(expected 'anny', 'smpl[:gender]' or an SMPL file; a relative path is read "
                    "from the config's folder)"
                )
            scene.synthetic.overrides["body_model"] = str(path)
        scene.videos = (
            [fix(p) for p in scene.videos] if isinstance(scene.videos, list) else fix(scene.videos)
        )
        scene.masks = fix(scene.masks)
        if scene.calibration:
            scene.calibration.file = fix(scene.calibration.file)
        if scene.board:
            b = scene.board
            b.videos = [fix(p) for p in b.videos] if isinstance(b.videos, list) else fix(b.videos)
    return cfg


class _CoreSchemaLoader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2's core schema for plain scalars: `010` is 10 (not
    octal 8), `12:30` and `yes` / `on` stay text (not 750 and true), and `1e-3` is a number
    inside lists and mappings too (YAML 1.1 wants a dot in it)."""

    def construct_mapping(self, node, deep=False):
        # a key given twice: PyYAML keeps the last one without a word (two `pretrain:` blocks,
        # the first one's settings silently gone)
        seen: dict = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag.endswith(":merge"):
                continue  # `<<: *base` merges may repeat keys on purpose
            key, line = key_node.value, key_node.start_mark.line + 1
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"key '{key}' is given twice (lines {seen[key]} and {line}); keep one",
                    key_node.start_mark,
                )
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


# YAML 1.1's booleans, octal/sexagesimal numbers, dates (`2024-06-01` a datetime.date) and the
# `=` value tag are not YAML 1.2's core schema: left as text
_OLD_TAGS = {
    "tag:yaml.org,2002:bool",
    "tag:yaml.org,2002:int",
    "tag:yaml.org,2002:float",
    "tag:yaml.org,2002:timestamp",
    "tag:yaml.org,2002:value",
}
_CoreSchemaLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in rules if tag not in _OLD_TAGS]
    for first, rules in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_CoreSchemaLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)
_CoreSchemaLoader.add_implicit_resolver(
    "tag:yaml.org,2002:int",
    re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"),
    list("-+0123456789"),
)
_CoreSchemaLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+0123456789."),
)


def _core_int(loader: yaml.SafeLoader, node: yaml.Node) -> int:
    text = loader.construct_scalar(node)
    return int(text, 0) if text[:2] in ("0o", "0x") else int(text, 10)


_CoreSchemaLoader.add_constructor("tag:yaml.org,2002:int", _core_int)


def _fields_at(model: type[BaseModel] | None, loc: tuple) -> list[str] | None:
    """The field names of the model that holds the key at `loc` (its parent path), following
    `model`'s fields and the values of its dicts; None where the path leaves the models."""
    key_next = False  # the part after a dict field is one of its keys (a scene named 'videos')
    for part in loc[:-1]:
        if model is None:
            return None
        if key_next:
            key_next = False
            continue
        field = model.model_fields.get(str(part))
        if field is None:
            return None
        key_next = typing.get_origin(_unoptional(field.annotation)) is dict
        model = _model_in(field.annotation)
    return None if model is None or key_next else list(model.model_fields)


def _unoptional(annotation):
    """`X` of `X | None`."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType) and len(args) == 1:
        return args[0]
    return annotation


def _model_in(annotation) -> type[BaseModel] | None:
    """The pydantic model an annotation holds: itself, an Optional's, a dict's value's."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in reversed(typing.get_args(annotation)):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _suggest(model: type[BaseModel] | None, loc: tuple) -> str:
    """' (did you mean 'videos'?)' or ' (keys here: ...)' for an unknown key at `loc`."""
    if not loc:
        return ""
    names = _fields_at(model, tuple(loc))
    if not names:
        return ""
    close = difflib.get_close_matches(str(loc[-1]), names, n=1)
    if close:
        return f" (did you mean '{close[0]}'?)"
    return f" (keys here: {', '.join(names)})"


def load_yaml(text: str) -> Any:
    """YAML text (the config file, a `--set` value) read with YAML 1.2's core schema."""
    return yaml.load(text, Loader=_CoreSchemaLoader)  # a SafeLoader: builds no Python objects


def format_error_line(
    err: dict, source: str, model: type[BaseModel] | None = None, key_prefix: str = ""
) -> str:
    """One pydantic error as `file: dotted.key: what was expected (got ...)`. `model`: the
    validated model, whose fields an unknown key is matched against ("did you mean").
    `key_prefix`: where the model sits in the file (a synthetic scene's `overrides`), put
    before its keys; `source` "" leaves the file out."""
    keys = _keys(err["loc"])
    loc = ".".join([key_prefix, *keys] if key_prefix else keys) or "(top level)"
    head = f"{source}: {loc}" if source else loc
    if err["type"] == "extra_forbidden":
        return f"{head}: unknown key" + _suggest(model, err["loc"])
    if err["type"] == "missing":
        return f"{head}: required key is missing"
    msg = err["msg"].removeprefix("Value error, ")
    got = err.get("input")
    # a check of the whole prefixed model has the model's fields as its input, not a value
    whole = key_prefix and not keys
    shown = "" if isinstance(got, dict) or whole else f" (got {got!r})"
    return f"{head}: {msg}{shown}"


def format_validation_error(exc: ValidationError, source: str) -> str:
    """One line per problem: file, dotted key, and what was expected."""
    return "\n".join(format_error_line(err, source, PipelineConfig) for err in exc.errors())


def parse_override(text: str) -> tuple[list[str], Any]:
    """`stage.key=value` -> (['stage', 'key'], value parsed as YAML)."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE, e.g. --set train.steps=200")
    key, raw = text.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if len(parts) < 2 and parts[:1] not in (["workspace"], ["default_scene"]):
        raise ConfigError(
            f"--set {text!r}: expected STAGE.KEY=VALUE (or a top-level key like executor.workers)"
        )
    try:
        value = load_yaml(raw)
    except yaml.YAMLError as exc:
        # (PyYAML names the value "<unicode string>")
        where = str(exc).replace('in "<unicode string>", ', "at ")
        raise ConfigError(f"--set {text!r}: value is not valid YAML ({where})") from exc
    return parts, value


def scene_key_parts(parts: list[str], scenes) -> list[str]:
    """An override key's parts with a scene's name as one part: a name may hold dots (`take.1`),
    so `scenes.take.1.fps` is the longest scene name the key starts with, then the rest (split
    at every dot it said "no scene 'take'")."""
    if parts[0] == "scenes" and len(parts) > 2:
        for end in range(len(parts) - 1, 2, -1):
            if ".".join(parts[1:end]) in scenes:
                return [parts[0], ".".join(parts[1:end]), *parts[end:]]
    return parts


def apply_override(raw: dict, parts: list[str], value: Any) -> list[str]:
    """Apply a parsed override to the raw YAML dict. `stage.k=v` sets stages.stage.params.k;
    keys starting with a top-level section (workspace, executor, scenes, ...) are set directly.
    A stage override also removes that key from every scene's `params` for the stage. Returns
    the key as it is recorded (`stages.S.params.K` as `S.K`)."""
    top_level = set(PipelineConfig.model_fields)
    scenes = raw.get("scenes") if isinstance(raw.get("scenes"), dict) else {}
    parts = scene_key_parts(parts, scenes)
    if parts[0] == "scenes" and len(parts) > 2 and parts[1] not in scenes:
        if parts[2] not in ("synthetic", "videos"):  # a typo'd scene, not a new one
            raise ConfigError(
                f"--set {'.'.join(parts)}: no scene '{parts[1]}' (scenes: {sorted(scenes)}); a "
                "new scene needs its footage first (scenes.NAME.synthetic or .videos)"
            )
    if len(parts) > 3 and parts[0] == "stages" and parts[2] == "params":
        parts = [parts[1], *parts[3:]]  # the long form: as `--set S.K=V`, over scenes' values
    if parts[0] in top_level:
        path = parts
    else:
        stages = raw.get("stages") or {}
        if parts[0] not in stages:
            raise ConfigError(
                f"--set {'.'.join(parts)}: '{parts[0]}' is neither a stage ({sorted(stages)}) "
                f"nor a top-level key ({sorted(top_level)})"
            )
        path = ["stages", parts[0], "params", *parts[1:]]
        # --set wins over a scene's own value of that parameter (a malformed scene is left
        # for the config's validation to name)
        scenes = raw.get("scenes")
        for scene in scenes.values() if isinstance(scenes, dict) else ():
            params = scene.get("params") if isinstance(scene, dict) else None
            scene_params = params.get(parts[0]) if isinstance(params, dict) else None
            if isinstance(scene_params, dict) and len(parts) > 1:
                scene_params.pop(parts[1], None)
    node = raw
    for p in path[:-1]:
        nxt = node.get(p)
        if nxt is None:
            nxt = node[p] = {}
        if not isinstance(nxt, dict):
            raise ConfigError(f"--set {'.'.join(parts)}: '{p}' is not a mapping")
        node = nxt
    node[path[-1]] = value
    return parts


def load_config(path: str | Path, overrides: list[str] = ()) -> PipelineConfig:
    """Read, override and validate `pipeline.yaml`. Raises ConfigError with a readable message."""
    path = Path(path)
    if path.is_dir():  # `--config configs/`: the file in it was meant
        raise ConfigError(
            f"config file {path} is a folder; pass the pipeline file in it (--config "
            f"{path / 'pipeline.yaml'})"
        )
    if not path.is_file():  # the folder it was looked for in: the user ran from another one
        raise ConfigError(
            f"config file not found: {path} (looked for from {Path.cwd()}; pass --config PATH)"
        )
    try:
        raw = load_yaml(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        # PyYAML names the text it read "<unicode string>": the file is meant
        text = str(exc).replace('"<unicode string>"', f'"{path}"')
        if "'\\t'" in text:  # "found character '\t' that cannot start any token"
            text += "\n(YAML indents with spaces, not tabs: replace the tab)"
        raise ConfigError(f"{path}: not valid YAML: {text}") from exc
    except (UnicodeDecodeError, OSError) as exc:  # a video or a UTF-16 file given as --config
        raise ConfigError(f"{path}: not a readable UTF-8 YAML file ({exc})") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(raw).__name__}")
    given: dict[str, str] = {}
    parsed = [(text, *parse_override(text)) for text in overrides]
    # a scene's own values first, so that `--set STAGE.KEY` wins over them in any order (given
    # after it, `--set scenes.S.params.STAGE.KEY` won)
    parsed.sort(key=lambda item: item[1][0] != "scenes")
    for text, parts, value in parsed:
        # the long form `stages.S.params.K` is recorded as `S.K`, the key the stage's
        # validation looks up (an error in it blamed the file, which said something else)
        given[".".join(apply_override(raw, parts, value))] = text
    try:
        cfg = validate_strictly(PipelineConfig, raw)
    except ValidationError as exc:
        raise ConfigError(_name_overrides(format_validation_error(exc, str(path)), given)) from None
    cfg = _resolve_paths(cfg, path.resolve().parent)
    blocked = next((p for p in (cfg.workspace, *cfg.workspace.parents) if p.exists()), None)
    if blocked is not None and not blocked.is_dir():
        raise ConfigError(
            f"{path}: workspace: {cfg.workspace} cannot be a folder: {blocked} is a file"
        )
    cfg._source = path.resolve()
    cfg._overrides = given
    return cfg


def _name_overrides(message: str, given: dict[str, str]) -> str:
    """Say which error lines concern a value that came from `--set`."""
    lines = []
    for line in message.splitlines():
        parts = line.split(": ")  # "file: dotted.key: what was expected"
        loc = parts[1] if len(parts) > 2 else ""
        if loc == "(top level)" and len(parts) > 3:  # a cross-field check names its key next
            loc = parts[2]
        # the key itself, a value inside it, or the block whose check it failed; a text search
        # named `--set workspace=out` for an error at `myworkspace/...`'s executor.workers
        hit = [
            t
            for k, t in given.items()
            for key in (k, f"stages.{k.split('.')[0]}.params.{'.'.join(k.split('.')[1:])}")
            if loc and (loc == key or loc.startswith(key + ".") or key.startswith(loc + "."))
        ]
        lines.append(line + (f" (set by --set {hit[0]})" if hit else ""))
    return "\n".join(lines)
