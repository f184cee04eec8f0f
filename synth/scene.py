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

import functools
import json
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gst.atomic import atomic_dir
from synth.animate import check_body_model, pose_person
from synth.appearance import BodyAtlas
from synth.board import board_json
from synth.io import write_json, write_png
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
from synth.spec import PRESETS, SceneSpec, preset  # noqa: F401  (re-exported)
from synth.truth import (
    BOARD_POSES_FILE,
    BOARD_VIEWS_FILE,
    PEOPLE_FILE,
    VIEWS_FILE,
    ViewRows,
    board_tables,
    write_board_truth,
    write_truth_tables,
)
from synth.world import WORLD_CONVENTION

ProgressFn = Callable[[str, int, int], None]
MapFn = Callable[..., Sequence]  # map_fn(fn, items, description=...) -> results in item order
SCENE_FORMAT_VERSION = 1
CALIBRATION_FILES = (
    ("rig", "calibration/rig.json"),
    ("panoptic", "calibration/calibration_synth.json"),
    ("h36m", "calibration/cameras.h5"),
)


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
    # the scene's z-up world in its Panoptic file is documented (docs/formats/synth_scene.md);
    # the warning came once per pretraining world, about the project's own scratch files
    return functools.partial(write_rig, warn_up=False)


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
    _check_replaceable(out_dir)
    report = progress or (lambda *_: None)
    model = body_model if body_model is not None else _load_body_model(spec.body_model)
    check_body_model(model)
    writer = rig_writer or _default_rig_writer()
    # Absolute: workers (Ray's in particular) do not run in the caller's working directory.
    with atomic_dir(Path(os.path.abspath(out_dir))) as staging:
        summary = _render_into(spec, staging, report, model, writer, map_fn, shares)
    return SceneSummary(out_dir=out_dir, seconds=time.perf_counter() - t0, **summary)


def _check_replaceable(out_dir: Path) -> None:
    """Refuse to replace a folder that holds anything but a synthetic scene: the render swaps
    `out_dir` out whole, and a workspace named there (`render_scene(spec, "workspace/demo")`,
    once the package's own example) lost its models, tracks and calibration."""
    if out_dir.is_symlink() or (out_dir.exists() and not out_dir.is_dir()):
        raise ValueError(
            f"{out_dir}: is a file or a link, not a folder; the render replaces its output "
            "folder whole, so give an empty or new folder"
        )
    if not out_dir.is_dir() or not any(out_dir.iterdir()):
        return
    try:
        fmt = json.loads((out_dir / "scene.json").read_text()).get("format")
    except (OSError, ValueError, AttributeError):
        fmt = None
    if fmt != "synth-scene":
        raise ValueError(
            f"{out_dir}: holds files that are not a synthetic scene (no scene.json of format "
            "'synth-scene'); the render replaces its output folder whole, so give an empty or "
            "new folder, or an earlier scene's"
        )


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
            f"map_fn returned {len(results)} results of types "
            f"{sorted({type(r).__name__ for r in results})} for {len(jobs)} camera shares; "
            "expected one ShareResult per share, in order"
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
    write_truth_tables(out, tracks, views, meta)
    if poses:
        bp, bv = board_tables(
            board_spec, poses, list(rig.cameras), radii, {"board": board_json(board_spec)}, stage
        )
        write_board_truth(out, bp, bv)
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
            "board": "board.json",
            "calibration": {fmt: rel for fmt, rel in CALIBRATION_FILES},
            "people": PEOPLE_FILE,
            "views": VIEWS_FILE,
            "masks": "truth/masks/<camera>.h5",
            "contact_sheet": "preview/contact_sheet.png",
        },
    }
    if poses:  # a scene without a board clip (board.n_frames 0) has none of these
        scene["files"].update(
            board_videos="board/<camera>.mp4",
            board_poses=BOARD_POSES_FILE,
            board_views=BOARD_VIEWS_FILE,
        )
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
