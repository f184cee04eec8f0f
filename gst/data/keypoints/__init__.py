"""Multi-view, multi-person association by 2D keypoint geometry.

Per frame, each camera's person instances (BlazePose's 33 landmarks in distorted pixels with
confidences, a box, optionally a mask) are grouped into people across the calibrated cameras
(`match_frame`: joint and cycle-consistent; a person seen by one camera keeps a single-view
group), each multi-view person gets a triangulated skeleton, and `PersonIdTracker` keeps their
ids over time.

```python
from gst.data.keypoints import PersonInstance, PersonIdTracker, match_frame

tracker = PersonIdTracker(rig, step_seconds=1 / fps)
for frame, per_camera in frames:  # per_camera: camera name -> [PersonInstance, ...]
    match = match_frame(per_camera, rig)
    ids = tracker.update(frame, match, per_camera)  # one id per match.groups entry
```
"""

from gst.data.keypoints.instances import (
    BODY_LANDMARKS,
    LEFT_RIGHT,
    MIRROR,
    N_LANDMARKS,
    InstanceError,
    PersonInstance,
)
from gst.data.keypoints.matching import (
    AssociationError,
    FrameMatch,
    MatchConfig,
    PersonGroup,
    match_frame,
)
from gst.data.keypoints.tracking import PersonIdTracker, TrackerConfig

__all__ = [
    "BODY_LANDMARKS",
    "LEFT_RIGHT",
    "MIRROR",
    "N_LANDMARKS",
    "AssociationError",
    "FrameMatch",
    "InstanceError",
    "MatchConfig",
    "PersonGroup",
    "PersonIdTracker",
    "PersonInstance",
    "TrackerConfig",
    "match_frame",
]
