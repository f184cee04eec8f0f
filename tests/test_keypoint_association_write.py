"""Phase 2 of the keypoint extraction (gst.data.extract.keypoint_association): which ids are
trusted, and phase 1's instances read back in a crowd larger than the landmark array."""

from __future__ import annotations

import h5py
import numpy as np

from gst.data.extract.keypoint_association import _frame_instances, _write
from gst.data.extract.masks import MAX_INSTANCES
from gst.data.keypoints.people import FramePeople, FramePerson, PersonView

W, H = 64, 48


def _results(multi_view_frames: set[int], n_frames: int = 43) -> list[FramePeople]:
    """Person 7 seen by camera a in every frame, by camera b too in `multi_view_frames`."""
    mask = np.zeros((H, W), bool)
    mask[10:30, 20:30] = True
    lm = np.zeros((33, 3))
    lm[:, :2], lm[:, 2] = (50, 40), 0.9
    out = []
    for f in range(n_frames):
        if f in multi_view_frames:
            views = {n: PersonView(lm.copy(), mask, "refined", 1.0) for n in ("a", "b")}
            person = FramePerson(7, np.zeros((33, 3)), views)
        else:
            person = FramePerson(7, None, {"a": PersonView(lm.copy(), mask, "single", np.nan)})
        out.append(FramePeople(f, [person], []))
    return out


def _short(results, tmp_path, n_frames: int = 43) -> list[int]:
    sizes, scale = {"a": (W, H), "b": (W, H)}, {"a": (1.0, 1.0), "b": (1.0, 1.0)}
    return _write(
        results, ["a", "b"], sizes, list(range(n_frames)), tmp_path, scale, 5, sizes, 0.3
    ).short_tracks


def test_a_long_single_view_track_survives_a_brief_second_camera(tmp_path):
    """40 single-view frames and 3 in which a second camera also saw him: his crops stay (the
    multi-view count alone, 3 < 5, dropped every one of them)."""
    assert _short(_results(set()), tmp_path / "a") == []
    assert _short(_results({20, 21, 22}), tmp_path / "b") == []
    # a brief id is still not trusted
    assert _short(_results({1, 2}, n_frames=4), tmp_path / "c", n_frames=4) == [7]


def test_a_clip_shorter_than_the_track_minimum_keeps_who_is_in_all_its_frames(tmp_path):
    """A 4-frame clip (5 frames make a trusted id) lost every id, so extraction wrote no crop
    at all; seen by two cameras in all 4 frames he is kept, in 3 of them he is not."""
    assert _short(_results({0, 1, 2, 3}, n_frames=4), tmp_path / "a", n_frames=4) == []
    three = _results({0, 1, 2}, n_frames=4)
    three[3].people.clear()
    assert _short(three, tmp_path / "b", n_frames=4) == [7]


def test_a_crowd_larger_than_the_landmark_array_is_read_back(tmp_path):
    """Phase 1 keeps landmarks for MAX_INSTANCES people per frame but labels every one: the
    extra people are read as having no instance (was: an IndexError that ended extraction)."""
    labels = np.zeros((1, 40, 80), np.uint8)
    for k in range(MAX_INSTANCES + 1):
        labels[0, :, 2 * k : 2 * k + 2] = k + 1
    path = tmp_path / "persons.h5"
    with h5py.File(path, "w") as f:
        f["labels"] = labels
        f["landmarks"] = np.ones((1, MAX_INSTANCES, 33, 3), np.float32)
        f["presence"] = np.ones((1, MAX_INSTANCES), np.float32)
    with h5py.File(path) as f:
        insts, masks = _frame_instances(f, 0, 1.0, 1.0, "cam")
    assert len(insts) == len(masks) == MAX_INSTANCES


def test_refined_views_land_on_full_resolution_pixel_centres():
    """A landmark model that answers exactly where a skeleton projects, on a half- and a
    quarter-resolution work image: the refined view's landmarks are the full-resolution
    projections (u / s put them 0.5 px up-left at half resolution, 1.5 px at a quarter)."""
    from calibration.synthetic import ring_rig
    from gst.data.keypoints.people import CrowdConfig, CrowdTracker

    cam = ring_rig(4, seed=0)[0]
    heights = np.linspace(0.1, 1.7, 33)
    centre = cam.center + 3.5 * cam.optical_axis
    skeleton = np.c_[
        np.full(33, centre[0]) + 0.1 * np.sin(heights * 7), np.full(33, centre[1]), heights
    ]
    for s in (0.5, 0.25):
        h, w = round(cam.height * s), round(cam.width * s)

        def segment(name, image, roi, origin, s=s):
            work = (cam.project(skeleton) + 0.5) * s - 0.5  # the same points, work pixels
            return (
                np.c_[work - origin, np.full(33, 0.9)],
                0.9,
                np.zeros(image.shape[:2], np.float32),
            )

        tracker = CrowdTracker([cam], 1 / 30, CrowdConfig(), segment, {cam.name: s})

        class Candidate:
            single = None

        Candidate.skeleton = skeleton
        img = np.zeros((h, w, 3), np.uint8)
        got = tracker._look(cam.name, 0, Candidate, np.zeros((h, w), np.int32), img, img)
        assert got is not None
        err = got[0].landmarks[:, :2] - cam.project(skeleton)
        assert np.abs(err).max() < 1e-6, (s, err.mean(0))


def test_strided_extraction_times_its_tracker_in_seconds():
    """Every third frame at 30 fps: the tracker's velocity is the walker's 1.5 m/s (stride / fps
    as the time between consecutive frame numbers made it 0.5) and it remembers people for
    max_gap processed frames."""
    from crowd_people import instances, person, rig

    from gst.data.extract.scene import keypoint_tracker_timing
    from gst.data.keypoints import PersonIdTracker, match_frame
    from gst.data.keypoints.people import CrowdConfig

    crowd, step = keypoint_tracker_timing(CrowdConfig(), 3, 30.0)
    assert (
        crowd.tracker.frame_stride == 3 and crowd.tracker.max_gap == CrowdConfig().tracker.max_gap
    )
    cams = rig("dome", 5, seed=1)
    tracker = PersonIdTracker(cams, step, crowd.tracker)
    for f in range(0, 30, 3):
        found, _ = instances(cams, [person(1.5 * f / 30, 0.0)], seed=f)
        tracker.update(f, match_frame(found, cams), found)
    assert abs(tracker._tracks[0].velocity[0] - 1.5) < 0.1
    # the next processed frame is predicted a whole stride on (the coast fade starts after it)
    moved = (
        tracker._tracks[0].predict(30, step, crowd.tracker.coast, 3) - tracker._tracks[0].skeleton
    )
    assert abs(float(np.nanmedian(moved[:, 0])) - 1.5 * 0.1) < 0.01
