"""Camera shares: the unit in which `render_scene` renders, serially or fanned out to workers.

A share is a set of cameras of one scene. Rendering a share writes its cameras' people videos,
truth masks and board videos into the scene's staging folder and returns its view-truth rows,
joint-check counts and preview frames; the caller merges those in camera order. Every random
stream is seeded per camera and frame, so how cameras are split into shares changes no byte.

For workers a share is plain data (`CameraShareJob`): the spec, the staging folder, camera indices
and a `CastFiles` reference. The posed people are posed once by the caller and shared as .npy
files in the staging folder (memory-mapped by workers), so workers never load the body model and
render exactly the caller's geometry. Workers therefore need the staging folder on a filesystem
they share with the caller (always true for local processes and a local Ray cluster).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from synth.appearance import BodyAtlas, Outfit
from synth.board import BoardPose, BoardTexture, ChArUcoSpec, board_clip
from synth.imaging import CameraResponse, develop
from synth.io import MaskStore, VideoOut
from synth.projection import field_radius, project_in_view
from synth.render import PosedPerson, RayCaster, RenderOptions, ViewRenderer, floor_shadow_maps
from synth.rigs import make_rig
from synth.spec import SceneSpec
from synth.stage import Stage, stage_for_rig
from synth.truth import ViewRows

StepFn = Callable[[str, int], None]  # (step name, camera-frames just finished)
CAST_FIELDS = ("vertices", "normals", "joints")


@dataclass(frozen=True)
class SceneSetup:
    """Everything besides the people that rendering needs, rebuilt identically from the spec."""

    rig: Any
    fps: float
    stage: Stage
    board: ChArUcoSpec
    texture: BoardTexture
    board_poses: list[BoardPose]
    options: RenderOptions
    responses: list[CameraResponse]
    radii: dict[str, float]

    @classmethod
    def build(cls, spec: SceneSpec) -> SceneSetup:
        rig = make_rig(**spec.rig.model_dump(), seed=spec.seed)
        board = spec.board.board()
        poses = board_clip(
            board,
            spec.board.n_frames,
            rig.meta["volume_center"],
            rig.meta["volume_radius"],
            np.random.default_rng(np.random.SeedSequence([spec.seed, 3])),
            camera_centers=np.stack([c.center for c in rig.cameras]),
        )
        im = spec.imaging
        options = RenderOptions(
            antialias=im.antialias,
            background_samples=im.background_samples,
            shadow_samples=im.shadow_samples,
            backend=im.backend,
        )
        return cls(
            rig=rig,
            fps=float(rig.meta["fps"]),
            stage=stage_for_rig(spec.rig.kind, spec.seed),
            board=board,
            texture=board.texture(),
            board_poses=poses,
            options=options,
            responses=_responses(spec, len(rig)),
            radii={cam.name: field_radius(cam) for cam in rig.cameras},
        )


def _responses(spec: SceneSpec, n: int) -> list[CameraResponse]:
    out = []
    for i in range(n):
        rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 4, i]))
        j = spec.imaging.exposure_jitter
        out.append(
            CameraResponse(
                exposure=float(np.exp(rng.uniform(-j, j))),
                vignetting=spec.imaging.vignetting,
                blur_sigma=spec.imaging.blur_sigma,
                noise_sigma=spec.imaging.noise_sigma,
            )
        )
    return out


@dataclass(frozen=True)
class CastMember:
    """One posed person as the renderer and the view truth need it."""

    person_id: int
    vertices: np.ndarray  # (T, V, 3) world
    normals: np.ndarray  # (T, V, 3) float32, unit
    joints: np.ndarray  # (T, 24, 3) world
    atlas: BodyAtlas
    outfit: Outfit


@dataclass(frozen=True)
class Cast:
    """The posed people of a scene."""

    members: list[CastMember]
    faces: np.ndarray  # (F, 3) int32

    def posed(self, frame: int) -> list[PosedPerson]:
        return [
            PosedPerson(
                m.person_id, m.vertices[frame], m.normals[frame], self.faces, m.atlas, m.outfit
            )
            for m in self.members
        ]


@dataclass(frozen=True)
class CastFiles:
    """Where a saved cast lives: per-person arrays as .npy in `folder`, small fields inline."""

    folder: Path
    people: tuple[tuple[int, BodyAtlas, Outfit], ...]

    @classmethod
    def save(cls, cast: Cast, folder: Path) -> CastFiles:
        folder.mkdir(parents=True, exist_ok=True)
        np.save(folder / "faces.npy", cast.faces)
        for k, m in enumerate(cast.members):
            for name in CAST_FIELDS:
                np.save(folder / f"{k}_{name}.npy", getattr(m, name))
        return cls(folder, tuple((m.person_id, m.atlas, m.outfit) for m in cast.members))

    def load(self) -> Cast:
        """The cast, its per-frame arrays memory-mapped (no pickles: allow_pickle=False)."""

        def arr(name: str, mmap: bool = True) -> np.ndarray:
            path = self.folder / f"{name}.npy"
            if not path.is_file():
                raise FileNotFoundError(
                    f"{path} is missing: the cast files of this render were removed, or the "
                    "worker does not share the scene's staging folder with the caller"
                )
            return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)

        members = [
            CastMember(pid, *(arr(f"{k}_{name}") for name in CAST_FIELDS), atlas, outfit)
            for k, (pid, atlas, outfit) in enumerate(self.people)
        ]
        return Cast(members, arr("faces", mmap=False))


@dataclass
class JointCheck:
    """Counts in-image GT joints landing on a person's mask and on their own person's mask."""

    in_image: int = 0
    on_person: int = 0
    on_own: int = 0

    def add(
        self, camera, radius: float, members: Sequence[CastMember], frame: int, mask: np.ndarray
    ) -> None:
        for m in members:
            uv, inside = project_in_view(camera, m.joints[frame], radius)
            px = np.rint(uv[inside]).astype(int)
            hit = mask[px[:, 1], px[:, 0]]
            self.in_image += int(inside.sum())
            self.on_own += int((hit == m.person_id).sum())
            self.on_person += int((hit > 0).sum())

    def merge(self, other: JointCheck) -> None:
        self.in_image += other.in_image
        self.on_person += other.on_person
        self.on_own += other.on_own

    def fractions(self) -> tuple[float, float]:
        if not self.in_image:
            return float("nan"), float("nan")
        return self.on_person / self.in_image, self.on_own / self.in_image


@dataclass
class ShareResult:
    """What a share returns: view-truth rows, joint-check counts, preview frames by camera name."""

    views: ViewRows = field(default_factory=ViewRows)
    check: JointCheck = field(default_factory=JointCheck)
    preview: dict[str, np.ndarray] = field(default_factory=dict)
    board_preview: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class CameraShareJob:
    """A picklable share for a worker: render cameras `cameras` of `spec` into `out_dir`."""

    spec: SceneSpec
    out_dir: Path
    cameras: tuple[int, ...]
    cast: CastFiles


def camera_shares(groups: Sequence[Sequence[int]], n_shares: int | None) -> list[tuple[int, ...]]:
    """Split memory groups (see scene._camera_groups) into about `n_shares` shares of equal size,
    consecutive cameras each, never across groups (None: one share per group).

    Every share rebuilds the per-frame Embree scene and floor shadows (about a tenth of the demo's
    render time), so more shares than workers only adds work."""
    if n_shares is not None and n_shares < 1:
        raise ValueError(f"n_shares must be >= 1, got {n_shares}")
    total = sum(len(g) for g in groups)
    size = None if n_shares is None else max(1, -(-total // n_shares))  # ceil
    out = []
    for g in groups:
        step = len(g) if size is None else size
        out.extend(tuple(g[i : i + step]) for i in range(0, len(g), step))
    return out


def render_share_job(job: CameraShareJob) -> ShareResult:
    """Worker entry point: rebuild the setup from the spec, map the cast, render the share."""
    return render_share(
        job.spec, SceneSetup.build(job.spec), job.cast.load(), job.cameras, job.out_dir
    )


def render_share(
    spec: SceneSpec,
    setup: SceneSetup,
    cast: Cast,
    cameras: Sequence[int],
    out: Path,
    step: StepFn | None = None,
) -> ShareResult:
    """Render people and board clips of `cameras` into `out`; `step(name, n)` after each frame."""
    step = step or (lambda *_: None)
    renderers = [ViewRenderer(setup.rig.cameras[i], setup.stage, setup.options) for i in cameras]
    result = ShareResult()
    _render_people_clip(spec, setup, out, cast, cameras, renderers, result, step)
    if setup.board_poses:
        _render_board_clip(spec, setup, out, cameras, renderers, result, step)
    return result


def _render_people_clip(
    spec: SceneSpec,
    setup: SceneSetup,
    out: Path,
    cast: Cast,
    cameras: Sequence[int],
    renderers: list[ViewRenderer],
    result: ShareResult,
    step: StepFn,
) -> None:
    """videos/<cam>.mp4 and truth/masks/<cam>.h5 for the share's cameras, plus view truth."""
    preview_f = spec.preview_frame if spec.preview_frame is not None else spec.n_frames // 2
    cams = [r.camera for r in renderers]
    videos = [
        VideoOut(out / "videos" / f"{c.name}.mp4", setup.fps, c.width, c.height) for c in cams
    ]
    masks = [
        MaskStore(
            out / "truth" / "masks" / f"{c.name}.h5",
            spec.n_frames,
            c.width,
            c.height,
            c.name,
            spec.imaging.write_depth,
        )
        for c in cams
    ]
    try:
        for f in range(spec.n_frames):
            posed = cast.posed(f)
            # One Embree scene and one set of floor shadows per frame, shared by the share's
            # cameras.
            caster = RayCaster([(p.vertices, p.faces) for p in posed], spec.imaging.backend)
            shadows = floor_shadow_maps(posed, caster, setup.stage, spec.imaging.shadow_samples)
            for ci, (cam_i, rend) in enumerate(zip(cameras, renderers, strict=True)):
                layers = rend.render_people(posed, caster, shadows)
                rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 5, cam_i, f, 0]))
                image = develop(layers.radiance, setup.responses[cam_i], rng)
                videos[ci].write(image)
                masks[ci].write(f, layers.mask, layers.depth)
                radius = setup.radii[rend.camera.name]
                result.views.add(rend.camera, radius, f, cast.members, layers.mask, layers.depth)
                result.check.add(rend.camera, radius, cast.members, f, layers.mask)
                if f == preview_f:
                    result.preview[rend.camera.name] = image
            step("render", len(renderers))
    except BaseException:
        for sink in videos + masks:
            sink.abort()
        raise
    for sink in videos + masks:
        sink.close()


def _render_board_clip(
    spec: SceneSpec,
    setup: SceneSetup,
    out: Path,
    cameras: Sequence[int],
    renderers: list[ViewRenderer],
    result: ShareResult,
    step: StepFn,
) -> None:
    """board/<cam>.mp4 for the share's cameras."""
    poses = setup.board_poses
    videos = [
        VideoOut(out / "board" / f"{r.camera.name}.mp4", setup.fps, r.camera.width, r.camera.height)
        for r in renderers
    ]
    try:
        for f, pose in enumerate(poses):
            for ci, (cam_i, rend) in enumerate(zip(cameras, renderers, strict=True)):
                layers = rend.render_board(setup.board, pose, setup.texture)
                rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 5, cam_i, f, 1]))
                image = develop(layers.radiance, setup.responses[cam_i], rng)
                videos[ci].write(image)
                if f == len(poses) // 2:
                    result.board_preview[rend.camera.name] = image
            step("board", len(renderers))
    except BaseException:
        for v in videos:
            v.abort()
        raise
    for v in videos:
        v.close()
