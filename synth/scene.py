"""Scene specs, presets and `render_scene`, which writes a complete synthetic capture folder.

Layout (see docs/formats/synth_scene.md): scene.json, board.json, videos/<cam>.mp4,
board/<cam>.mp4, calibration/{rig.json, calibration_synth.json, cameras.h5},
truth/{people,views,board_poses,board_views}.parquet, truth/masks/<cam>.h5,
preview/{contact_sheet,truth_overlay,board_sheet}.png.

Everything is deterministic from the spec's seed: each random stream (rig, stage, people, each
person's motion, board path, each camera's response and noise) has its own seed sequence, so
outputs are byte-identical run to run and do not change when unrelated settings do.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from synth.animate import check_body_model, pose_person
from synth.appearance import BodyAtlas
from synth.board import ChArUcoSpec, board_json
from synth.io import replace_dir, write_json, write_parquet, write_png
from synth.people import sample_crowd, sample_people
from synth.preview import contact_sheet, truth_overlay
from synth.render import vertex_normals
from synth.shares import (
    CameraShareJob,
    Cast,
    CastFiles,
    CastMember,
    JointCheck,
    SceneSetup,
    ShareResult,
    camera_shares,
    render_share,
    render_share_job,
)
from synth.skeleton import JOINT_NAMES
from synth.truth import OCCLUSION_TOLERANCE, ViewRows, board_tables, people_table
from synth.world import WORLD_CONVENTION

ProgressFn = Callable[[str, int, int], None]
MapFn = Callable[..., Sequence]  # map_fn(fn, items, description=...) -> results in item order
SCENE_FORMAT_VERSION = 1
CALIBRATION_FILES = (
    ("rig", "calibration/rig.json"),
    ("panoptic", "calibration/calibration_synth.json"),
    ("h36m", "calibration/cameras.h5"),
)


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RigSpec(_Spec):
    kind: Literal["dome", "h36m", "hall"] = "dome"
    n_cameras: int | None = Field(None, ge=1, le=256)
    width: int | None = Field(None, ge=16, le=8192)
    height: int | None = Field(None, ge=16, le=8192)
    fov_deg: float | None = Field(None, gt=5, lt=150)
    focal_mm: float | None = Field(None, gt=0)
    distortion: Literal["none", "mild", "strong"] | list[float] | None = None
    fps: float | None = Field(None, gt=0, le=1000)

    @model_validator(mode="after")
    def _one_focal(self):
        if self.fov_deg is not None and self.focal_mm is not None:
            raise ValueError("give rig.fov_deg or rig.focal_mm, not both")
        return self


class BoardClipSpec(_Spec):
    squares_x: int = Field(5, ge=3, le=40)
    squares_y: int = Field(4, ge=3, le=40)
    square_size: float = Field(0.3, gt=0, le=1.0)
    marker_size: float = Field(0.24, gt=0, le=1.0)
    dictionary: str = "DICT_4X4_50"
    margin: float = Field(0.06, ge=0, le=0.5)
    n_frames: int = Field(40, ge=0, le=100_000)

    def board(self) -> ChArUcoSpec:
        return ChArUcoSpec(
            self.squares_x,
            self.squares_y,
            self.square_size,
            self.marker_size,
            self.dictionary,
            self.margin,
        )


class ImagingSpec(_Spec):
    antialias: int = Field(2, ge=1, le=8)
    background_samples: int = Field(2, ge=1, le=8)
    shadow_samples: int = Field(4, ge=1, le=8)
    noise_sigma: float = Field(1.5, ge=0, le=50)
    blur_sigma: float = Field(0.5, ge=0, le=10)
    exposure_jitter: float = Field(0.1, ge=0, le=0.9)
    vignetting: float = Field(0.2, ge=0, lt=1)
    write_depth: bool = True
    backend: Literal["embree", "trimesh"] = "embree"


class SceneSpec(_Spec):
    """Everything that defines a synthetic capture. Validated; frozen."""

    name: str = "synth"
    seed: int = Field(0, ge=0)
    n_frames: int = Field(48, ge=1, le=1_000_000)
    n_people: int = Field(2, ge=1, le=255)
    motions: list[list[str]] | None = None  # per-person programmes; None = sampled
    # Where people are: "loop" (runners around the volume, in-place movers apart) or "crowd"
    # (people a few decimetres apart, walkers crossing them: synth.crowd).
    layout: Literal["loop", "crowd"] = "loop"
    rig: RigSpec = RigSpec()
    board: BoardClipSpec = BoardClipSpec()
    imaging: ImagingSpec = ImagingSpec()
    body_model: str = "anny"
    preview_frame: int | None = None  # frame of the contact sheet (default: middle)

    @field_validator("name")
    @classmethod
    def _safe_name(cls, v: str) -> str:
        if not v or any(c in v for c in "/\\\0") or v.startswith("."):
            raise ValueError(f"scene name {v!r} must be a plain file name")
        return v

    @model_validator(mode="after")
    def _consistent(self):
        if self.motions is not None and len(self.motions) != self.n_people:
            raise ValueError(
                f"motions has {len(self.motions)} programmes but n_people is {self.n_people}"
            )
        if self.preview_frame is not None and not 0 <= self.preview_frame < self.n_frames:
            raise ValueError(
                f"preview_frame {self.preview_frame} is outside 0..{self.n_frames - 1}"
            )
        if self.board.marker_size >= self.board.square_size:
            raise ValueError("board.marker_size must be smaller than board.square_size")
        return self


PRESETS: dict[str, dict] = {
    # Small enough to render in well under 2 minutes on 2 CPU cores, board clip included.
    "demo": dict(
        name="demo",
        n_frames=48,
        n_people=2,
        motions=[["run"], ["jump"]],
        rig=dict(kind="dome", n_cameras=6, width=480, height=360, distortion="mild", fps=30.0),
        board=dict(n_frames=40),
    ),
    # People who come within 0.5 m of each other, walkers crossing and hiding the others.
    "crowd": dict(
        name="crowd",
        n_frames=48,
        n_people=4,
        layout="crowd",
        rig=dict(kind="dome", n_cameras=7, width=480, height=360, distortion="mild", fps=30.0),
        board=dict(n_frames=40),
    ),
    "small": dict(
        name="small",
        n_frames=120,
        n_people=2,
        rig=dict(kind="dome", n_cameras=8, width=640, height=480, distortion="mild", fps=30.0),
        board=dict(n_frames=80),
    ),
    "full": dict(
        name="full",
        n_frames=300,
        n_people=4,
        rig=dict(kind="hall", n_cameras=8, width=1920, height=1080, distortion="mild"),
        board=dict(n_frames=200, squares_x=7, squares_y=5, square_size=0.2, marker_size=0.15),
        imaging=dict(antialias=3),
    ),
}


def _merge(base: dict, overrides: dict) -> dict:
    out = dict(base)
    for key, value in overrides.items():
        if "__" in key or "." in key:
            head, rest = key.replace(".", "__").split("__", 1)
            out[head] = _merge(dict(out.get(head) or {}), {rest: value})
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def preset(name: str, **overrides) -> SceneSpec:
    """A preset spec ('demo', 'crowd', 'small', 'full') with overrides. Nested fields take a dict
    (`rig={"width": 320}`) or a double-underscore key (`rig__width=320`)."""
    if name not in PRESETS:
        raise KeyError(f"unknown synth preset '{name}', expected one of {sorted(PRESETS)}")
    return SceneSpec.model_validate(_merge(PRESETS[name], overrides))


@dataclass(frozen=True)
class SceneSummary:
    """What `render_scene` produced. Built-in sanity checks: `joints_in_mask` is the fraction of
    in-image GT joints whose projection lands inside the GT mask (on a person),
    `joints_on_own_mask` on the joint's own person (lower when people occlude each other)."""

    out_dir: Path
    name: str
    n_frames: int
    n_board_frames: int
    fps: float
    cameras: tuple[str, ...]
    n_people: int
    joints_in_mask: float
    joints_on_own_mask: float
    seconds: float


def _load_body_model(name: str):
    try:
        from gst.body import load_body_model
    except ImportError as exc:
        raise ImportError(
            f"synth needs gst.body.load_body_model to load body model '{name}' "
            "(or pass body_model= to render_scene)"
        ) from exc
    return load_body_model(name)


def _default_rig_writer():
    try:
        from calibration.formats import write_rig
    except ImportError as exc:
        raise ImportError(
            "synth writes calibration files with calibration.formats.write_rig "
            "(or pass rig_writer= to render_scene)"
        ) from exc
    return write_rig


def _write_calibration(rig, out: Path, rig_writer: Callable) -> dict:
    """Write rig.json, Panoptic JSON and H36M cameras.h5. H36M's lens model has no exact
    equivalent of OpenCV's tangential terms; synth's own distortion is radial only, so all three
    files describe the same cameras exactly unless the user gave tangential coefficients (then the
    H36M file holds a least-squares fit, noted in the return value)."""
    notes = {}
    tangential = any(c.dist.size >= 4 and np.any(c.dist[2:4] != 0) for c in rig.cameras)
    for fmt, rel in CALIBRATION_FILES:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        if fmt == "h36m" and tangential:
            rig_writer(rig, out / rel, fmt, approximate_distortion=True)
            notes[fmt] = "tangential distortion fitted approximately in H36M's lens model"
        else:
            rig_writer(rig, out / rel, fmt)
        if not (out / rel).is_file():
            raise OSError(f"rig writer did not create {rel} (format '{fmt}')")
    return notes


def _camera_groups(rig, budget_bytes: float = 1.5e9) -> list[list[int]]:
    """Camera index groups whose render caches fit the memory budget together."""
    per_px = 64  # bytes of cached rays, room radiance, points and depth per pixel
    groups, cur, used = [], [], 0.0
    for i, cam in enumerate(rig.cameras):
        need = per_px * (cam.width + 1) * (cam.height + 1)
        if cur and used + need > budget_bytes:
            groups.append(cur)
            cur, used = [], 0.0
        cur.append(i)
        used += need
    if cur:
        groups.append(cur)
    return groups


def render_scene(
    spec: SceneSpec,
    out_dir: str | os.PathLike,
    progress: ProgressFn | None = None,
    body_model=None,
    rig_writer: Callable | None = None,
    map_fn: MapFn | None = None,
    shares: int | None = None,
) -> SceneSummary:
    """Render a complete synthetic capture for `spec` into `out_dir` (replaced atomically).

    `body_model` defaults to `gst.body.load_body_model(spec.body_model)`; `rig_writer(rig, path,
    fmt)` defaults to `calibration.formats.write_rig`.

    Cameras are rendered in shares (see synth.shares). With `map_fn(fn, items, description=...)`
    (an executor's `map`: ordered results, picklable items) the shares run as independent items,
    e.g. in worker processes; the files are byte-identical to a serial run. `shares` is how many
    items to aim for (give the executor's worker count); default: one per memory group.
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    report = progress or (lambda *_: None)
    model = body_model if body_model is not None else _load_body_model(spec.body_model)
    check_body_model(model)
    writer = rig_writer or _default_rig_writer()
    # Absolute: workers (Ray's in particular) do not run in the caller's working directory.
    staging = Path(os.path.abspath(out_dir)).with_name(f".{out_dir.name}.partial-{os.getpid()}")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    try:
        summary = _render_into(spec, staging, report, model, writer, map_fn, shares)
        replace_dir(staging, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return SceneSummary(out_dir=out_dir, seconds=time.perf_counter() - t0, **summary)


@dataclass
class _Progress:
    report: ProgressFn
    total: int
    done: int = 0

    def step(self, name: str, n: int = 1) -> None:
        self.done += n
        self.report(name, self.done, self.total)


def _pose_cast(
    spec: SceneSpec, model, rig, fps: float, report: ProgressFn
) -> tuple[list, list, Cast]:
    """(people specs, person tracks, the cast the renderer sees)."""
    faces = np.asarray(model.faces, dtype=np.int32)
    rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 1]))
    where = (rig.meta["volume_center"], rig.meta["volume_radius"], spec.n_frames, fps)
    if spec.layout == "crowd":
        people = sample_crowd(
            spec.n_people, rng, int(model.num_betas), *where, spec.seed, programmes=spec.motions
        )
    else:
        people = sample_people(
            spec.n_people, rng, int(model.num_betas), *where, programmes=spec.motions
        )
    tracks, members = [], []
    for k, person in enumerate(people):
        report("pose", k, len(people))
        track = pose_person(
            model, person.betas, person.motion_clip(spec.n_frames, fps, spec.seed), person.person_id
        )
        tracks.append(track)
        atlas = BodyAtlas.build(
            track.rest_vertices,
            track.rest_joints,
            getattr(model, "part_labels", None),
            getattr(model, "part_names", None),
        )
        members.append(
            CastMember(
                track.person_id,
                track.vertices,
                vertex_normals(track.vertices, faces),
                track.joints,
                atlas,
                person.outfit,
            )
        )
    report("pose", len(people), len(people))
    return people, tracks, Cast(members, faces)


def _render_shares(
    spec: SceneSpec,
    setup: SceneSetup,
    cast: Cast,
    shares: list[tuple[int, ...]],
    out: Path,
    progress: _Progress,
    map_fn: MapFn | None,
) -> list[ShareResult]:
    """Render every share, inline (with per-frame progress) or through `map_fn`."""
    if map_fn is None:
        return [render_share(spec, setup, cast, share, out, progress.step) for share in shares]
    cast_files = CastFiles.save(cast, out / ".cast")
    try:
        jobs = [CameraShareJob(spec, out, share, cast_files) for share in shares]
        results = list(map_fn(render_share_job, jobs, description=f"synth {spec.name}: render"))
    finally:
        shutil.rmtree(cast_files.folder, ignore_errors=True)
    if len(results) != len(jobs) or not all(isinstance(r, ShareResult) for r in results):
        raise RuntimeError(
            f"map_fn returned {len(results)} results of types {sorted({type(r).__name__ for r in results})} "
            f"for {len(jobs)} camera shares; expected one ShareResult per share, in order"
        )
    n_cams = sum(len(s) for s in shares)
    progress.step("render", n_cams * spec.n_frames)
    if setup.board_poses:
        progress.step("board", n_cams * len(setup.board_poses))
    return results


def _render_into(
    spec: SceneSpec,
    out: Path,
    report: ProgressFn,
    model,
    rig_writer,
    map_fn: MapFn | None,
    n_shares: int | None,
) -> dict:
    setup = SceneSetup.build(spec)
    rig, fps, stage, board_spec, texture, poses = (
        setup.rig,
        setup.fps,
        setup.stage,
        setup.board,
        setup.texture,
        setup.board_poses,
    )
    radii = setup.radii
    people, tracks, cast = _pose_cast(spec, model, rig, fps, report)
    # Camera caches of one memory group fit in memory together; shares split groups further.
    shares = camera_shares(_camera_groups(rig), n_shares)
    progress = _Progress(report, len(rig) * (spec.n_frames + spec.board.n_frames))
    preview, board_preview = {}, {}
    views, check = ViewRows(), JointCheck()
    for result in _render_shares(
        spec, setup, cast, shares, out, progress, map_fn
    ):  # in share (camera) order
        views.extend(result.views)
        check.merge(result.check)
        preview.update(result.preview)
        board_preview.update(result.board_preview)
    names = [c.name for c in rig.cameras]
    missing = [n for n in names if n not in preview or (poses and n not in board_preview)]
    if missing:
        raise RuntimeError(
            f"no rendered preview frame came back for camera(s) {missing}: a share was not rendered"
        )

    report("write", 0, 1)
    body_meta = {
        "name": spec.body_model,
        "num_betas": int(model.num_betas),
        "num_vertices": int(tracks[0].vertices.shape[1]),
        "num_faces": int(len(cast.faces)),
        "joint_names": list(JOINT_NAMES),
    }
    meta = {
        "scene": spec.name,
        "fps": fps,
        "units": "m",
        "world": WORLD_CONVENTION,
        "joint_names": list(JOINT_NAMES),
        "body_model": body_meta,
        "format_version": SCENE_FORMAT_VERSION,
    }
    write_parquet(out / "truth" / "people.parquet", people_table(tracks, meta))
    write_parquet(
        out / "truth" / "views.parquet",
        views.table(
            {
                **meta,
                "occlusion_tolerance_m": OCCLUSION_TOLERANCE,
                "pixel_convention": "OpenCV, pixel centres at integers",
            }
        ),
    )
    if poses:
        bp, bv = board_tables(
            board_spec, poses, list(rig.cameras), radii, {"board": board_json(board_spec)}
        )
        write_parquet(out / "truth" / "board_poses.parquet", bp)
        write_parquet(out / "truth" / "board_views.parquet", bv)
        write_png(
            out / "preview" / "board_sheet.png",
            contact_sheet([board_preview[n] for n in names], names),
        )
    write_json(out / "board.json", board_json(board_spec))
    calibration_notes = _write_calibration(rig, out, rig_writer)
    preview_f = spec.preview_frame if spec.preview_frame is not None else spec.n_frames // 2
    write_png(
        out / "preview" / "contact_sheet.png", contact_sheet([preview[n] for n in names], names)
    )
    write_png(
        out / "preview" / "truth_overlay.png",
        truth_overlay([preview[n] for n in names], list(rig.cameras), tracks, preview_f),
    )
    scene = {
        "format": "synth-scene",
        "format_version": SCENE_FORMAT_VERSION,
        "name": spec.name,
        "spec": spec.model_dump(mode="json"),
        "fps": fps,
        "n_frames": spec.n_frames,
        "n_board_frames": spec.board.n_frames,
        "cameras": names,
        "image_size": {n: [c.width, c.height] for n, c in zip(names, rig.cameras, strict=True)},
        "volume": {"center": rig.meta["volume_center"], "radius": rig.meta["volume_radius"]},
        "world": WORLD_CONVENTION,
        "stage": stage.to_dict(),
        "body_model": body_meta,
        "people": [p.to_dict() for p in people],
        "board": board_json(board_spec),
        "board_margin_m": float(texture.margin),
        "preview_frame": preview_f,
        "calibration_notes": calibration_notes,
        "files": {
            "videos": "videos/<camera>.mp4",
            "board_videos": "board/<camera>.mp4",
            "board": "board.json",
            "calibration": {fmt: rel for fmt, rel in CALIBRATION_FILES},
            "people": "truth/people.parquet",
            "views": "truth/views.parquet",
            "masks": "truth/masks/<camera>.h5",
            "board_poses": "truth/board_poses.parquet",
            "board_views": "truth/board_views.parquet",
            "contact_sheet": "preview/contact_sheet.png",
        },
    }
    write_json(out / "scene.json", scene)
    report("write", 1, 1)
    on_person, on_own = check.fractions()
    return dict(
        name=spec.name,
        n_frames=spec.n_frames,
        n_board_frames=spec.board.n_frames,
        fps=fps,
        cameras=tuple(names),
        n_people=len(people),
        joints_in_mask=on_person,
        joints_on_own_mask=on_own,
    )


def scene_cameras(scene_dir: str | os.PathLike) -> Sequence[str]:
    """Camera names of a rendered scene (from scene.json)."""
    path = Path(scene_dir) / "scene.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: not a synth scene folder")
    return json.loads(path.read_text())["cameras"]
