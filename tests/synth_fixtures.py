"""Test fixtures for synth: a capsule body in the SMPL joint layout behind the body-model API.

`CapsuleBody` mimics `gst.body.BodyModel` (faces, parents, joint_names, num_betas, part_labels,
part_names, forward(betas, body_pose, global_orient, transl) -> vertices, joints) with rigid
skinning of capsules and ellipsoids, so synth can be tested before the real body model lands.
`rest="A"` builds it in an A-pose (arms 45 degrees down) like Anny's rest pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from synth.scene import SceneSpec, preset
from synth.skeleton import JOINT_NAMES, PARENTS

# Rest joints of a ~1.68 m person in SMPL axes (x left, y up, z facing), pelvis at the origin.
_REST_JOINTS = {
    "pelvis": (0.0, 0.0, 0.0),
    "left_hip": (0.09, -0.08, 0.0),
    "right_hip": (-0.09, -0.08, 0.0),
    "spine1": (0.0, 0.11, -0.01),
    "left_knee": (0.10, -0.47, 0.01),
    "right_knee": (-0.10, -0.47, 0.01),
    "spine2": (0.0, 0.24, 0.0),
    "left_ankle": (0.10, -0.86, -0.03),
    "right_ankle": (-0.10, -0.86, -0.03),
    "spine3": (0.0, 0.30, 0.01),
    "left_foot": (0.11, -0.92, 0.09),
    "right_foot": (-0.11, -0.92, 0.09),
    "neck": (0.0, 0.52, -0.02),
    "left_collar": (0.07, 0.42, -0.01),
    "right_collar": (-0.07, 0.42, -0.01),
    "head": (0.0, 0.60, 0.03),
    "left_shoulder": (0.18, 0.44, -0.02),
    "right_shoulder": (-0.18, 0.44, -0.02),
    "left_elbow": (0.44, 0.44, -0.03),
    "right_elbow": (-0.44, 0.44, -0.03),
    "left_wrist": (0.69, 0.44, -0.03),
    "right_wrist": (-0.69, 0.44, -0.03),
    "left_hand": (0.77, 0.44, -0.03),
    "right_hand": (-0.77, 0.44, -0.03),
}
PART_NAMES = [
    "head",
    "neck",
    "torso",
    "hips",
    "upperarm",
    "forearm",
    "hand",
    "upperleg",
    "lowerleg",
    "foot",
]


@dataclass
class BodyOutput:
    vertices: torch.Tensor
    joints: torch.Tensor


def _capsule_mesh(
    a, b, radius, scale=(1.0, 1.0, 1.0), count=(10, 14), max_edge=0.04
) -> trimesh.Trimesh:
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b - a))
    mesh = trimesh.creation.capsule(height=max(length, 1e-3), radius=radius, count=list(count))
    mesh.apply_scale(1.0)
    mesh.vertices *= np.asarray(scale)
    mesh.vertices[:, 2] += length / 2  # trimesh capsules are centred; start at a
    z = (b - a) / max(length, 1e-9)
    x = np.cross([0.0, 1.0, 0.0], z) if abs(z[1]) < 0.9 else np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    mesh.vertices = mesh.vertices @ np.stack([x, y, z]) + a
    # Capsule sides are single long triangles; split them so per-vertex attributes resolve.
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge)
    return trimesh.Trimesh(v, f, process=False)


def _ellipsoid(centre, radii, subdivisions=3) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    mesh.vertices = mesh.vertices * np.asarray(radii) + np.asarray(centre)
    return mesh


def _axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    angle = aa.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    k = aa / angle
    K = torch.zeros(aa.shape[:-1] + (3, 3), dtype=aa.dtype)
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    eye = torch.eye(3, dtype=aa.dtype).expand(K.shape)
    return eye + s * K + (1 - c) * (K @ K)


class CapsuleBody(torch.nn.Module):
    """Capsule person with rigid skinning in the SMPL joint layout (a stand-in body model)."""

    num_betas = 10
    joint_names = list(JOINT_NAMES)

    def __init__(self, rest: str = "T", detail: int = 1, max_edge: float = 0.04):
        super().__init__()
        self.parents = np.array(PARENTS)
        j = {k: np.array(v) for k, v in _REST_JOINTS.items()}
        c = (10 * detail, 14 * detail)
        parts = []

        def _capsule(*args, **kw):  # this body's edge length
            return _capsule_mesh(*args, max_edge=max_edge, **kw)

        # (mesh, joint that moves it, part name)

        def add(mesh, joint, part):
            parts.append((mesh, joint, part))

        for s in ("left", "right"):
            sx = 1.0 if s == "left" else -1.0
            add(_capsule(j[f"{s}_hip"], j[f"{s}_knee"], 0.075, count=c), f"{s}_hip", "upperleg")
            add(_capsule(j[f"{s}_knee"], j[f"{s}_ankle"], 0.052, count=c), f"{s}_knee", "lowerleg")
            heel = j[f"{s}_ankle"] + np.array([0.0, -0.05, -0.05])
            toe = j[f"{s}_foot"] + np.array([0.0, -0.005, 0.06])
            add(_capsule(heel, toe, 0.038, scale=(1.3, 1.0, 1.0), count=c), f"{s}_ankle", "foot")
            add(
                _capsule(j[f"{s}_shoulder"], j[f"{s}_elbow"], 0.047, count=c),
                f"{s}_shoulder",
                "upperarm",
            )
            add(_capsule(j[f"{s}_elbow"], j[f"{s}_wrist"], 0.038, count=c), f"{s}_elbow", "forearm")
            add(
                _ellipsoid(j[f"{s}_wrist"] + np.array([sx * 0.07, 0.0, 0.0]), (0.08, 0.022, 0.045)),
                f"{s}_wrist",
                "hand",
            )
            add(
                _capsule(j[f"{s}_collar"], j[f"{s}_shoulder"], 0.06, count=c),
                f"{s}_collar",
                "torso",
            )
        add(
            _capsule(
                j["left_hip"] * [1, 1, 0],
                j["right_hip"] * [1, 1, 0],
                0.115,
                scale=(1, 1, 0.95),
                count=c,
            ),
            "pelvis",
            "hips",
        )
        add(
            _capsule(j["pelvis"], j["spine2"], 0.14, scale=(1.0, 0.68, 1.0), count=c),
            "spine1",
            "torso",
        )
        add(
            _capsule(j["spine2"], j["neck"] - [0, 0.06, 0], 0.15, scale=(1.0, 0.7, 1.0), count=c),
            "spine3",
            "torso",
        )
        add(_capsule(j["neck"] - [0, 0.04, 0], j["head"], 0.052, count=c), "neck", "neck")
        add(
            _ellipsoid(
                j["head"] + np.array([0.0, 0.07, 0.0]),
                (0.082, 0.112, 0.098),
                subdivisions=3 + (detail > 1),
            ),
            "head",
            "head",
        )

        verts, faces, weights, labels, off = [], [], [], [], 0
        for mesh, joint, part in parts:
            verts.append(mesh.vertices)
            faces.append(mesh.faces + off)
            weights.append(np.full(len(mesh.vertices), JOINT_NAMES.index(joint)))
            labels.append(np.full(len(mesh.vertices), PART_NAMES.index(part)))
            off += len(mesh.vertices)
        self.faces = np.concatenate(faces).astype(np.int64)
        self.part_labels = np.concatenate(labels).astype(np.int64)
        self.part_names = list(PART_NAMES)
        self._bone = torch.as_tensor(np.concatenate(weights))
        rest_v = torch.as_tensor(np.concatenate(verts), dtype=torch.float32)
        rest_j = torch.as_tensor(np.stack([j[n] for n in JOINT_NAMES]), dtype=torch.float32)
        if rest == "A":  # re-rest with the arms 45 degrees down, as Anny's rest pose is
            pose = torch.zeros(1, 23, 3)
            pose[0, JOINT_NAMES.index("left_shoulder") - 1, 2] = -np.pi / 4
            pose[0, JOINT_NAMES.index("right_shoulder") - 1, 2] = np.pi / 4
            v, jj = self._skin(
                rest_v[None],
                rest_j[None],
                _axis_angle_to_matrix(pose),
                torch.eye(3)[None],
                torch.zeros(1, 3),
            )
            rest_v, rest_j = v[0], jj[0]
        elif rest != "T":
            raise ValueError(f"rest must be 'T' or 'A', got {rest!r}")
        self.register_buffer("rest_vertices", rest_v)
        self.register_buffer("rest_joints", rest_j)

    def _skin(self, rest_v, rest_j, rots, root, transl):
        B = rest_v.shape[0]
        G = [root]
        P = [rest_j[:, 0] + transl]
        for i in range(1, len(PARENTS)):
            p = PARENTS[i]
            G.append(G[p] @ rots[:, i - 1])
            P.append(P[p] + (G[p] @ (rest_j[:, i] - rest_j[:, p])[..., None])[..., 0])
        G = torch.stack(G, 1)
        P = torch.stack(P, 1)
        idx = self._bone.expand(B, -1)
        Gv = G[torch.arange(B)[:, None], idx]
        local = rest_v - rest_j[torch.arange(B)[:, None], idx]
        v = (Gv @ local[..., None])[..., 0] + P[torch.arange(B)[:, None], idx]
        return v, P

    def forward(self, betas=None, body_pose=None, global_orient=None, transl=None) -> BodyOutput:
        B = next(x.shape[0] for x in (betas, body_pose, global_orient, transl) if x is not None)
        betas = torch.zeros(B, self.num_betas) if betas is None else betas.float()
        rots = torch.zeros(B, 23, 3) if body_pose is None else body_pose.float()
        if rots.shape[-1] == 3 and rots.dim() == 3:
            rots = _axis_angle_to_matrix(rots)
        root = torch.zeros(B, 3) if global_orient is None else global_orient.float()
        if root.dim() == 2:
            root = _axis_angle_to_matrix(root)
        transl = torch.zeros(B, 3) if transl is None else transl.float()
        # betas[0] scales height, betas[1] girth (about the pelvis and each bone's axis).
        h = 1.0 + 0.04 * betas[:, 0:1, None]
        g = 1.0 + 0.06 * betas[:, 1:2, None]
        rest_j = self.rest_joints[None] * h
        idx = self._bone
        anchor = rest_j[:, idx]
        rest_v = anchor + (self.rest_vertices[None] * h - anchor) * g
        v, jnt = self._skin(rest_v, rest_j, rots, root, transl)
        return BodyOutput(vertices=v, joints=jnt)


def read_panoptic(path) -> list:
    """Independent reader of a CMU Panoptic calibration JSON (t in centimetres)."""
    import json

    from calibration import Camera

    data = json.loads(Path(path).read_text())
    return [
        Camera.create(
            c["name"],
            c["K"],
            c["distCoef"],
            c["R"],
            np.asarray(c["t"], float).ravel() / 100.0,
            c["resolution"][0],
            c["resolution"][1],
        )
        for c in data["cameras"]
    ]


def rig_io():
    """(writer, reader) for calibration files: calibration.formats' write_rig and read_rig."""
    from calibration import formats

    return formats.write_rig, formats.read_rig


# The test scene before overrides, in `preset`'s double-underscore keys so that a nested override
# (`rig=dict(width=160)`) changes only the fields it names.
_SMALL_SCENE = {
    "n_frames": 4,
    "n_people": 2,
    "motions": [["run"], ["squat"]],
    "rig__kind": "dome",
    "rig__n_cameras": 2,
    "rig__width": 96,
    "rig__height": 72,
    "rig__distortion": "none",
    "board__n_frames": 1,
    "imaging__antialias": 1,
    "imaging__background_samples": 1,
    "imaging__shadow_samples": 1,
}


def small_scene_spec(**overrides) -> SceneSpec:
    """The 'demo' preset cut down to a test scene: 4 frames of two people (run, squat), a dome of
    two undistorted 96x72 cameras, a one-frame board clip and one sample per pixel, background
    and shadow. `overrides` as `synth.scene.preset` takes them."""
    return preset("demo", **{**_SMALL_SCENE, **overrides})
