"""BlazePose detections on rendered synthetic crops, with exact truth: the landmark-world dataset.

Small synthetic worlds (seeds 5000.., rigs cycled over dome / h36m / hall, field of view drawn
per world, two people, every fourth world independent random poses) are rendered with
`synth.scene`, cut into crops with `gst.train.synthetic_crops.crops_from_synth_scene` (the
extraction convention: square box, undistorted, own K), and the BlazePose landmark model looks
at every crop as one region of interest (the whole crop, as `gst.train.keypoints` does). One
`.npz` per world keeps the detections beside the truth; the format is documented in
`/work/data/landmark_worlds/README.md` (written by `write_readme`). The noise model
(`gst.lift.noise`) and the virtual markers (`gst.body.markers`) are fitted on it.

Regenerate (about 1.5-3 min per world on 2 cores):

    python -m gst.lift.dataset --out /work/data/landmark_worlds --worlds 8
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from gst.atomic import atomic_save_npz, atomic_write_text
from gst.detect.blazepose import BlazePose
from gst.detect.crops import detect_crop_landmarks
from gst.train.synthetic_crops import crops_from_synth_scene
from synth.truth import read_scene_truth

DEFAULT_SEED = 5000
WORLD_RIGS = ("dome", "h36m", "hall")
FORMAT_VERSION = 1


@dataclass(frozen=True)
class LandmarkWorld:
    """Detections and truth of every crop of one world (N crops). See README for units."""

    frame: np.ndarray  # (N,) int32
    person: np.ndarray  # (N,) int16, person id in the scene
    camera: np.ndarray  # (N,) int16, index into camera_names
    camera_names: np.ndarray  # (C,) str
    K_crop: np.ndarray  # (N, 3, 3) float32, crop intrinsics (pixel centres at integers)
    R: np.ndarray  # (N, 3, 3) float32, world -> camera
    t: np.ndarray  # (N, 3) float32
    landmarks: np.ndarray  # (N, 33, 3) float32: u, v crop px, visibility in [0, 1]
    presence: np.ndarray  # (N,) float32
    world_landmarks: np.ndarray  # (N, 33, 3) float32, metres, mid-hip origin, crop axes
    joints_world: np.ndarray  # (N, 24, 3) float32, metres, world frame
    joints2d: np.ndarray  # (N, 24, 2) float32, crop px (projection of joints_world)
    visible: np.ndarray  # (N, 24) bool
    global_orient: np.ndarray  # (N, 3) float32 axis-angle, model axes -> world
    body_pose: np.ndarray  # (N, 23, 3) float32 axis-angle
    betas: np.ndarray  # (N, B) float32
    transl: np.ndarray  # (N, 3) float32, metres
    crop_size: int
    seed: int
    rig_kind: str
    fov_deg: float
    motion: np.ndarray | None = None  # (N,) str, the motion playing ('random_static': random poses)

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    def save(self, path: str | Path) -> None:
        arrays = {
            f.name: np.asarray(getattr(self, f.name))
            for f in fields(self)
            if getattr(self, f.name) is not None
        }
        arrays["format_version"] = np.asarray(FORMAT_VERSION)
        atomic_save_npz(path, compressed=True, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> LandmarkWorld:
        with np.load(path, allow_pickle=False) as z:
            version = int(z["format_version"]) if "format_version" in z else -1
            if version != FORMAT_VERSION:
                raise ValueError(
                    f"{path}: landmark world format {version}, expected {FORMAT_VERSION}"
                )
            kw = {}
            for f in fields(cls):
                if f.name == "motion" and f.name not in z:  # written before the field existed
                    continue
                if f.name not in z:
                    raise ValueError(f"{path}: key '{f.name}' missing")
                v = z[f.name]
                kw[f.name] = v.item() if v.ndim == 0 else v
        kw["crop_size"], kw["seed"] = int(kw["crop_size"]), int(kw["seed"])
        kw["rig_kind"], kw["fov_deg"] = str(kw["rig_kind"]), float(kw["fov_deg"])
        return cls(**kw)


def load_worlds(root: str | Path) -> list[LandmarkWorld]:
    """Every `world_*.npz` under `root`, sorted by name."""
    paths = sorted(Path(root).glob("world_*.npz"))
    if not paths:
        raise FileNotFoundError(f"no world_*.npz under {root} (python -m gst.lift.dataset)")
    return [LandmarkWorld.load(p) for p in paths]


def named_worlds(items: list[str]) -> dict[str, LandmarkWorld]:
    """Command-line `NAME=world.npz` items -> the loaded worlds by name (a clear exit on a
    malformed item)."""
    worlds = {}
    for item in items:
        name, _, path = item.partition("=")
        if not path:
            raise SystemExit(f"--val expects NAME=PATH, got {item!r}")
        worlds[name] = LandmarkWorld.load(path)
    return worlds


def world_spec(
    k: int,
    seed0: int = DEFAULT_SEED,
    n_frames: int = 40,
    fps: float = 10.0,
    rigs: tuple[str, ...] = WORLD_RIGS,
):
    """The k-th world's scene spec (deterministic from its seed)."""
    from synth.scene import preset

    seed = seed0 + k
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x1F7]))
    static = k % 4 == 3
    spec = preset(
        "demo",
        seed=seed,
        n_frames=n_frames,
        n_people=2,
        motions=[["random_static"]] * 2 if static else None,
        rig={
            "kind": rigs[k % len(rigs)],
            "n_cameras": 6,
            "width": 480,
            "height": 360,
            "fps": fps,
            "fov_deg": float(rng.uniform(40.0, 75.0)),
        },
        board={"n_frames": 1},
    )
    return spec.model_copy(update={"name": f"world_{seed}"})


def _people_columns(scene_dir: Path) -> tuple[dict[tuple[int, int], int], dict[str, np.ndarray]]:
    truth = read_scene_truth(scene_dir)
    cols = {
        "global_orient": truth.global_orient,
        "body_pose": truth.body_pose.reshape(len(truth), -1),
        "betas": truth.betas,
        "transl": truth.transl,
        "motion": np.asarray([str(m) for m in truth.motion]),
    }
    return truth.row_index(), cols


def detect_crops(
    images: np.ndarray | torch.Tensor, model: BlazePose
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BlazePose on (N, S, S, 3) uint8 RGB crops (`gst.detect.crops`): landmarks (N, 33, 3)
    crop px + visibility, world landmarks (N, 33, 3), presence (N,)."""
    found = detect_crop_landmarks(np.asarray(images), model, rgb=True)
    return found.landmarks, found.world, found.presence


def detect_world(
    scene_dir: str | Path, model: BlazePose, crop_size: int = 256, seed: int = -1
) -> LandmarkWorld:
    """Crops of a rendered scene, BlazePose on each (whole crop as the region), and the truth."""
    scene_dir = Path(scene_dir)
    crops = crops_from_synth_scene(scene_dir, crop_size=crop_size)
    lms, world, presence = detect_crops(crops.images.numpy(), model)
    index, cols = _people_columns(scene_dir)
    rows = np.array(
        [index[(int(f), int(p))] for f, p in zip(crops.frame, crops.person, strict=True)]
    )
    spec = json.loads((scene_dir / "scene.json").read_text())["spec"]
    return _world(crops, rows, cols, lms, world, presence, spec, crop_size, seed)


def world_from_crop_store(
    store_path: str | Path, scene_dir: str | Path, model: BlazePose
) -> LandmarkWorld:
    """An extracted crop store (`crops.h5`) of a synthetic scene: its crops matched to the
    truth (`gst.train.scene_truth.attach_scene_truth`; unmatched crops are dropped) and
    BlazePose on each, as one LandmarkWorld (e.g. the demo's crops, to score single-image
    pose exactly on what training and tracking see)."""
    from gst.train.scene_truth import attach_scene_truth, select_rows
    from gst.train.views import load_cropset

    scene_dir = Path(scene_dir)
    crops, boxes = load_cropset(store_path)
    truth = attach_scene_truth(crops, boxes, scene_dir)
    keep = torch.nonzero(crops.truth["has_truth"])[:, 0]
    if len(keep) == 0:
        raise ValueError(f"{store_path}: no crop matches a person of {scene_dir}")
    crops = select_rows(crops, keep)
    lms, world, presence = detect_crops(crops.images.numpy(), model)
    rows = crops.truth["truth_row"].numpy()
    cols = {
        "global_orient": truth.global_orient,
        "body_pose": truth.body_pose.reshape(len(truth), -1),
        "betas": truth.betas,
        "transl": truth.transl,
        "motion": np.asarray(truth.motion),
    }
    spec = json.loads((scene_dir / "scene.json").read_text())["spec"]
    return _world(crops, rows, cols, lms, world, presence, spec, crops.crop_size, -1)


def _world(crops, rows, cols, lms, world, presence, spec, crop_size, seed) -> LandmarkWorld:
    tr = crops.truth
    return LandmarkWorld(
        frame=crops.frame.numpy().astype(np.int32),
        person=crops.person.numpy().astype(np.int16),
        camera=crops.camera.numpy().astype(np.int16),
        camera_names=np.asarray(crops.camera_names),
        K_crop=crops.K.numpy().astype(np.float32),
        R=crops.R.numpy().astype(np.float32),
        t=crops.t.numpy().astype(np.float32),
        landmarks=lms,
        presence=presence,
        world_landmarks=world,
        joints_world=tr["joints_world"].numpy().astype(np.float32),
        joints2d=tr["joints2d"].numpy().astype(np.float32),
        visible=tr["visible"].numpy().astype(bool),
        global_orient=cols["global_orient"][rows],
        body_pose=cols["body_pose"][rows].reshape(-1, 23, 3),
        betas=cols["betas"][rows],
        transl=cols["transl"][rows],
        motion=np.asarray(cols["motion"][rows]).astype(str),  # never object arrays (no pickle)
        crop_size=crop_size,
        seed=int(spec["seed"]) if seed < 0 else seed,
        rig_kind=str(spec["rig"]["kind"]),
        fov_deg=float(spec["rig"]["fov_deg"] or float("nan")),
    )


README = """# Landmark worlds: BlazePose on rendered synthetic crops, with exact truth

Built by `python -m gst.lift.dataset --out {root} --worlds {n}` (branch `lift`, module
`gst/lift/dataset.py`). Seeds {seed0}..{seed_last}; the rendered scenes are kept under
`scenes/world_<seed>/` (layout: docs/formats/synth_scene.md), one `world_<seed>.npz` per world.

Worlds: `synth.scene.preset("demo", seed=s, n_frames=40, n_people=2)` with the rig kind cycled
over dome / h36m / hall (6 cameras, 480x360, mild distortion, 10 fps so frames are not
near-duplicates), the horizontal field of view drawn in 40-75 degrees per world, and every fourth
world (k % 4 == 3) holding independent random poses (`random_static`) instead of motions.
Crops: `gst.train.synthetic_crops.crops_from_synth_scene(scene, crop_size=256)` (square HMR2
box around the truth mask, undistorted; filters: mask area >= 200 px, >= 8 visible joints).
Detections: `gst.detect.blazepose.BlazePose().segment(crop_bgr, roi)` with the whole crop as the
region (centre (127.5, 127.5), side 256, angle 0), as `gst.detect.crops.detect_crop_landmarks` does.

| world | rig | fov (deg) | crops |
|---|---|---|---|
{table}

## Fields of `world_<seed>.npz` (N crops; load with `gst.lift.dataset.LandmarkWorld.load`)

| key | shape, dtype | meaning |
|---|---|---|
| `frame` | (N,) int32 | frame index in the scene |
| `person` | (N,) int16 | person id (1..2, the value in the scene's masks) |
| `camera` | (N,) int16 | index into `camera_names` |
| `camera_names` | (C,) str | the scene's camera names |
| `K_crop` | (N, 3, 3) float32 | crop intrinsics; with `R`, `t` and zero distortion it describes \
the crop exactly (pixel centres at integers) |
| `R`, `t` | (N, 3, 3), (N, 3) float32 | world -> camera (OpenCV, `X_cam = R X + t`), metres |
| `landmarks` | (N, 33, 3) float32 | BlazePose landmarks (MediaPipe order): u, v in crop pixels, \
visibility in [0, 1] (sigmoid of the model's logit) |
| `presence` | (N,) float32 | the landmark model's person presence score in [0, 1]; the \
per-landmark confidence of the project's convention is `visibility * presence` |
| `world_landmarks` | (N, 33, 3) float32 | the model's (1, 117) output = 39 x 3, first 33: \
metres, origin at the mid-point of the hips (landmarks 23, 24), axes of the region = the crop's \
camera axes (x right, y down, z away from the camera); measured in docs/landmark_prior.md |
| `joints_world` | (N, 24, 3) float32 | true SMPL-layout joints, world frame, metres (Z up) |
| `joints2d` | (N, 24, 2) float32 | their projection with `K_crop`, `R`, `t`, crop pixels |
| `visible` | (N, 24) bool | truth visibility in the camera (in the image, on the person's own \
mask, not occluded by anything more than 0.25 m in front; docs/formats/synth_scene.md) |
| `global_orient` | (N, 3) float32 | axis-angle, body-model (SMPL) axes -> world, as in \
`truth/people.parquet` |
| `body_pose` | (N, 23, 3) float32 | axis-angle local rotations (the body model's parameters) |
| `betas` | (N, B) float32 | shape coefficients of the body model that rendered the scene (`anny`) |
| `transl` | (N, 3) float32 | world translation, metres |
| `motion` | (N,) str | the motion playing (`run`, `jump`, ...; `random_static` = independent \
random poses, where BlazePose is much worse: docs/landmark_prior.md) |
| `crop_size`, `seed`, `rig_kind`, `fov_deg`, `format_version` | scalars | |

`gst.body.load_body_model("anny")(betas, body_pose, global_orient, transl)` reproduces
`joints_world` (float32 precision). The body joint <-> landmark correspondence used until the
virtual markers exist is `gst.train.keypoints.BODY_FROM_BLAZEPOSE`.
"""


def write_readme(root: Path, worlds: list[LandmarkWorld]) -> None:
    table = "\n".join(
        f"| world_{w.seed} | {w.rig_kind} | {w.fov_deg:.1f} | {len(w)} |" for w in worlds
    )
    seeds = [w.seed for w in worlds]
    text = README.format(
        root=root, n=len(worlds), seed0=min(seeds), seed_last=max(seeds), table=table
    )
    atomic_write_text(root / "README.md", text)


def build(
    root: Path,
    n_worlds: int,
    seed0: int = DEFAULT_SEED,
    log=print,
    rigs: tuple[str, ...] = WORLD_RIGS,
) -> list[LandmarkWorld]:
    """Render, crop and detect each world (skipping those already done), then the README."""
    from gst.body import load_body_model
    from synth.scene import render_scene

    root.mkdir(parents=True, exist_ok=True)
    body = None
    model = BlazePose(threads=1)
    worlds = []
    for k in range(n_worlds):
        spec = world_spec(k, seed0, rigs=rigs)
        npz = root / f"world_{spec.seed}.npz"
        if npz.is_file():
            w = LandmarkWorld.load(npz)
            if w.motion is None:  # an older file: add the motion column from the scene's truth
                scene = root / "scenes" / f"world_{spec.seed}"
                index, cols = _people_columns(scene)
                rows = [index[(int(f), int(p))] for f, p in zip(w.frame, w.person, strict=True)]
                w = dataclasses.replace(w, motion=cols["motion"][rows])
                w.save(npz)
            worlds.append(w)
            continue
        scene = root / "scenes" / f"world_{spec.seed}"
        t0 = time.perf_counter()
        if not (scene / "scene.json").is_file():
            body = body or load_body_model(spec.body_model)
            render_scene(spec, scene, body_model=body)
        t1 = time.perf_counter()
        w = detect_world(scene, model, seed=spec.seed)
        w.save(npz)
        worlds.append(w)
        log(
            f"world_{spec.seed} ({spec.rig.kind}): {len(w)} crops, render {t1 - t0:.0f} s, "
            f"crops + detection {time.perf_counter() - t1:.0f} s"
        )
    write_readme(root, worlds)
    return worlds


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--worlds", type=int, default=8)
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--rigs", nargs="+", default=list(WORLD_RIGS), choices=WORLD_RIGS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    build(args.out, args.worlds, args.seed, rigs=tuple(args.rigs))


if __name__ == "__main__":
    main()
