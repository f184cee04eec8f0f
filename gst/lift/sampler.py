"""Render-free training samples for the landmark -> body path: a posed body, a camera, the crop
the pipeline would cut around it, and the BlazePose detections it would see (simulated).

Everything is batched torch after a one-off setup (about a second):

- poses: a bank of authored joint angles (`synth.motions`: every motion of the library under
  several seeds, plus programmes of two to three crossfaded motions, plus `random_static_poses`
  drawn within the joint limits, `random_share` of the bank), each mirrored with probability
  1/2 and blended with a second pose with probability `blend_p`; a fraction `uniform_p` comes
  from `gst.body.joint_limits.sample_body_pose` (every angle uniform in its limits, scaled)
  instead;
- shapes: the first 10 betas ~ N(0, 0.9^2) clipped to +-2.5 (as `synth.people.sample_betas`);
- cameras: a pool of rigs of every kind (`synth.rigs.make_rig`: dome, h36m, hall; horizontal
  field of view 40-75 degrees), the person standing on the floor at a uniform spot of the
  kind's capture volume, facing a uniform heading;
- crops: the box of the projected body (a vertex subset), jittered in scale and centre as mask
  boxes are, then the HMR2 square window (`gst.data.crop`: 1.2 x the longer side) at
  `crop_size`, with its own K;
- visibility: a coarse z-buffer of the body's own vertices in the crop (a joint more than
  0.25 m behind the surface it projects onto is occluded, the synthetic truth's rule), joints
  outside the crop, and with probability `occluder_p` a random box standing for another
  person in front;
- detections: `gst.lift.noise.LandmarkNoise.simulate` on the true landmark positions (the
  joints for the 12 limb landmarks, `landmark_set="limbs"`; the virtual markers of
  `gst.body.markers` for all 33, `landmark_set="all"`) and their visibility;
  `whole_body_flips=False` leaves out the whole-body left/right flips (a person read as facing
  the other way): from landmarks alone such a sample's answer cannot be told, so training on it
  teaches the network to hedge (docs/landmark_prior.md).

The body pose follows the synthetic worlds' convention: angles authored against the T-pose are
turned into the body model's local rotations with its rest corrections at the mean shape
(`synth.skeleton.rest_corrections`), so the poses have the same meaning as in rendered scenes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from gst.body import BodyModel
from gst.body.joint_limits import sample_body_pose
from gst.body.markers import MarkerModel
from gst.body.rotations import axis_angle_to_matrix
from gst.body.skeleton import SMPL_JOINT_NAMES
from gst.body.subsets import vertex_subset
from gst.data.crop import CROP_ENLARGE
from gst.lift.errors import LANDMARK_SETS
from gst.lift.noise import POSE_KINDS, LandmarkNoise, load_models
from synth.motions import MOTIONS, generate_motion, random_static_poses
from synth.rigs import RIG_KINDS, make_rig
from synth.skeleton import PARENTS, clip_to_limits, mirror_angles, rest_corrections
from synth.world import heading_rotation

OCCLUSION_DEPTH = 0.25  # metres, as the synthetic truth's visibility rule

# the joints of each arm (collar to hand) and each leg (hip to foot): the chains `limb mixing`
# swaps between poses
ARM_CHAINS = tuple(
    tuple(
        SMPL_JOINT_NAMES.index(f"{side}_{part}")
        for part in ("collar", "shoulder", "elbow", "wrist", "hand")
    )
    for side in ("left", "right")
)
LEG_CHAINS = tuple(
    tuple(SMPL_JOINT_NAMES.index(f"{side}_{part}") for part in ("hip", "knee", "ankle", "foot"))
    for side in ("left", "right")
)


@dataclass
class LiftBatch:
    """One batch of simulated crops (B samples). Pixel units are the crop's."""

    landmarks: torch.Tensor  # (B, L, 3) simulated landmarks of the set: u, v, confidence
    presence: torch.Tensor  # (B,)
    K: torch.Tensor  # (B, 3, 3) crop intrinsics
    R: torch.Tensor  # (B, 3, 3) world -> camera
    t: torch.Tensor  # (B, 3)
    rotmats_cam: torch.Tensor  # (B, 24, 3, 3): [0] global orientation in the camera, then local
    betas: torch.Tensor  # (B, nb)
    joints_cam: torch.Tensor  # (B, 24, 3) metres
    joints2d: torch.Tensor  # (B, 24, 2) crop px
    visible: torch.Tensor  # (B, 24) bool
    reference2d: torch.Tensor  # (B, L, 2) true landmark positions, crop px
    reference_visible: torch.Tensor  # (B, L) bool
    random_pose: torch.Tensor  # (B,) bool: a random pose (simulated with that kind's noise)
    crop_size: int

    def __len__(self) -> int:
        return int(self.K.shape[0])


def _pose_bank(
    rng: np.random.Generator,
    fps: float = 10.0,
    seconds: float = 6.0,
    random_share: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(P, 24, 3) authored Euler angles (radians, model signs) of the library's motions and of
    random poses (`random_share` of the bank; None: one third), and (P,) True for the random
    ones."""
    n = int(fps * seconds)
    clips = []
    names = list(MOTIONS)
    for _ in range(4):
        for name in names:
            clips.append(generate_motion([name], n, fps, rng).angles)
    for _ in range(24):
        prog = list(rng.choice(names, size=int(rng.integers(2, 4)), replace=False))
        clips.append(generate_motion(prog, n, fps, rng).angles)
    n_motion = sum(len(c) for c in clips)
    if random_share is None:
        n_random = n_motion // 2
    elif 0 <= random_share < 1:
        n_random = int(round(random_share / (1 - random_share) * n_motion))
    else:
        raise ValueError(f"random_share must be in [0, 1), got {random_share}")
    if n_random:
        clips.append(random_static_poses(n_random, rng).angles)
    bank = np.concatenate(clips).astype(np.float32)
    return bank, np.arange(len(bank)) >= n_motion


def _euler_xyz(angles: torch.Tensor) -> torch.Tensor:
    """Intrinsic XYZ Euler angles (..., 3) -> Rx Ry Rz (..., 3, 3) (scipy's 'XYZ')."""
    a, b, c = angles.unbind(-1)
    ca, sa, cb, sb, cc, sc = a.cos(), a.sin(), b.cos(), b.sin(), c.cos(), c.sin()
    return torch.stack(
        [
            torch.stack([cb * cc, -cb * sc, sb], -1),
            torch.stack([sa * sb * cc + ca * sc, -sa * sb * sc + ca * cc, -sa * cb], -1),
            torch.stack([-ca * sb * cc + sa * sc, ca * sb * sc + sa * cc, ca * cb], -1),
        ],
        -2,
    )


@dataclass(frozen=True)
class _CameraPool:
    R: torch.Tensor  # (C, 3, 3)
    t: torch.Tensor  # (C, 3)
    K: torch.Tensor  # (C, 3, 3)
    centre: torch.Tensor  # (C, 3) volume centre of the camera's rig
    radius: torch.Tensor  # (C,) volume radius


def _camera_pool(rng: np.random.Generator, rigs_per_kind: int = 40) -> _CameraPool:
    Rs, ts, Ks, cs, rs = [], [], [], [], []
    for kind, d in RIG_KINDS.items():
        for _ in range(rigs_per_kind):
            n = int(rng.integers(4, 9))
            rig = make_rig(
                kind,
                n_cameras=n,
                width=480,
                height=360,
                fov_deg=float(rng.uniform(40, 75)),
                seed=int(rng.integers(1 << 30)),
            )
            for cam in rig.cameras:
                Rs.append(cam.R)
                ts.append(cam.t)
                Ks.append(cam.K)
                cs.append(d.volume_center)
                rs.append(d.volume_radius)

    def f(x):
        return torch.as_tensor(np.asarray(x), dtype=torch.float32)

    return _CameraPool(f(Rs), f(ts), f(Ks), f(cs), f(rs))


def lean_rotations(B: int, spread: float, gen: torch.Generator) -> torch.Tensor:
    """(B, 3, 3) world rotations (z up) by an angle ~ N(0, spread) (radians) about a uniformly
    random horizontal axis: a body turned by one leans that far from upright."""
    psi = torch.rand(B, generator=gen) * (2 * np.pi)
    axis = torch.stack([psi.cos(), psi.sin(), torch.zeros(B)], -1)
    theta = spread * torch.randn(B, generator=gen)
    return axis_angle_to_matrix(axis * theta[:, None])


class LiftSampler:
    """`sample(batch_size) -> LiftBatch`; deterministic from `seed`. `lean_deg`: the spread
    (normal, degrees) of a lean of the whole body about a random horizontal axis (0: bodies
    stand as the motion library authored them). `noise_scale`: a factor on the noise model's
    scatter and gross-error rates (1: BlazePose as measured on our rendered crops)."""

    def __init__(
        self,
        body: BodyModel,
        noise: LandmarkNoise | dict[str, LandmarkNoise] | None = None,
        crop_size: int = 256,
        landmark_set: str = "limbs",
        seed: int = 0,
        blend_p: float = 0.3,
        uniform_p: float = 0.1,
        occluder_p: float = 0.1,
        box_jitter: float = 0.05,
        zbuffer: int = 64,
        random_share: float | None = None,
        whole_body_flips: bool = True,
        lean_deg: float = 0.0,
        noise_scale: float = 1.0,
        arm_mix_p: float = 0.0,
        leg_mix_p: float = 0.0,
    ):
        if landmark_set not in LANDMARK_SETS:
            raise ValueError(
                f"landmark_set must be one of {sorted(LANDMARK_SETS)}, got {landmark_set!r}"
            )
        # refused up front: a crop size or z-buffer below 1 gave NaN landmarks or an index
        # error at the first batch, and probabilities outside [0, 1] were taken silently
        for name, v in (("crop_size", crop_size), ("zbuffer", zbuffer)):
            if not v >= 1:
                raise ValueError(f"{name} must be >= 1, got {v}")
        for name, v in (("box_jitter", box_jitter), ("lean_deg", lean_deg)):
            if not v >= 0:
                raise ValueError(f"{name} must be >= 0, got {v}")
        for name, p in (("blend_p", blend_p), ("uniform_p", uniform_p), ("occluder_p", occluder_p)):
            if not 0 <= p <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {p}")
        if isinstance(noise, dict) and not set(POSE_KINDS) <= set(noise):
            raise ValueError(
                f"noise must hold a model per pose kind {POSE_KINDS}, got {sorted(noise)}"
            )
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0x11F7]))
        self.body = body
        # BlazePose is much worse on unusual poses (docs/landmark_prior.md): one noise model for
        # the library's motions, one for random poses; a single model serves both if given
        self.lset = LANDMARK_SETS[landmark_set]
        noise = load_models(set_name=landmark_set) if noise is None else noise
        self.noise = noise if isinstance(noise, dict) else {"motion": noise, "random": noise}
        if not whole_body_flips:  # the person read as facing the other way: not simulated
            self.noise = {k: replace(m, flip=0.0) for k, m in self.noise.items()}
        self.noise = {k: m.scaled(noise_scale) for k, m in self.noise.items()}
        for m in self.noise.values():
            if m.set_name != landmark_set:
                raise ValueError(
                    f"noise model of set '{m.set_name}' given for landmark set '{landmark_set}'"
                )
        self.markers = MarkerModel.load() if landmark_set != "limbs" else None
        self.crop_size = int(crop_size)
        self.blend_p, self.uniform_p, self.occluder_p = blend_p, uniform_p, occluder_p
        self.box_jitter, self.zbuffer = box_jitter, zbuffer
        self.lean = float(np.radians(lean_deg))
        for name, p in (("arm_mix_p", arm_mix_p), ("leg_mix_p", leg_mix_p)):
            if not 0 <= p <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {p}")
        self.arm_mix_p, self.leg_mix_p = float(arm_mix_p), float(leg_mix_p)
        self.gen = torch.Generator().manual_seed(int(rng.integers(1 << 62)))
        bank, random = _pose_bank(rng, random_share=random_share)
        self.bank, self.bank_random = torch.from_numpy(bank), torch.from_numpy(random)
        self.cams = _camera_pool(rng)
        self.vids = torch.from_numpy(vertex_subset(body, "1723")).long()
        with torch.no_grad():
            rest = body.rest_joints(torch.zeros(1, body.num_betas, dtype=body.dtype))[0]
        # rest joints in SMPL axes -> the per-joint corrections of the synthetic worlds
        C = rest_corrections(rest.double().numpy())
        self.C = torch.as_tensor(C, dtype=torch.float32)
        self.parents = torch.as_tensor(np.asarray(PARENTS), dtype=torch.long)

    # -- pieces ----------------------------------------------------------------------------

    def _rand(self, *shape) -> torch.Tensor:
        return torch.rand(*shape, generator=self.gen)

    def _angles(self, B: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 24, 3) authored angles: bank draws, mirrored, sometimes blended; and (B,) True
        where the pose is mostly a random one."""
        idx = torch.randint(len(self.bank), (2, B), generator=self.gen)
        a, b = self.bank[idx[0]].numpy(), self.bank[idx[1]].numpy()
        mir = self._rand(2, B).numpy() < 0.5
        a[mir[0]] = mirror_angles(a[mir[0]])
        b[mir[1]] = mirror_angles(b[mir[1]])
        w = self._rand(B).numpy() * (self._rand(B).numpy() < self.blend_p)
        # a convex blend of in-limit angles stays in the limits; clip anyway (soft, cheap)
        out = clip_to_limits((1 - w)[:, None, None] * a + w[:, None, None] * b)
        if self.arm_mix_p > 0 or self.leg_mix_p > 0:  # no draws when off: batches as before
            out = self._mix_limbs(out)
        rnd = torch.where(
            torch.from_numpy(w > 0.5), self.bank_random[idx[1]], self.bank_random[idx[0]]
        )
        return torch.as_tensor(out, dtype=torch.float32), rnd

    def _mix_limbs(self, out: np.ndarray) -> np.ndarray:
        """Each arm (leg) of each pose takes, with probability `arm_mix_p` (`leg_mix_p`), its
        angles from another bank pose (mirrored half the time): combinations the library never
        authored, which real people make (docs/landmark_prior.md "Limb mixing": the lab
        capture's single-image bodies follow their landmarks more closely). Joint angles are
        local to their parent, so a swapped chain stays within its joints' limits."""
        B = len(out)
        donor = self.bank[torch.randint(len(self.bank), (B,), generator=self.gen)].numpy()
        flip = self._rand(B).numpy() < 0.5
        donor[flip] = mirror_angles(donor[flip])
        for chains, p in ((ARM_CHAINS, self.arm_mix_p), (LEG_CHAINS, self.leg_mix_p)):
            if p <= 0:
                continue
            for chain in chains:
                take = np.flatnonzero(self._rand(B).numpy() < p)
                out[np.ix_(take, chain)] = donor[np.ix_(take, chain)]
        return out

    def local_rotations(self, angles: torch.Tensor) -> torch.Tensor:
        """Authored angles -> the body model's local rotations (B, 24, 3, 3), root authored."""
        return self._from_t_pose(_euler_xyz(angles))

    def _from_t_pose(self, A: torch.Tensor) -> torch.Tensor:
        """(B, 24, 3, 3) rotations about the T-pose's axes -> the body model's local rotations,
        through its rest corrections (the root as given)."""
        Cp = self.C[self.parents.clamp_min(0)]
        local = Cp.transpose(-1, -2) @ A @ self.C
        local[:, 0] = A[:, 0]
        return local

    def _betas(self, B: int) -> torch.Tensor:
        nb = self.body.num_betas
        out = torch.zeros(B, nb)
        k = min(nb, 10)
        out[:, :k] = (torch.randn(B, k, generator=self.gen) * 0.9).clamp(-2.5, 2.5)
        return out

    def sample(self, B: int) -> LiftBatch:
        with torch.no_grad():
            return self._sample(B)

    def _sample(self, B: int) -> LiftBatch:
        S = self.crop_size
        angles, random_pose = self._angles(B)
        local = self.local_rotations(angles)
        uni = self._rand(B) < self.uniform_p
        if uni.any():
            # the joint limits' axes are the T-pose's, as the authored angles' are: through the
            # rest corrections too (applied as they were to a body whose rest pose has the arms
            # lowered, an elbow's flexion turned the forearm across the body)
            A = _euler_xyz(angles[uni])
            A[:, 1:] = sample_body_pose(int(uni.sum()), self.gen, scale=0.8)
            local[uni] = self._from_t_pose(A)
        random_pose = random_pose | uni
        betas = self._betas(B)
        heading = self._rand(B) * (2 * np.pi) - np.pi
        H = torch.as_tensor(heading_rotation(heading.double().numpy()), dtype=torch.float32)
        root_world = H @ local[:, 0]
        if self.lean > 0:  # the whole body leans about a random horizontal axis
            root_world = lean_rotations(B, self.lean, self.gen) @ root_world
        # camera and position in its capture volume
        ci = torch.randint(len(self.cams.R), (B,), generator=self.gen)
        R, t, K = self.cams.R[ci], self.cams.t[ci], self.cams.K[ci]
        r = self.cams.radius[ci] * self._rand(B).sqrt()
        phi = self._rand(B) * 2 * np.pi
        spot = self.cams.centre[ci, :2] + torch.stack([r * phi.cos(), r * phi.sin()], -1)
        dt = self.body.dtype
        out = self.body(
            betas.to(dt),
            local[:, 1:].to(dt),
            root_world.to(dt),
            torch.zeros(B, 3, dtype=dt),
            vertex_ids=self.vids,
            return_transforms=self.markers is not None,
        )
        verts, joints = out.vertices.float(), out.joints.float()
        marks = self.markers.positions(out).float() if self.markers is not None else None
        shift = torch.zeros(B, 3)
        shift[:, :2] = spot - joints[:, 0, :2]
        shift[:, 2] = -verts[..., 2].amin(1)  # lowest point on the floor (airborne poses too)
        verts, joints = verts + shift[:, None], joints + shift[:, None]
        if marks is not None:
            marks = marks + shift[:, None]
        vc = verts @ R.transpose(1, 2) + t[:, None]
        jc = joints @ R.transpose(1, 2) + t[:, None]
        mc = marks @ R.transpose(1, 2) + t[:, None] if marks is not None else None
        # bodies behind or grazing a camera: move them in front (rare; keeps the batch full)
        bad = vc[..., 2].amin(1) < 0.5
        if bad.any():
            push = (0.5 - vc[bad, :, 2].amin(1)).clamp_min(0) + 1.0
            vc[bad, :, 2] += push[:, None]
            jc[bad, :, 2] += push[:, None]
            if mc is not None:
                mc[bad, :, 2] += push[:, None]
            t = t.clone()  # the camera steps back: the batch's R, t still map the world body
            t[bad, 2] += push
        uv = vc[..., :2] / vc[..., 2:] @ K[:, :2, :2].transpose(1, 2) + K[:, None, :2, 2]
        lo, hi = uv.amin(1), uv.amax(1)
        centre = (lo + hi) / 2 + (hi - lo) * self.box_jitter * torch.randn(B, 2, generator=self.gen)
        size = (hi - lo).amax(-1) * torch.exp(self.box_jitter * torch.randn(B, generator=self.gen))
        side = CROP_ENLARGE * size
        x0 = centre - side[:, None] / 2  # pixel-centre coordinates of the window's edge
        s = S / side
        Kc = torch.zeros(B, 3, 3)
        Kc[:, 0, 0] = K[:, 0, 0] * s
        Kc[:, 1, 1] = K[:, 1, 1] * s
        Kc[:, :2, 2] = (K[:, :2, 2] - x0) * s[:, None] - 0.5
        Kc[:, 2, 2] = 1.0
        j2 = jc[..., :2] / jc[..., 2:] @ Kc[:, :2, :2].transpose(1, 2) + Kc[:, None, :2, 2]
        v2 = vc[..., :2] / vc[..., 2:] @ Kc[:, :2, :2].transpose(1, 2) + Kc[:, None, :2, 2]
        visible = self._visibility(v2, vc[..., 2], j2, jc[..., 2])
        if mc is not None:
            ref = mc[..., :2] / mc[..., 2:] @ Kc[:, :2, :2].transpose(1, 2) + Kc[:, None, :2, 2]
            # a marker's visibility is its anchor joint's, and only where it lands in the crop
            in_crop = ((ref >= 0) & (ref <= self.crop_size - 1)).all(-1)
            ref_vis = visible[:, self.markers.anchors] & (mc[..., 2] > 0) & in_crop
        else:
            ref, ref_vis = j2[:, list(self.lset.joints)], visible[:, list(self.lset.joints)]
        det = torch.zeros(B, len(self.lset), 3)
        presence = torch.zeros(B)
        for kind, sel in (("motion", ~random_pose), ("random", random_pose)):
            if sel.any():
                det[sel], presence[sel] = self.noise[kind].simulate(
                    ref[sel], ref_vis[sel], j2[sel], S, self.gen
                )
        rot_cam = local.clone()
        rot_cam[:, 0] = R @ root_world
        return LiftBatch(
            landmarks=det,
            presence=presence,
            K=Kc,
            R=R,
            t=t,
            rotmats_cam=rot_cam,
            betas=betas,
            joints_cam=jc,
            joints2d=j2,
            visible=visible,
            reference2d=ref,
            reference_visible=ref_vis,
            random_pose=random_pose,
            crop_size=S,
        )

    def _visibility(self, v2, vz, j2, jz) -> torch.Tensor:
        """Joints in the crop, not behind their own body's surface, not behind an occluder."""
        B, S, G = v2.shape[0], self.crop_size, self.zbuffer
        cell = (v2 / S * G).floor().long()
        inside = ((cell >= 0) & (cell < G)).all(-1)
        flat = (cell[..., 1].clamp(0, G - 1) * G + cell[..., 0].clamp(0, G - 1)) + (
            torch.arange(B)[:, None] * G * G
        )
        depth = torch.full((B * G * G,), float("inf"))
        depth.scatter_reduce_(0, flat[inside], vz[inside], reduce="amin")
        jc = (j2 / S * G).floor().long()
        in_crop = ((j2 >= 0) & (j2 <= S - 1)).all(-1)
        jflat = (jc[..., 1].clamp(0, G - 1) * G + jc[..., 0].clamp(0, G - 1)) + (
            torch.arange(B)[:, None] * G * G
        )
        surface = depth[jflat]
        visible = in_crop & (surface > jz - OCCLUSION_DEPTH)
        # another person in front: a random box of 20-60% of the crop's width, full height
        occ = self._rand(B) < self.occluder_p
        w = (0.2 + 0.4 * self._rand(B)) * S
        x0 = self._rand(B) * (S - w)
        covered = (j2[..., 0] >= x0[:, None]) & (j2[..., 0] <= (x0 + w)[:, None]) & occ[:, None]
        return visible & ~covered
