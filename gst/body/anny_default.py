"""The open default body: Anny converted to the SMPL layout (24 joints, PCA betas, SMPL axes).

Licences. Anny's code is Apache-2.0 (NAVER Corp.); the MakeHuman-derived mesh, blend shapes, rig
and skinning weights it ships are CC0 1.0 (public domain dedication). The arrays built here are
derived from those data only (Anny's SMPL/SMPL-X topologies, which need non-commercial
downloads, are not used), so the result may be redistributed; we still credit Anny and
MakeHuman in ``licence``.

What the conversion does (see docs/body_model.md):
- Mesh: Anny's default topology (13718 vertices, triangles) minus the tongue, a separate
  component inside the mouth. Axes: (x, y, z)_SMPL = (x, z, -y)_Anny, metres.
- Skeleton: 24 SMPL joints, each an Anny bone (``ANNY_BONE_FOR_JOINT``). The skinning weights
  of every other bone go to its nearest kept ancestor, except fingers and toes, which go to the
  hand and foot joints (SMPL's hand and foot joints carry the fingers and toes).
- Pose: Anny's 'local-ref' deltas are rotations about each bone head in world-aligned axes,
  exactly SMPL's convention, so with the other bones at rest the conversion is exact for a
  given rest shape. The rest pose is Anny's (arms lowered about 45 degrees), not SMPL's T-pose.
- Shape: PCA of rest meshes over Anny's calibrated phenotype distribution (ages
  ``age_range``), done exactly in Anny's blend-shape coefficient space. Betas are in units of
  standard deviations, like SMPL's; the explained variance is stored.
- Joint regressor: per joint, weights over the vertices around it (rows sum to one) chosen so
  that the regressed joints of every mesh in the PCA space equal the best linear prediction of
  Anny's bone heads from the betas (see ``_fit_joint_regressor``).
- Part labels: Anny's UV segmentation (head, hands, feet, eyes, cavities) with the remaining
  body split by dominant skinning joint.

Built once (about a minute on top of Anny's own first build) and cached by content as an .npz
under ``$GST_CACHE_DIR`` or ``~/.cache/gst-capture/``; later loads take well under a second.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
import scipy.optimize
import scipy.sparse
import torch

from gst.body.model import BodyModelData
from gst.body.skeleton import (
    NUM_JOINTS,
    PART_NAMES,
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    parts_from_weights,
)

__all__ = [
    "build_anny_default",
    "default_cache_dir",
    "ANNY_BONE_FOR_JOINT",
    "ANNY_TO_SMPL_AXES",
    "ANNY_LICENCE",
    "AnnyReference",
]

log = logging.getLogger(__name__)

# Bump when the conversion changes: it is part of the cache key.
CONVERTER_VERSION = 1

ANNY_LICENCE = (
    "Derived from Anny (https://github.com/naver/anny): code Apache-2.0 (NAVER Corp.), model data "
    "from MakeHuman (mesh, blend shapes, rig, weights) CC0 1.0. Converted to the SMPL layout by "
    "gst.body.anny_default; redistributable. Please credit Anny and MakeHuman."
)

# (x, y, z)_SMPL = ANNY_TO_SMPL_AXES @ (x, y, z)_Anny: Anny is Z up and faces -Y.
ANNY_TO_SMPL_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

ANNY_BONE_FOR_JOINT: dict[str, str] = {
    "pelvis": "root",
    "left_hip": "upperleg01.L", "right_hip": "upperleg01.R",
    "spine1": "spine04",
    "left_knee": "lowerleg01.L", "right_knee": "lowerleg01.R",
    "spine2": "spine02",
    "left_ankle": "foot.L", "right_ankle": "foot.R",
    "spine3": "spine01",
    "left_foot": "toe3-1.L", "right_foot": "toe3-1.R",  # ball of the foot
    "neck": "neck01",
    "left_collar": "clavicle.L", "right_collar": "clavicle.R",
    "head": "head",
    "left_shoulder": "upperarm01.L", "right_shoulder": "upperarm01.R",
    "left_elbow": "lowerarm01.L", "right_elbow": "lowerarm01.R",
    "left_wrist": "wrist.L", "right_wrist": "wrist.R",
    "left_hand": "finger3-1.L", "right_hand": "finger3-1.R",  # middle knuckle
}  # fmt: skip

# Anny segmentation label -> our part name (None: label the vertex by its dominant joint).
_SEGMENT_TO_PART: dict[str, str | None] = {
    "body": None, "head": None, "hand.L": "left_hand", "hand.R": "right_hand",
    "foot.L": "left_foot", "foot.R": "right_foot", "eye_front.L": "left_eye",
    "eye_front.R": "right_eye", "eye_back.L": "eye_cavity", "eye_back.R": "eye_cavity",
    "eye_cavity.L": "eye_cavity", "eye_cavity.R": "eye_cavity", "mouth_cavity": "mouth_cavity",
    "tongue": "mouth_cavity",
}  # fmt: skip
_DROPPED_SEGMENTS = ("tongue",)


def default_cache_dir() -> Path:
    """``$GST_CACHE_DIR`` if set, else ``~/.cache/gst-capture``."""
    env = os.environ.get("GST_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "gst-capture"


def _import_anny():
    try:
        import anny
    except ImportError as err:  # pragma: no cover - anny is a declared dependency
        raise ImportError(
            "the open default body needs the 'anny' package (pip install anny==0.6.2)"
        ) from err
    return anny


def _anny_version() -> str:
    """Anny's installed version, without importing it (its import initialises warp, ~4 s)."""
    try:
        return importlib.metadata.version("anny")
    except importlib.metadata.PackageNotFoundError as err:
        raise ImportError(
            "the open default body needs the 'anny' package (pip install anny==0.6.2)"
        ) from err


# --------------------------------------------------------------------------- Anny access
class AnnyReference:
    """Anny itself, wrapped for conversion and for checking the converted model against it.

    Everything returned is in SMPL axes. Builds ``anny.Anny()`` (about 60 s and 1.5 GB the first
    time on a machine, cached by Anny under ``~/.cache/anny``; 0.3 s afterwards).
    """

    def __init__(self) -> None:
        anny = _import_anny()
        self.anny_version = anny.__version__
        self.model = anny.Anny()  # rig 'anny', topology 'anny', 'local-ref' pose deltas, float64
        self.bone_labels: list[str] = list(self.model.bone_labels)
        self.bone_parents: list[int] = [int(p) for p in self.model.bone_parents]
        self.joint_bones = np.array(
            [self.bone_labels.index(ANNY_BONE_FOR_JOINT[n]) for n in SMPL_JOINT_NAMES]
        )
        self.axes = torch.as_tensor(ANNY_TO_SMPL_AXES, dtype=self.model.dtype)
        self.merge_targets = _merge_targets(self.bone_labels, self.bone_parents, self.joint_bones)

    @property
    def dtype(self) -> torch.dtype:
        return self.model.dtype

    def sample_phenotypes(self, n: int, age_range: tuple[float, float], seed: int) -> torch.Tensor:
        """(n, 6) phenotypes from Anny's calibrated distribution, morphological age uniform in
        ``age_range`` years (Anny's own default spans 0-90)."""
        from anny.shape_distribution import SimpleShapeDistribution

        lo, hi = (torch.tensor(float(a), dtype=self.dtype) for a in age_range)
        dist = SimpleShapeDistribution(
            self.model, morphological_age_distribution=torch.distributions.Uniform(lo, hi)
        )
        state = torch.random.get_rng_state()
        try:
            torch.manual_seed(seed)
            _, kwargs = dist.sample(n)
        finally:
            torch.random.set_rng_state(state)
        return torch.stack([kwargs[k].to(self.dtype) for k in self.model.phenotype_labels], dim=1)

    def blendshape_coefficients(self, phenotypes: torch.Tensor) -> torch.Tensor:
        """(n, K) coefficients of Anny's (compacted) blend shapes for (n, 6) phenotypes."""
        empty = phenotypes.new_zeros(len(phenotypes), 0)
        # Anny's forward() computes these internally and does not return them.
        return self.model._get_phenotype_blendshape_coefficients(phenotypes, empty, empty)

    def to_smpl_axes(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.axes.T

    def rest(self, phenotypes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest vertices (n, V_anny, 3) and the 24 mapped bone heads (n, 24, 3), SMPL axes."""
        out = self.model(phenotype_kwargs=phenotypes)
        heads = out["rest_bone_heads"][:, self.joint_bones]
        return self.to_smpl_axes(out["rest_vertices"]), self.to_smpl_axes(heads)

    def posed(
        self, phenotypes: torch.Tensor, rotmats: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Pose Anny, with its own kinematics, from SMPL-layout local rotations (n, 24, 3, 3) in
        SMPL axes. Returns posed vertices (n, V_anny, 3) and the posed heads of the 24 mapped
        bones (n, 24, 3), SMPL axes, with the root bone's head at the origin.

        Anny's 'local-*' deltas are relative to its reference orientations, which differ from
        its rest pose, so we drive it in its 'world-orient' parameterisation instead: every bone
        gets the world rotation of the joint that takes its skinning weights (composed along
        the SMPL tree), times its own rest orientation, and Anny places each bone head by
        moving it with its parent. With the other bones following their joint like this, Anny
        and the converted model agree exactly up to shape and regressor errors, except for
        fingers and toes, which Anny turns about their own bones and we about the hand and foot
        joints.
        """
        rotmats = rotmats.to(self.dtype)
        n = rotmats.shape[0]
        world = [rotmats[:, 0]]
        for j in range(1, NUM_JOINTS):
            world.append(world[SMPL_PARENTS[j]] @ rotmats[:, j])
        world_anny = self.axes.T @ torch.stack(world, dim=1) @ self.axes  # (n, 24, 3, 3)
        rest = self.model(phenotype_kwargs=phenotypes)["rest_bone_poses"].expand(n, -1, -1, -1)
        deltas = torch.eye(4, dtype=self.dtype).repeat(n, len(self.bone_labels), 1, 1)
        deltas[..., :3, :3] = world_anny[:, self.merge_targets] @ rest[..., :3, :3]
        out = self.model(
            pose_parameters=deltas,
            phenotype_kwargs=phenotypes,
            pose_parameterization="world-orient",
        )
        heads = out["bone_poses"][:, self.joint_bones, :3, 3]
        return self.to_smpl_axes(out["vertices"]), self.to_smpl_axes(heads)


# --------------------------------------------------------------------------- conversion pieces
def _merge_targets(
    bone_labels: list[str], bone_parents: list[int], joint_bones: np.ndarray
) -> np.ndarray:
    """For every Anny bone, the SMPL joint that takes its skinning weights."""
    kept = {int(b): j for j, b in enumerate(joint_bones)}
    hand = {"L": SMPL_JOINT_NAMES.index("left_hand"), "R": SMPL_JOINT_NAMES.index("right_hand")}
    foot = {"L": SMPL_JOINT_NAMES.index("left_foot"), "R": SMPL_JOINT_NAMES.index("right_foot")}
    targets = np.empty(len(bone_labels), dtype=np.int64)
    for b, label in enumerate(bone_labels):
        side = label.rsplit(".", 1)[-1]
        if label.startswith("finger"):
            targets[b] = hand[side]
        elif label.startswith("toe"):
            targets[b] = foot[side]
        else:
            a = b
            while a not in kept:
                a = bone_parents[a]
                if a < 0:
                    raise ValueError(f"Anny bone {label!r} has no kept ancestor")
            targets[b] = kept[a]
    return targets


def _segment_faces(ref: AnnyReference) -> tuple[list[str], np.ndarray]:
    """Anny's segmentation label of every face (its UV centre's colour in Anny's part map)."""
    import yaml
    from anny.face_segmentation import get_face_segmentation_mask
    from anny.paths import get_anny_root_dir

    meta = get_anny_root_dir() / "data" / "segmentation" / "body_parts_segmentation.yaml"
    labels = list(yaml.safe_load(meta.read_text())["colors"])
    unknown = [label for label in labels if label not in _SEGMENT_TO_PART]
    if unknown:
        raise ValueError(f"{meta}: unknown Anny segmentation labels {unknown}")
    face_label = np.full(len(ref.model.faces), -1, dtype=np.int64)
    for i, label in enumerate(labels):
        face_label[get_face_segmentation_mask(ref.model, [label]).cpu().numpy()] = i
    if (face_label < 0).any():
        raise ValueError(f"{int((face_label < 0).sum())} Anny faces have no segmentation label")
    return labels, face_label


def _vertex_majority(
    faces: np.ndarray, face_label: np.ndarray, n_vertices: int, n_labels: int
) -> np.ndarray:
    counts = np.zeros((n_vertices, n_labels), dtype=np.int64)
    np.add.at(counts, (faces.ravel(), np.repeat(face_label, 3)), 1)
    return counts.argmax(axis=1)


def _pca_shape_space(coeffs: np.ndarray, blend: np.ndarray, template: np.ndarray, num_betas: int):
    """Exact PCA of x = template + coeffs @ blend over the sampled coefficients.

    The covariance of the meshes is blend^T Sigma blend with Sigma the (K, K) covariance of the
    coefficients, so its eigenvectors come from the thin SVD of blend^T L, Sigma = L L^T: a
    (3V, K) matrix instead of a (3V, 3V) one. Returns mean (3V,), directions (3V, nb) scaled to
    one standard deviation, the variance of every component (K,) and the projection matrix
    P (K, nb) with betas = (c - mean_c) @ P.
    """
    mean_c = coeffs.mean(axis=0)
    sigma = np.cov(coeffs, rowvar=False)
    evals, evecs = np.linalg.eigh(sigma)
    root = evecs * np.sqrt(np.clip(evals, 0.0, None))
    u, s, _ = np.linalg.svd(blend.T @ root, full_matrices=False)
    u = u[:, :num_betas]
    # Deterministic signs: the largest entry of each direction is positive.
    signs = np.sign(u[np.abs(u).argmax(axis=0), np.arange(num_betas)])
    u = u * signs
    std = s[:num_betas]
    directions = u * std
    projection = (blend @ u) / std
    return template + mean_c @ blend, directions, s**2, projection


def _joint_shape_model(
    coeffs: np.ndarray, projection: np.ndarray, template_j: np.ndarray, blend_j: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Best linear prediction of the bone heads from the betas over the shape distribution.

    Heads are h = template_j + c @ blend_j and betas b = (c - mean_c) @ P are white, so the
    least-squares map is h ~ mean_h + J_dirs b with J_dirs = cov(h, b) = blend_j^T Sigma P.
    Returns mean_h (J, 3) and J_dirs (J, 3, nb).
    """
    mean_h = template_j + np.einsum("k,kjd->jd", coeffs.mean(axis=0), blend_j)
    sigma = np.cov(coeffs, rowvar=False)
    return mean_h, np.einsum("kjd,kl,lb->jdb", blend_j, sigma, projection)


def _fit_joint_regressor(
    mean_v: np.ndarray,
    directions: np.ndarray,
    mean_j: np.ndarray,
    joint_dirs: np.ndarray,
    support_size: int,
    radius: float,
) -> scipy.sparse.csr_matrix:
    """A regressor R (J, V) with R @ (mean_v + directions @ b) = mean_j + joint_dirs @ b for
    every beta vector b, and rows summing to one (translation equivariance).

    Per joint these are 3 (nb + 1) + 1 linear equations in its ``support_size`` nearest vertices;
    among the exact solutions we take the one of least weighted norm sum r_v^2 / p_v, with
    p_v = exp(-(d_v / radius)^2) favouring vertices near the joint. A non-negative, local
    regressor like SMPL's cannot follow Anny's joints across shapes (about 5 mm mean error in
    our tests against 1.2 mm for this one), so this one is exact on the shape space but is
    neither local nor convex: use the model's joints, not this regressor on posed meshes.
    mean_v (V, 3), directions (V, 3, nb), mean_j (J, 3), joint_dirs (J, 3, nb).
    """
    n_vertices, _, nb = directions.shape
    rows, cols, vals = [], [], []
    for j in range(mean_j.shape[0]):
        dist = np.linalg.norm(mean_v - mean_j[j], axis=1)
        support = np.sort(np.argsort(dist)[:support_size])
        prior = np.exp(-((dist[support] / radius) ** 2))
        # Equations: coordinates of the mean mesh, of every direction, and the partition of unity.
        a = np.concatenate(
            [mean_v[support].T[None], directions[support].transpose(2, 1, 0)], axis=0
        )
        a = np.vstack([a.reshape(-1, len(support)), np.ones((1, len(support)))])
        b = np.append(np.concatenate([mean_j[j][None], joint_dirs[j].T], axis=0).reshape(-1), 1.0)
        r = prior * (a.T @ np.linalg.solve((a * prior) @ a.T, b))
        rows += [j] * len(support)
        cols += support.tolist()
        vals += r.tolist()
    return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(mean_j.shape[0], n_vertices))


# --------------------------------------------------------------------------- build + cache
def _build(
    num_betas: int,
    age_range: tuple[float, float],
    num_shape_samples: int,
    support_size: int,
    regressor_radius: float,
    seed: int,
) -> BodyModelData:
    t0 = time.perf_counter()
    ref = AnnyReference()
    model = ref.model
    axes = ANNY_TO_SMPL_AXES

    # Mesh: drop the tongue, a closed component inside the mouth.
    faces_all = model.faces.cpu().numpy().astype(np.int64)
    seg_labels, face_seg = _segment_faces(ref)
    dropped = np.isin(face_seg, [seg_labels.index(s) for s in _DROPPED_SEGMENTS])
    n_anny = model.template_vertices.shape[0]
    used = np.zeros(n_anny, dtype=bool)
    used[faces_all[~dropped].ravel()] = True
    source_ids = np.flatnonzero(used)
    new_index = np.full(n_anny, -1, dtype=np.int64)
    new_index[source_ids] = np.arange(len(source_ids))
    faces = new_index[faces_all[~dropped]]
    V = len(source_ids)

    # Skinning weights merged onto the 24 joints.
    dense = torch.zeros(n_anny, len(ref.bone_labels), dtype=torch.float64)
    dense.scatter_add_(
        1, model.vertex_bone_indices.long().cpu(), model.vertex_bone_weights.cpu().double()
    )
    targets = ref.merge_targets
    merge = np.zeros((len(ref.bone_labels), NUM_JOINTS))
    merge[np.arange(len(targets)), targets] = 1.0
    weights = dense.numpy()[source_ids] @ merge
    weights /= weights.sum(axis=1, keepdims=True)

    # Shape space, in SMPL axes, over Anny's phenotype distribution.
    phen = ref.sample_phenotypes(num_shape_samples, age_range, seed)
    coeffs = ref.blendshape_coefficients(phen).detach().cpu().numpy()
    blend_v = model.blendshapes.detach().cpu().numpy()[:, source_ids] @ axes.T  # (K, V, 3)
    template_v = model.template_vertices.detach().cpu().numpy()[source_ids] @ axes.T
    blend_j = model.bone_heads_blendshapes.detach().cpu().numpy()[:, ref.joint_bones] @ axes.T
    template_j = model.template_bone_heads.detach().cpu().numpy()[ref.joint_bones] @ axes.T
    _check_coefficients(ref, phen[:4], coeffs[:4], source_ids, blend_v, template_v)
    mean_v, directions, variances, projection = _pca_shape_space(
        coeffs, blend_v.reshape(len(blend_v), -1), template_v.reshape(-1), num_betas
    )
    shapedirs = directions.reshape(V, 3, num_betas)

    # Joint regressor: regressed joints of the model's meshes follow Anny's bone heads as well
    # as any linear function of the betas can.
    mean_j, joint_dirs = _joint_shape_model(coeffs, projection, template_j, blend_j)
    regressor = _fit_joint_regressor(
        mean_v.reshape(V, 3), shapedirs, mean_j, joint_dirs, support_size, regressor_radius
    )

    # Part labels: Anny's segmentation where it is specific, the dominant joint elsewhere.
    vertex_seg = _vertex_majority(faces_all, face_seg, n_anny, len(seg_labels))[source_ids]
    part_labels = parts_from_weights(weights, SMPL_JOINT_NAMES)
    for i, seg in enumerate(seg_labels):
        part = _SEGMENT_TO_PART[seg]
        if part is not None:
            part_labels[vertex_seg == i] = PART_NAMES.index(part)
    # Anny's 'head' segment reaches down the neck: its vertices stay head or neck by joint,
    # never torso (a few of them are dominated by the collar or spine joints).
    head_seg = vertex_seg == seg_labels.index("head")
    neck_or_head = np.isin(part_labels, [PART_NAMES.index("head"), PART_NAMES.index("neck")])
    part_labels[head_seg & ~neck_or_head] = PART_NAMES.index("head")

    ratio = variances / variances.sum()
    data = BodyModelData(
        v_template=mean_v.reshape(V, 3),
        shapedirs=shapedirs,
        J_regressor=regressor,
        weights=weights,
        parents=np.array(SMPL_PARENTS, dtype=np.int64),
        faces=faces,
        joint_names=SMPL_JOINT_NAMES,
        part_labels=part_labels,
        part_names=PART_NAMES,
        posedirs=None,
        name="anny-default",
        source=(
            f"anny {ref.anny_version} (rig 'anny', topology 'anny'), converter "
            f"v{CONVERTER_VERSION}, PCA of {num_shape_samples} shapes, ages "
            f"{age_range[0]:g}-{age_range[1]:g}"
        ),
        licence=ANNY_LICENCE,
        shape_variance=variances[:num_betas],
        shape_variance_ratio=ratio[:num_betas],
        source_vertex_ids=source_ids,
    )
    log.info(
        "built the Anny default body in %.1f s (%d vertices, %d betas explain %.4f%% of shape "
        "variance)",
        time.perf_counter() - t0,
        V,
        num_betas,
        100 * ratio[:num_betas].sum(),
    )
    return data.validate()


def _check_coefficients(ref, phen, coeffs, source_ids, blend_v, template_v) -> None:
    """Guard against Anny API drift: our coefficients must rebuild Anny's own rest meshes."""
    rest, _ = ref.rest(phen)
    ours = template_v[None] + np.einsum("nk,kvd->nvd", coeffs, blend_v)
    err = np.abs(rest.detach().cpu().numpy()[:, source_ids] - ours).max()
    if err > 1e-6:
        raise RuntimeError(
            f"Anny blend-shape coefficients do not reproduce Anny's rest mesh "
            f"(max error {err:.2e} m); is anny {ref.anny_version} supported?"
        )


def build_anny_default(
    cache_dir: str | Path | None = None,
    *,
    num_betas: int = 16,
    age_range: tuple[float, float] = (12.0, 80.0),
    num_shape_samples: int = 5000,
    support_size: int = 3200,
    regressor_radius: float = 0.2,
    seed: int = 0,
    rebuild: bool = False,
) -> BodyModelData:
    """The open default body in SMPL layout, built from Anny once and then read from the cache.

    Args:
        cache_dir: folder for the cached .npz (default ``$GST_CACHE_DIR`` or
            ``~/.cache/gst-capture``; the file goes to ``<cache_dir>/body/``).
        num_betas: PCA shape components kept (>= 10). SMPL and GST use the first 10; the
            components are nested, so passing fewer betas is the same as a smaller model.
        age_range: morphological ages (years) of the shape distribution the PCA is fitted to.
        num_shape_samples: shapes sampled from Anny's distribution for the PCA.
        support_size, regressor_radius: vertices each joint's regressor may use, and the
            length scale (m) of its preference for near ones (see _fit_joint_regressor).
        seed: RNG seed of the shape samples (the build is deterministic for given arguments).
        rebuild: ignore an existing cache file.
    Every argument and the Anny and converter versions are part of the cache key.
    """
    if num_betas < 10:
        raise ValueError(f"num_betas must be at least 10, got {num_betas}")
    key = {
        "converter": CONVERTER_VERSION,
        "anny": _anny_version(),
        "num_betas": num_betas,
        "age_range": [float(a) for a in age_range],
        "num_shape_samples": num_shape_samples,
        "support_size": support_size,
        "regressor_radius": regressor_radius,
        "seed": seed,
    }
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    folder = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    path = folder / "body" / f"anny-default-smpl24-{digest}.npz"
    if path.is_file() and not rebuild:
        try:
            return BodyModelData.load_npz(path)
        except (ValueError, OSError, KeyError) as err:
            log.warning("ignoring unreadable cached body %s (%s); rebuilding", path, err)
    log.info("building the Anny default body (first time only, about a minute) -> %s", path)
    data = _build(
        num_betas, tuple(age_range), num_shape_samples, support_size, regressor_radius, seed
    )
    data.save_npz(path)
    return data
