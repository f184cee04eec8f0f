"""Quality proxies for an extraction that has no ground truth (real footage).

- coverage: per camera, the share of frames in which `expected` people were cropped
  (min(crops, expected) / expected, averaged over frames).
- cross-view consistency: for each (frame, person) cropped in >= 2 cameras, the person box
  centres (undistorted) are triangulated (DLT) and reprojected; the error is divided by the
  box height, so 0.05 means the views disagree by 5% of the person's size. Box centres are
  not exactly one 3D point, so correct associations give a few percent, wrong ones tens.
- id continuity: distinct ids, ids that cover at least `min_frames` frames, and the share of
  (frame, person) groups that belong to the `expected` longest ids.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from calibration import Rig
from calibration.triangulate import dlt_points
from gst.data.store import CropStore


@dataclass(frozen=True)
class ExtractProxies:
    coverage: dict[str, float]  # camera -> mean share of the expected people found per frame
    groups: int  # (frame, person) seen by >= 2 cameras
    reprojection_median: float  # box-height fractions
    reprojection_p90: float
    ids: int
    ids_long: int  # ids seen in >= min_frames frames
    main_id_share: float  # share of (frame, person) groups held by the `expected` longest ids

    def to_dict(self) -> dict:
        return asdict(self)


def extract_proxies(
    store_path, rig: Rig, expected: int = 2, min_frames: int = 10
) -> ExtractProxies:
    """Proxies (module doc) of a crop store written for `rig` (box columns are undistorted
    full-resolution pixel edges, so a pinhole K [R | t] projects them)."""
    store = CropStore(store_path)
    t = store.index.to_pandas()
    names = list(store.camera_names)
    n_frames = int(store.attrs.get("n_frames", t["frame"].max() + 1)) if len(t) else 0
    coverage = {}
    for n in names:
        sel = t[t["camera"] == n]
        per_frame = sel.groupby("frame").size().reindex(range(n_frames), fill_value=0).to_numpy()
        coverage[n] = (
            float(np.mean(np.minimum(per_frame, expected) / expected)) if n_frames else 0.0
        )
    P = {c.name: c.K @ np.concatenate([c.R, c.t.reshape(3, 1)], axis=1) for c in rig}
    errors = []
    groups = 0
    for _, g in t.groupby(["frame", "person_id"]):
        if len(g) < 2:
            continue
        groups += 1
        # box edges -> centre in pixel-centre coordinates (edges are centre coordinate +- 0.5)
        uv = np.stack([0.5 * (g["x0"] + g["x1"]), 0.5 * (g["y0"] + g["y1"])], axis=1) - 0.5
        Ps = np.stack([P[c] for c in g["camera"]])
        X = dlt_points(Ps, uv[:, None, :])[0]
        proj = Ps @ np.append(X, 1.0)
        err = (
            np.linalg.norm(proj[:, :2] / proj[:, 2:3] - uv, axis=1) / (g["y1"] - g["y0"]).to_numpy()
        )
        errors.extend(err.tolist())
    per_id = t.groupby("person_id")["frame"].nunique().sort_values(ascending=False)
    groups_per_id = t.groupby("person_id").apply(
        lambda g: g["frame"].nunique(), include_groups=False
    )
    total = float(groups_per_id.sum()) if len(groups_per_id) else 0.0
    main = (
        float(groups_per_id.sort_values(ascending=False).iloc[:expected].sum())
        if len(groups_per_id)
        else 0.0
    )
    return ExtractProxies(
        coverage,
        groups,
        float(np.median(errors)) if errors else float("nan"),
        float(np.percentile(errors, 90)) if errors else float("nan"),
        int(len(per_id)),
        int((per_id >= min_frames).sum()),
        main / total if total else 0.0,
    )
