"""`track --video` with the demo's model on the four cameras of the real lab capture, each
renamed so that it is no calibrated camera of any scene (issue: a real clip straight after the
README demo). Slow: the demo's model is trained first (`python -m pipeline run train` in a
temporary workspace, about 8 minutes on 2 cores), unless GST_DEMO_CHECKPOINT names one (for
example `workspace/demo/models/gst.pt` after the README's demo command):

    GST_DEMO_CHECKPOINT=workspace/demo/models/gst.pt pytest -m slow tests/test_track_lab_cameras.py

Per camera it checks who is tracked (one id per person visible, none on the floor, no id that
jumps from one person to another) and the network's 3D body against the landmark model's 2D
joints, with no pose fit (the network alone):
- `joints2d` against the landmarks, over every tracked row: a median within 20 px at 1088x1920;
- the body's own BlazePose points (like with like, gst.track.agreement) against the landmarks,
  for the two people who walk in front (the man and the woman): within 20 px.
The body's joints against the landmarks for the man and the woman alone carry the offset
between a body model's joint and a BlazePose point (docs/track_evaluation.md), and are printed,
not checked.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from tests.real_capture import LAB, NEEDS_MODELS_AND_LAB

pytestmark = [pytest.mark.slow, *NEEDS_MODELS_AND_LAB]

ROOT = Path(__file__).resolve().parents[1]
# people in view on each camera: the man and the woman who walk in front, and on cam01 and cam02
# a bystander standing at the back (hidden on cam03 and cam04)
VISIBLE = {"cam01": 3, "cam02": 3, "cam03": 2, "cam04": 2}
FRAMES = 100


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    given = os.environ.get("GST_DEMO_CHECKPOINT")
    if given:
        path = Path(given)
        assert path.is_file(), f"GST_DEMO_CHECKPOINT={given}: no such checkpoint"
        return path
    ws = tmp_path_factory.mktemp("demo_workspace")
    cmd = [sys.executable, "-m", "pipeline", "run", "train", "-q", "--set", f"workspace={ws}"]
    subprocess.run(cmd, cwd=ROOT, check=True)
    return ws / "demo" / "models" / "gst.pt"


@pytest.fixture(scope="module")
def tracks(checkpoint, tmp_path_factory) -> dict[str, pa.Table]:
    from calibration.formats import read_rig
    from gst.track import read_tracks
    from gst.track.scene import TrackRequest, TrackSettings, track_scene

    d = tmp_path_factory.mktemp("lab_as_video")
    videos = []
    for cam in VISIBLE:
        clip = d / f"clip_{cam}.mp4"  # no camera name of the lab rig
        clip.symlink_to(LAB / f"{cam}.mp4")
        videos.append(clip)
    request = TrackRequest(
        videos=videos,
        checkpoint=checkpoint,
        rig=read_rig(LAB / "Calib.qca.txt", "qualisys"),
        tracks_dir=d / "tracks",
        reports_dir=d / "reports",
        staging=d / "staging",
        scene="demo",
    )
    outcomes = track_scene(TrackSettings(overlay=False, fit_pose=False), request)
    return {
        o.result.path.parent.name.removeprefix("video=clip_"): read_tracks(o.result.path)
        for o in outcomes
    }


def _people(table: pa.Table) -> dict[int, pa.Table]:
    ids = table.column("person_id")
    return {int(p): table.filter(pc.equal(ids, p)) for p in np.unique(ids.to_numpy())}


def _height(table: pa.Table) -> float:
    from gst.track import column_array

    box = column_array(table, "bbox")
    return float(np.median(box[:, 3] - box[:, 1]))


@pytest.mark.parametrize("cam", list(VISIBLE))
def test_one_id_per_person_in_view_and_none_on_the_floor(tracks, cam):
    from gst.detect.persons import LIMB_JOINTS
    from gst.track.read import landmark_array

    people = _people(tracks[cam])
    lasting = {p: t for p, t in people.items() if t.num_rows > 2}  # parts: at most 2 frames
    assert len(lasting) == VISIBLE[cam], {p: t.num_rows for p, t in people.items()}
    front = sorted(lasting, key=lambda p: -_height(lasting[p]))[:2]
    for p, t in lasting.items():
        frames = np.sort(t.column("frame").to_numpy())
        lm = landmark_array(t)[np.argsort(t.column("frame").to_numpy())]
        # a person, not the floor: the landmark model is sure of their limbs
        assert np.median(lm[:, LIMB_JOINTS, 2]) >= 0.5, (cam, p)
        # one person all along: the mid-hips never jump to someone else between frames
        hips = lm[:, [23, 24], :2].mean(axis=1)
        step = np.linalg.norm(np.diff(hips, axis=0), axis=1) / np.maximum(np.diff(frames), 1)
        assert step.max() < 0.2 * _height(t), (cam, p, step.max())
        if p in front:  # the man and the woman are in view the whole clip
            assert len(frames) >= 0.9 * FRAMES, (cam, p, len(frames))


@pytest.mark.parametrize("cam", list(VISIBLE))
def test_the_network_body_agrees_with_the_landmark_model(tracks, cam):
    from gst.track.agreement import joints_vs_landmarks
    from gst.track.read import parse_metadata
    from gst.track.scene import body_points_vs_landmarks

    table = tracks[cam]
    assert parse_metadata(table.schema)["calibration"]["calibrated"] is False
    every = joints_vs_landmarks(table)
    assert every.median_px < 20.0, (cam, every)
    people = _people(table)
    front = sorted(people, key=lambda p: -_height(people[p]))[:2]
    both = table.filter(
        pc.is_in(table.column("person_id"), pa.array(front, table.column("person_id").type))
    )
    own = body_points_vs_landmarks(both)
    joints = joints_vs_landmarks(both)
    print(
        f"{cam}: joints2d, every row {every.median_px:.1f} px; man and woman: joints "
        f"{joints.median_px:.1f} px, their own BlazePose points {own.median_px:.1f} px"
    )
    assert own.median_px < 20.0, (cam, own)
