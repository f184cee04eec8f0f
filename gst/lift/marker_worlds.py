"""Marker worlds: BlazePose detections on rendered synthetic crops, with the truth body of
every crop (`gst.fuse.marker_data.MarkerData`), for fitting the virtual-marker model
(gst.body.markers, `python -m gst.fuse.fit_markers`).

A synthetic world is rendered (`synth.scene`, tuning seeds 5000+ only, never the demo seed 0 or
reporting seeds), every truth person box is cropped (HMR2 square, undistorted, own K: the
extraction's convention) and BlazePose runs on each crop exactly as
`gst.fuse.observations.crop_landmarks` does on extracted crops
(`detect_crop_landmarks(refine=True)`: whole crop, then the alignment region and its mirror).

    python -m gst.lift.marker_worlds --seed 5000 --out /work/data/fuse/worlds
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from gst.fuse.marker_data import MarkerData
from synth.truth import has_scene_truth, read_scene_truth

__all__ = ["detect_world"]


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
