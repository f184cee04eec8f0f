"""Multi-view person association with a coarse visual hull, and ids that persist over time.

Per frame (`associate_frame`):
1. `hull`: every voxel of a grid over the capture volume (`volume`) is projected into every
   camera's foreground label image; occupied voxels form the hull.
2. `splitting`: occupied voxels form 3D connected components. People are roughly upright, so a
   component holding two people who touch is split at the peaks of its ground-plane density
   (or along person instances the cameras agree on).
3. `labels`: each person's voxels are projected back: a 2D blob that only one person's voxels
   land in belongs to that person; a blob shared by several is split by their projected
   footprints, nearer person first.
4. `ids`: `PersonTracker` matches people to the previous frame's by ground-plane distance
   (Hungarian), so ids stay the same over time; `link_tracklets` joins fragments offline.
"""

from gst.data.association.hull import AssociationConfig, FrameAssociation, Person3D, VoxelGrid
from gst.data.association.ids import PersonTracker, link_tracklets
from gst.data.association.labels import associate_frame
from gst.data.association.volume import CaptureVolume, project_fast

__all__ = [
    "AssociationConfig",
    "CaptureVolume",
    "FrameAssociation",
    "Person3D",
    "PersonTracker",
    "VoxelGrid",
    "associate_frame",
    "link_tracklets",
    "project_fast",
]
