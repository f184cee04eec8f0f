"""BlazePose detections on rendered synthetic crops, with the truth body of every crop.

The data the virtual-marker model (gst.body.markers) is fitted on: a synthetic world is
rendered (`synth.scene`, tuning seeds 5000+ only, never the demo seed 0 or reporting seeds),
every truth person box is cropped (HMR2 square, undistorted, own K: the extraction's
convention) and BlazePose runs on each crop exactly as `gst.fuse.observations.crop_landmarks`
does on extracted crops (`detect_crop_landmarks(refine=True)`: whole crop, then the alignment
region and its mirror).

    python -m gst.fuse.marker_data --seed 5000 --out /work/data/fuse/worlds
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gst.fuse.observations import N_LANDMARKS
from synth.truth import has_scene_truth, read_scene_truth

__all__ = ["MarkerData", "detect_world", "load_marker_data"]


@dataclass
class MarkerData:
    """One row per (frame, truth person, camera) crop."""

    landmarks: np.ndarray  # (N, 33, 3) crop px + confidence
    K: np.ndarray  # (N, 3, 3) crop intrinsics
    R: np.ndarray  # (N, 3, 3)
    t: np.ndarray  # (N, 3)
    px_scale: np.ndarray  # (N,) crop px -> full-image px
    frame: np.ndarray  # (N,)
    person: np.ndarray  # (N,) truth person id
    camera: np.ndarray  # (N,)
    world: np.ndarray  # (N,) world (seed) id
    betas: np.ndarray  # (N, nb)
    global_orient: np.ndarray  # (N, 3) axis-angle, body -> world
    body_pose: np.ndarray  # (N, 23, 3)
    transl: np.ndarray  # (N, 3)

    def save(self, path: Path) -> None:
        np.savez_compressed(path, **self.__dict__)


def load_marker_data(paths: list[Path]) -> MarkerData:
    parts = []
    for p in paths:
        with np.load(p, allow_pickle=False) as z:
            parts.append({k: z[k] for k in z.files})
    return MarkerData(**{k: np.concatenate([d[k] for d in parts]) for k in parts[0]})


def detect_world(scene_dir: Path, seed: int) -> MarkerData:
    """Crops of a rendered world with truth, and BlazePose landmarks on each."""
    from gst.detect.crops import detect_crop_landmarks
    from gst.train.synthetic_crops import crops_from_synth_scene

    crops = crops_from_synth_scene(scene_dir, crop_size=256)
    lm = detect_crop_landmarks(crops.images.numpy(), rgb=True, refine=True).with_confidence()
    people = read_scene_truth(scene_dir)
    key = people.row_index()
    frame, person = crops.frame.numpy(), crops.person.numpy()
    rows = np.array([key[(int(f), int(p))] for f, p in zip(frame, person, strict=True)])
    K = crops.K.numpy().astype(np.float64)
    full_K = np.stack([_full_K(scene_dir, crops.camera_names[c]) for c in crops.camera.numpy()])
    return MarkerData(
        landmarks=lm,
        K=K,
        R=crops.R.numpy().astype(np.float64),
        t=crops.t.numpy().astype(np.float64),
        px_scale=full_K[:, 0, 0] / K[:, 0, 0],
        frame=frame,
        person=person,
        camera=crops.camera.numpy(),
        world=np.full(len(crops), seed),
        betas=people.betas[rows],
        global_orient=people.global_orient[rows],
        body_pose=people.body_pose[rows],
        transl=people.transl[rows],
    )


def _full_K(scene_dir: Path, camera: str) -> np.ndarray:
    from calibration.formats import read_rig

    return read_rig(scene_dir / "calibration" / "rig.json", "rig")[camera].K


def main(argv: list[str] | None = None) -> None:
    import torch

    from synth.scene import preset, render_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--people", type=int, default=2)
    args = ap.parse_args(argv)
    if args.seed < 5000:
        raise SystemExit("marker data uses tuning seeds 5000+ only (demo = 0, pretraining 1000+)")
    torch.set_num_threads(1)
    scene = args.out / f"world_{args.seed}"
    spec = preset(
        "demo",
        seed=args.seed,
        n_frames=args.frames,
        n_people=args.people,
        motions=None,
        board={"n_frames": 0},
    )
    if not has_scene_truth(scene):
        render_scene(spec, scene)
    data = detect_world(scene, args.seed)
    data.save(args.out / f"detections_{args.seed}.npz")
    print(f"{scene}: {len(data.frame)} crops")


if __name__ == "__main__":
    main()


def people_from_marker_data(data: MarkerData, world: int):
    """One world's detections as `PersonObservations` per truth person (ids are the truth ids),
    for tuning the fit on worlds with truth. Returns (people, truth rows (T,) per person)."""
    from gst.fuse.observations import PersonObservations

    sel = np.flatnonzero(data.world == world)
    C = int(data.camera.max()) + 1
    people, rows = [], []
    for pid in np.unique(data.person[sel]):
        mine = sel[data.person[sel] == pid]
        frames = np.unique(data.frame[mine])
        T = len(frames)
        ti = np.searchsorted(frames, data.frame[mine])
        ci = data.camera[mine]
        obs = PersonObservations(
            int(pid),
            frames.astype(np.int64),
            np.full((T, C, N_LANDMARKS, 2), np.nan),
            np.zeros((T, C, N_LANDMARKS)),
            np.broadcast_to(np.eye(3), (T, C, 3, 3)).copy(),
            np.broadcast_to(np.eye(3, 4), (T, C, 3, 4)).copy(),
            np.ones((T, C)),
            np.full((T, C), -1, np.int64),
        )
        obs.uv[ti, ci] = data.landmarks[mine, :, :2]
        obs.confidence[ti, ci] = data.landmarks[mine, :, 2]
        obs.K[ti, ci] = data.K[mine]
        obs.Rt[ti, ci] = np.concatenate([data.R[mine], data.t[mine, :, None]], -1)
        obs.px_scale[ti, ci] = data.px_scale[mine]
        obs.rows[ti, ci] = mine
        first = np.zeros(T, np.int64)
        first[ti] = mine
        people.append(obs)
        rows.append(first)
    return people, rows
