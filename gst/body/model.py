"""A body model in SMPL layout, and its differentiable, batched linear blend skinning (LBS).

The arrays follow SMPL's layout, so an official SMPL file and the open default built from Anny
run through the same code:

    v_template (V, 3)        rest mesh at the mean shape
    shapedirs  (V, 3, B)     shape blend shapes, one column per beta
    posedirs   (P, V*3)      optional pose correctives, smplx's layout, P = 9 * (J - 1)
    J_regressor (J, V)       rest joints = J_regressor @ rest vertices (dense or scipy sparse)
    weights    (V, J)        skinning weights, rows sum to 1
    parents    (J,)          kinematic parents, parents[0] = -1, parents[j] < j

Frame: SMPL's axes (Y up, the body faces +Z, body-left is +X), metres. Poses are local joint
rotations relative to the rest pose, in axes parallel to the model frame (SMPL's convention).

The math (Loper et al. 2015, as in smplx's ``lbs``): rest vertices v = v_template + S beta
(+ P (R - I) for pose correctives); rest joints J = J_regressor (v_template + S beta); the world
transform of joint j is G_j = G_parent [R_j | J_j - J_parent]; the skinning transform that maps
the rest pose to the posed one is A_j = G_j [I | -J_j] (plus the global translation), and each
vertex is moved by T_v = sum_j w_vj A_j. GST uses T_v to pose rest-frame Gaussian offsets and
rotations, so it is returned on request.
"""

from __future__ import annotations

import dataclasses
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse
import torch

from gst.atomic import atomic_save_npz
from gst.body.rotations import axis_angle_to_matrix
from gst.body.skeleton import kinematic_levels

__all__ = ["BodyModelData", "BodyOutput", "BodyModel", "NonFiniteBatch"]

_NPZ_FORMAT = "gst-body-v1"


WEIGHT_SUM_TOLERANCE = 1e-4  # skinning weights' rows sum to 1 within this

# what reading a damaged .npz member raises (a bad CRC, a cut stream)
NPZ_MEMBER_ERRORS = (zipfile.BadZipFile, EOFError, zlib.error, OSError)


def open_npz(path: Path, what: str) -> np.lib.npyio.NpzFile:
    """`path` opened as an .npz of plain arrays (no pickles), or a ValueError naming it and
    `what` it should be: empty, cut, not a zip, or a single .npy under an .npz name."""
    try:
        z = np.load(path, allow_pickle=False)
    except (*NPZ_MEMBER_ERRORS, ValueError) as exc:
        raise ValueError(f"{path}: not a readable {what} ({exc})") from exc
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"{path}: a single .npy array, not a {what}")
    return z


@dataclass
class BodyModelData:
    """The arrays of a body model in SMPL layout (numpy, float64 preferred). See module doc."""

    v_template: np.ndarray
    shapedirs: np.ndarray
    J_regressor: np.ndarray | scipy.sparse.spmatrix | scipy.sparse.sparray
    weights: np.ndarray
    parents: np.ndarray
    faces: np.ndarray
    joint_names: tuple[str, ...]
    part_labels: np.ndarray
    part_names: tuple[str, ...] | None = None
    posedirs: np.ndarray | None = None
    name: str = ""
    source: str = ""
    licence: str = ""
    # Variance of each shape component over the distribution it was fitted to (m^2 summed over
    # all vertex coordinates) and the fraction of the total it explains; PCA models only.
    shape_variance: np.ndarray | None = None
    shape_variance_ratio: np.ndarray | None = None
    # Index of every vertex in the mesh it was converted from (the Anny default drops a few).
    source_vertex_ids: np.ndarray | None = None

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.weights.shape[1])

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[2])

    def dense_J_regressor(self) -> np.ndarray:
        reg = self.J_regressor
        return np.asarray(reg.toarray() if scipy.sparse.issparse(reg) else reg, dtype=np.float64)

    def validate(self) -> BodyModelData:
        """Raise ValueError naming the first inconsistent field; return self when all is well."""
        who = f"body model {self.name!r}" if self.name else "body model"

        def fail(field: str, msg: str) -> None:
            raise ValueError(f"{who}: {field} {msg}")

        def shape_is(field: str, arr, want: tuple) -> None:
            got = tuple(np.shape(arr))
            if len(got) != len(want) or any(
                w is not None and g != w for g, w in zip(got, want, strict=True)
            ):
                pretty = "(" + ", ".join("*" if w is None else str(w) for w in want) + ")"
                fail(field, f"has shape {got}, expected {pretty}")

        shape_is("v_template", self.v_template, (None, 3))
        V = self.num_vertices
        shape_is("weights", self.weights, (V, None))
        J = self.num_joints
        shape_is("shapedirs", self.shapedirs, (V, 3, None))
        shape_is("J_regressor", self.J_regressor, (J, V))
        shape_is("parents", self.parents, (J,))
        shape_is("faces", self.faces, (None, 3))
        shape_is("part_labels", self.part_labels, (V,))
        if len(self.joint_names) != J:
            fail("joint_names", f"has {len(self.joint_names)} names, expected {J}")
        parents = np.asarray(self.parents)
        if parents[0] != -1 or np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, J)):
            fail(
                "parents",
                f"must have parents[0] = -1 and 0 <= parents[j] < j, got {parents.tolist()}",
            )
        faces = np.asarray(self.faces)
        if faces.size and (faces.min() < 0 or faces.max() >= V):
            fail("faces", f"index vertices outside [0, {V})")
        w = np.asarray(self.weights)
        drift = np.abs(w.sum(1) - 1).max()
        if not np.all(np.isfinite(w)) or w.min() < -1e-6 or drift > WEIGHT_SUM_TOLERANCE:
            fail(
                "weights", "must be finite, non-negative, and sum to 1 over joints for every vertex"
            )
        for field in ("v_template", "shapedirs", "J_regressor", "posedirs"):
            value = getattr(self, field)
            if scipy.sparse.issparse(value):
                value = value.data  # the stored entries (the rest are zeros)
            if value is not None and not np.all(np.isfinite(value)):
                fail(field, "contains NaN or Inf")
        if self.posedirs is not None:
            shape_is("posedirs", self.posedirs, (9 * (J - 1), 3 * V))
        labels = np.asarray(self.part_labels)
        n_parts = len(self.part_names) if self.part_names is not None else None
        if labels.size and (labels.min() < 0 or (n_parts is not None and labels.max() >= n_parts)):
            fail(
                "part_labels",
                f"must index part_names (0..{n_parts}), got range [{labels.min()}, {labels.max()}]",
            )
        return self

    # ----- persistence (our own npz; official SMPL files are read by gst.body.smpl_file) -----
    def save_npz(self, path: str | Path) -> Path:
        """Write to ``path`` atomically (temporary file + rename). No pickled objects inside."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays: dict[str, np.ndarray] = {
            "format": np.array(_NPZ_FORMAT),
            "v_template": np.asarray(self.v_template),
            "shapedirs": np.asarray(self.shapedirs),
            "J_regressor": self.dense_J_regressor(),
            "weights": np.asarray(self.weights),
            "parents": np.asarray(self.parents, dtype=np.int64),
            "faces": np.asarray(self.faces, dtype=np.int64),
            "joint_names": np.array(list(self.joint_names), dtype=str),
            "part_labels": np.asarray(self.part_labels, dtype=np.int64),
            "name": np.array(self.name),
            "source": np.array(self.source),
            "licence": np.array(self.licence),
        }
        optional = {
            "part_names": self.part_names,
            "posedirs": self.posedirs,
            "shape_variance": self.shape_variance,
            "shape_variance_ratio": self.shape_variance_ratio,
            "source_vertex_ids": self.source_vertex_ids,
        }
        for key, value in optional.items():
            if value is not None:
                arrays[key] = (
                    np.array(list(value), dtype=str) if key == "part_names" else np.asarray(value)
                )

        atomic_save_npz(path, **arrays)
        return path

    @classmethod
    def load_npz(cls, path: str | Path) -> BodyModelData:
        """Read a file written by :meth:`save_npz` (never unpickles). A damaged file (cut short,
        empty, not a zip) is a ValueError naming it."""
        path = Path(path)
        z = open_npz(path, "npz body file")
        try:
            with z:
                return cls._from_npz(z, path)
        except NPZ_MEMBER_ERRORS as exc:  # a damaged member (bad CRC)
            raise ValueError(f"{path}: not a readable npz body file ({exc})") from exc

    @classmethod
    def _from_npz(cls, z: np.lib.npyio.NpzFile, path: Path) -> BodyModelData:
        if "format" not in z.files or str(z["format"]) != _NPZ_FORMAT:
            raise ValueError(f"{path}: not a {_NPZ_FORMAT} body file (keys {sorted(z.files)})")
        get = lambda k: z[k] if k in z.files else None  # noqa: E731
        data = cls(
            v_template=z["v_template"],
            shapedirs=z["shapedirs"],
            J_regressor=z["J_regressor"],
            weights=z["weights"],
            parents=z["parents"],
            faces=z["faces"],
            joint_names=tuple(str(s) for s in z["joint_names"]),
            part_labels=z["part_labels"],
            part_names=tuple(str(s) for s in z["part_names"]) if "part_names" in z.files else None,
            posedirs=get("posedirs"),
            name=str(z["name"]),
            source=str(z["source"]),
            licence=str(z["licence"]),
            shape_variance=get("shape_variance"),
            shape_variance_ratio=get("shape_variance_ratio"),
            source_vertex_ids=get("source_vertex_ids"),
        )
        return data.validate()

    def replace(self, **changes) -> BodyModelData:
        return dataclasses.replace(self, **changes)


@dataclass
class BodyOutput:
    """What :meth:`BodyModel.forward` returns (batch B, V' = number of requested vertices)."""

    vertices: torch.Tensor  # (B, V', 3) posed vertices
    joints: torch.Tensor  # (B, J, 3) posed joints
    joint_transforms: torch.Tensor | None = None  # (B, J, 4, 4) skinning transforms A_j
    vertex_transforms: torch.Tensor | None = None  # (B, V', 4, 4) sum_j w_vj A_j


def _fmt(shape) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


class NonFiniteBatch(ValueError):
    """Parameters with NaN or Inf in some batch items (`rows`: all of them), e.g. a diverged
    network's output: a caller that scores many items can leave those out and count them."""

    def __init__(self, name: str, rows: list[int]):
        self.rows = rows
        super().__init__(f"{name} contains NaN or Inf (batch items {rows[:8]})")

    def __reduce__(self):  # rebuilt from its arguments across processes
        return (type(self), (str(self).split(" contains")[0], self.rows))


class BodyModel(torch.nn.Module):
    """Differentiable, batched LBS for a :class:`BodyModelData` (float32 or float64, any device).

    ``model.to(torch.float64)`` switches precision; inputs are cast to the model's dtype.
    """

    def __init__(
        self,
        data: BodyModelData,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        data.validate()
        self.data = data
        self.name = data.name
        self.num_vertices = data.num_vertices
        self.num_joints = data.num_joints
        self.num_betas = data.num_betas
        self.faces = np.asarray(data.faces, dtype=np.int64)
        self.parents = np.asarray(data.parents, dtype=np.int64)
        self.joint_names = tuple(data.joint_names)
        self.part_labels = np.asarray(data.part_labels, dtype=np.int64)
        self.part_names = tuple(data.part_names) if data.part_names is not None else None

        reg = data.dense_J_regressor()
        shapedirs = np.asarray(data.shapedirs, dtype=np.float64)
        v_template = np.asarray(data.v_template, dtype=np.float64)

        def buf(name: str, arr: np.ndarray) -> None:
            self.register_buffer(
                name, torch.as_tensor(np.ascontiguousarray(arr), dtype=dtype, device=device)
            )

        buf("v_template", v_template)
        buf("shapedirs", shapedirs)
        buf("weights", np.asarray(data.weights, dtype=np.float64))
        buf("J_regressor", reg)
        # Joints are linear in betas: regress the template and each blend shape once, in float64,
        # instead of multiplying a (J, V) matrix by every rest mesh at run time.
        buf("J_template", reg @ v_template)
        buf(
            "J_shapedirs",
            (reg @ shapedirs.reshape(self.num_vertices, -1)).reshape(self.num_joints, 3, -1),
        )
        if data.posedirs is not None:
            buf("posedirs", np.asarray(data.posedirs, dtype=np.float64))
        else:
            self.register_buffer("posedirs", None)

        # Forward-kinematics plan: one batched product per tree level
        # (see skeleton.kinematic_levels).
        levels = kinematic_levels(self.parents)
        order = np.concatenate(levels)
        self._level_slices: list[tuple[int, int]] = []
        local_parent = np.zeros(
            len(order), dtype=np.int64
        )  # parent's position inside previous level
        start = 0
        for d, level in enumerate(levels):
            self._level_slices.append((start, start + len(level)))
            if d > 0:
                prev = {int(j): i for i, j in enumerate(levels[d - 1])}
                local_parent[start : start + len(level)] = [
                    prev[int(self.parents[j])] for j in level
                ]
            start += len(level)
        self.register_buffer("_order", torch.as_tensor(order, device=device), persistent=False)
        self.register_buffer(
            "_inverse_order", torch.as_tensor(np.argsort(order), device=device), persistent=False
        )
        self.register_buffer(
            "_local_parent", torch.as_tensor(local_parent, device=device), persistent=False
        )
        self.register_buffer(
            "_parent_index",
            torch.as_tensor(np.maximum(self.parents, 0), device=device),
            persistent=False,
        )

    @property
    def dtype(self) -> torch.dtype:
        return self.v_template.dtype

    @property
    def device(self) -> torch.device:
        return self.v_template.device

    def extra_repr(self) -> str:
        return (
            f"name={self.name!r}, vertices={self.num_vertices}, joints={self.num_joints}, "
            f"betas={self.num_betas}, posedirs={self.posedirs is not None}"
        )

    # ------------------------------------------------------------------ input checking
    def _tensor(self, x, name: str) -> torch.Tensor:
        if not isinstance(x, torch.Tensor):
            if isinstance(x, np.ndarray):
                x = torch.from_numpy(x)
            else:
                raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        if not x.is_floating_point():
            raise ValueError(f"{name} must be a floating-point tensor, got dtype {x.dtype}")
        return x.to(device=self.device, dtype=self.dtype)

    @staticmethod
    def _finite(x: torch.Tensor, name: str) -> None:
        bad = ~torch.isfinite(x.reshape(x.shape[0], -1)).all(dim=1)
        if bool(bad.any()):
            raise NonFiniteBatch(name, torch.nonzero(bad).flatten().tolist())

    def _rotations(self, x, name: str, count: int) -> torch.Tensor:
        """(B, count, 3, 3) rotation matrices from rotmats or axis-angle in SMPL's shapes."""
        x = self._tensor(x, name)
        shape = tuple(x.shape)
        if count == 1:
            expected = "(B, 3, 3) rotation matrices or (B, 3) axis-angle"
            if x.dim() == 3 and shape[1:] == (3, 3):
                x = x[:, None]
            elif x.dim() == 4 and shape[1:] == (1, 3, 3):
                pass
            elif x.dim() == 2 and shape[1] == 3:
                x = x[:, None]
            elif x.dim() == 3 and shape[1:] == (1, 3):
                pass
            else:
                raise ValueError(f"{name} must have shape {expected}, got {_fmt(shape)}")
        else:
            expected = (
                f"(B, {count}, 3, 3) rotation matrices, (B, {count}, 3) or "
                f"(B, {3 * count}) axis-angle"
            )
            if x.dim() == 4 and shape[1:] == (count, 3, 3):
                pass
            elif x.dim() == 3 and shape[1:] == (count, 3):
                pass
            elif x.dim() == 2 and shape[1] == 3 * count:
                x = x.reshape(shape[0], count, 3)
            else:
                raise ValueError(f"{name} must have shape {expected}, got {_fmt(shape)}")
        if x.shape[0] == 0:
            raise ValueError(f"{name} has an empty batch")
        self._finite(x, name)
        return x if x.dim() == 4 else axis_angle_to_matrix(x)

    def _vertex_ids(self, vertex_ids) -> torch.Tensor | None:
        if vertex_ids is None:
            return None
        ids = torch.as_tensor(vertex_ids, device=self.device)
        if ids.dim() != 1 or ids.dtype not in (torch.int64, torch.int32):
            raise ValueError(
                f"vertex_ids must be a 1-D integer tensor, got shape {_fmt(ids.shape)} "
                f"dtype {ids.dtype}"
            )
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= self.num_vertices):
            raise ValueError(
                f"vertex_ids must lie in [0, {self.num_vertices}), got range "
                f"[{int(ids.min())}, {int(ids.max())}]"
            )
        return ids.long()

    # ------------------------------------------------------------------ model pieces
    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """(B, J, 3) rest-pose joints for (B, nb) betas (nb <= num_betas, missing ones are 0)."""
        nb = betas.shape[1]
        return self.J_template + torch.einsum("bl,jkl->bjk", betas, self.J_shapedirs[..., :nb])

    def rest_vertices(
        self, betas: torch.Tensor, vertex_ids: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, V', 3) rest-pose vertices (no pose correctives)."""
        nb = betas.shape[1]
        v_t = self.v_template if vertex_ids is None else self.v_template[vertex_ids]
        sd = self.shapedirs if vertex_ids is None else self.shapedirs[vertex_ids]
        sd = sd[..., :nb].reshape(-1, nb)
        return (v_t.reshape(1, -1) + betas @ sd.T).reshape(betas.shape[0], -1, 3)

    def _forward_kinematics(self, rotmats: torch.Tensor, joints: torch.Tensor):
        """World rotations and positions of every joint, one batched product per tree level."""
        rel = joints - joints[:, self._parent_index]
        rel[:, 0] = joints[:, 0]
        rot = rotmats[:, self._order]
        rel = rel[:, self._order]
        g_rot = [rot[:, :1]]
        g_pos = [rel[:, :1]]
        for d in range(1, len(self._level_slices)):
            a, b = self._level_slices[d]
            lp = self._local_parent[a:b]
            p_rot, p_pos = g_rot[-1][:, lp], g_pos[-1][:, lp]
            g_rot.append(p_rot @ rot[:, a:b])
            g_pos.append((p_rot @ rel[:, a:b, :, None])[..., 0] + p_pos)
        g_rot = torch.cat(g_rot, dim=1)[:, self._inverse_order]
        g_pos = torch.cat(g_pos, dim=1)[:, self._inverse_order]
        return g_rot, g_pos

    # ------------------------------------------------------------------ forward
    def forward(
        self,
        betas: torch.Tensor | None,
        body_pose: torch.Tensor,
        global_orient: torch.Tensor,
        transl: torch.Tensor | None = None,
        vertex_ids: torch.Tensor | None = None,
        return_transforms: bool = False,
    ) -> BodyOutput:
        """Pose the body.

        Args:
            betas: (B, nb) shape coefficients, nb <= num_betas (missing ones are 0); (1, nb)
                broadcasts over the batch; None is the mean shape.
            body_pose: (B, J-1, 3, 3) rotation matrices, or (B, J-1, 3) / (B, 3(J-1)) axis-angle,
                local rotations of joints 1.. relative to their parents (SMPL order).
            global_orient: (B, 3, 3) rotation matrix or (B, 3) axis-angle of the root
                ((B, 1, 3, 3) and (B, 1, 3) are accepted too). A 2-D (3, 3) is three
                axis-angle rows, never an unbatched matrix (which is (1, 3, 3)).
            transl: (B, 3) translation added to every output, or None.
            vertex_ids: 1-D LongTensor; only these vertices are posed and returned (joints
                always come from the full mesh).
            return_transforms: also return the joint and per-vertex skinning transforms.
        Raises:
            ValueError naming the argument on a wrong shape or a NaN/Inf value.
        """
        n_body = self.num_joints - 1
        body_rot = self._rotations(body_pose, "body_pose", n_body)
        B = body_rot.shape[0]
        root_rot = self._rotations(global_orient, "global_orient", 1)
        if root_rot.shape[0] != B:
            hint = ""
            if tuple(getattr(global_orient, "shape", ())) == (3, 3):
                hint = (
                    " (a (3, 3) global_orient reads as 3 axis-angle rows: one rotation matrix "
                    "needs shape (1, 3, 3))"
                )
            raise ValueError(
                f"global_orient has batch {root_rot.shape[0]} but body_pose has batch {B}{hint}"
            )
        if betas is None:
            betas = torch.zeros(B, self.num_betas, dtype=self.dtype, device=self.device)
        betas = self._tensor(betas, "betas")
        if (
            betas.dim() != 2
            or betas.shape[0] not in (1, B)
            or not 0 < betas.shape[1] <= self.num_betas
        ):
            raise ValueError(
                f"betas must have shape (B, nb) with B = {B} (or 1) and "
                f"1 <= nb <= {self.num_betas}, got {_fmt(betas.shape)}"
            )
        self._finite(betas, "betas")
        betas = betas.expand(B, -1)
        if transl is not None:
            transl = self._tensor(transl, "transl")
            if tuple(transl.shape) != (B, 3):
                raise ValueError(f"transl must have shape ({B}, 3), got {_fmt(transl.shape)}")
            self._finite(transl, "transl")
        ids = self._vertex_ids(vertex_ids)

        rotmats = torch.cat([root_rot, body_rot], dim=1)  # (B, J, 3, 3)
        joints_rest = self.rest_joints(betas)
        v = self.rest_vertices(betas, ids)
        if self.posedirs is not None:
            eye = torch.eye(3, dtype=self.dtype, device=self.device)
            pose_feature = (rotmats[:, 1:] - eye).reshape(B, -1)
            posedirs = self.posedirs
            if ids is not None:
                posedirs = posedirs.reshape(posedirs.shape[0], -1, 3)[:, ids].reshape(
                    posedirs.shape[0], -1
                )
            v = v + (pose_feature @ posedirs).reshape(B, -1, 3)

        g_rot, g_pos = self._forward_kinematics(rotmats, joints_rest)
        a_trans = g_pos - (g_rot @ joints_rest[..., None])[..., 0]
        if transl is not None:
            a_trans = a_trans + transl[:, None]
            g_pos = g_pos + transl[:, None]
        w_t = (self.weights if ids is None else self.weights[ids]).T  # (J, V')
        # Blend the joint transforms per vertex as (B, 12, V') rows and apply them with
        # elementwise products: on CPU this beats batched 3x3 matmuls over the vertices, forward
        # and (twice over) backward, and avoids slicing a large tensor, whose backward
        # zero-fills it.
        a12 = torch.cat([g_rot.reshape(B, self.num_joints, 9), a_trans], dim=-1)  # (B, J, 12)
        r00, r01, r02, r10, r11, r12, r20, r21, r22, tx, ty, tz = (
            a12.transpose(1, 2) @ w_t
        ).unbind(1)
        x, y, z = v.unbind(-1)
        vertices = torch.stack(
            [
                r00 * x + r01 * y + r02 * z + tx,
                r10 * x + r11 * y + r12 * z + ty,
                r20 * x + r21 * y + r22 * z + tz,
            ],
            dim=-1,
        )

        out = BodyOutput(vertices=vertices, joints=g_pos)
        if return_transforms:
            out.joint_transforms = _homogeneous(torch.cat([g_rot, a_trans[..., None]], dim=-1))
            # sum_j w_vj A_j; its last row is [0 0 0 1] because the weights sum to one.
            zero, one = torch.zeros_like(x), torch.ones_like(x)
            out.vertex_transforms = torch.stack(
                [r00, r01, r02, tx, r10, r11, r12, ty, r20, r21, r22, tz, zero, zero, zero, one],
                dim=-1,
            ).reshape(B, -1, 4, 4)
        return out


def _homogeneous(m34: torch.Tensor) -> torch.Tensor:
    """(..., 3, 4) -> (..., 4, 4) with last row [0, 0, 0, 1]."""
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=m34.dtype, device=m34.device)
    return torch.cat([m34, bottom.expand(m34.shape[:-2] + (1, 4))], dim=-2)
