"""The render-free sampler: the synthetic worlds' pose convention, exact crop geometry,
visibility, determinism."""

import numpy as np
import pytest
import torch

from gst.body import load_body_model
from gst.lift.errors import LIMB_LANDMARKS
from gst.lift.sampler import ARM_CHAINS, LEG_CHAINS, LiftSampler, lean_rotations
from synth.animate import pose_person
from synth.motions import generate_motion
from synth.skeleton import mirror_angles
from synth.world import heading_rotation


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


@pytest.fixture(scope="module")
def sampler(body):
    return LiftSampler(body, seed=3)


def test_poses_follow_the_synthetic_worlds_convention(body, sampler):
    """Authored angles -> local rotations as synth.animate poses a person (mean shape)."""
    clip = generate_motion(["kick"], 12, 10.0, np.random.default_rng(0), heading=0.7)
    betas = np.zeros(body.num_betas, np.float32)
    track = pose_person(body, betas, clip, 1)
    local = sampler.local_rotations(torch.as_tensor(clip.angles, dtype=torch.float32))
    root = torch.as_tensor(heading_rotation(clip.heading), dtype=torch.float32) @ local[:, 0]
    out = body(torch.zeros(12, body.num_betas), local[:, 1:], root, torch.zeros(12, 3))
    ours = out.joints - out.joints[:, :1]
    theirs = torch.as_tensor(track.joints - track.joints[:, :1], dtype=torch.float32)
    assert (ours - theirs).norm(dim=-1).max() < 1e-4  # metres


def test_batch_geometry_is_exact(sampler):
    b = sampler.sample(64)
    S = b.crop_size
    proj = b.joints_cam / b.joints_cam[..., 2:]
    uv = proj @ b.K.transpose(1, 2)
    assert torch.allclose(uv[..., :2], b.joints2d, atol=1e-3)
    assert (b.joints_cam[..., 2] > 0).all()
    # the HMR2 window (1.2 x the body's box, jittered) keeps the pelvis near the middle
    assert (b.joints2d[:, 0] - S / 2).abs().max() < 0.3 * S
    # the global orientation is in the camera frame; body joints come from the local rotations
    assert torch.allclose(
        b.rotmats_cam @ b.rotmats_cam.transpose(-1, -2),
        torch.eye(3).expand(64, 24, 3, 3),
        atol=1e-4,
    )
    assert b.landmarks.shape == (64, 12, 3) and b.presence.shape == (64,)
    assert ((b.landmarks[..., 2] >= 0) & (b.landmarks[..., 2] <= 1)).all()


def test_visibility_rate_is_like_the_rendered_worlds(sampler):
    """Rendered landmark worlds: 17% of limb joints occluded (docs/landmark_prior.md)."""
    b = sampler.sample(2000)
    ji = [j for _, j in LIMB_LANDMARKS]
    occluded = 1 - b.visible[:, ji].float().mean().item()
    assert 0.10 < occluded < 0.26
    # joints outside the crop are never visible
    out = ((b.joints2d < 0) | (b.joints2d > b.crop_size - 1)).any(-1)
    assert not (b.visible & out).any()


def test_sampler_is_deterministic_and_varied(body):
    a = LiftSampler(body, seed=5).sample(16)
    b = LiftSampler(body, seed=5).sample(16)
    c = LiftSampler(body, seed=6).sample(16)
    assert torch.equal(a.landmarks, b.landmarks) and torch.equal(a.rotmats_cam, b.rotmats_cam)
    assert not torch.allclose(a.joints_cam, c.joints_cam)
    assert a.betas[:, :10].std() > 0.3 and (a.betas[:, 10:] == 0).all()


def test_all_33_landmarks_sit_on_the_virtual_markers(body):
    s = LiftSampler(body, seed=4, landmark_set="all")
    b = s.sample(64)
    assert b.landmarks.shape == (64, 33, 3) and b.reference2d.shape == (64, 33, 2)
    # the limb markers lie near their joints (a few cm: within 6% of the crop), the nose near
    # the head joint, and every marker inherits its anchor joint's visibility
    ji = [j for _, j in LIMB_LANDMARKS]
    li = [m for m, _ in LIMB_LANDMARKS]
    near = (b.reference2d[:, li] - b.joints2d[:, ji]).norm(dim=-1) / b.crop_size
    assert near.median() < 0.03 and near.max() < 0.12
    assert ((b.reference2d[:, 0] - b.joints2d[:, 15]).norm(dim=-1) / b.crop_size).max() < 0.15
    anchors = s.markers.anchors
    assert torch.equal(b.reference_visible, b.visible[:, anchors] & b.reference_visible)


def test_markers_outside_the_crop_are_never_visible(body):
    """A marker off the crop is not seen even where its anchor joint is (16 of 33792 were
    marked visible in a batch of 1024)."""
    b = LiftSampler(body, seed=0, landmark_set="all", arm_mix_p=0.3, leg_mix_p=0.3).sample(1024)
    S = b.crop_size
    outside = ((b.reference2d < 0) | (b.reference2d > S - 1)).any(-1)
    assert outside.any()
    assert not (outside & b.reference_visible).any()


def _flip_rate(s: LiftSampler, n: int = 512) -> float:
    from gst.lift.errors import flipped_crops, pair_swaps

    b = s.sample(n)
    det = b.landmarks[..., :2].numpy() / b.crop_size
    ref = b.reference2d.numpy() / b.crop_size
    inside = b.reference_visible.numpy() & (b.landmarks[..., 2] > 0.5).numpy()
    swapped, countable = pair_swaps(det, ref, inside, s.lset.pairs)
    return float(flipped_crops(swapped, countable).mean())


def test_whole_body_flips_can_be_left_out(body):
    # the measured noise model flips about 6 % of motion crops as a whole; without the flips
    # only the independent per-group swaps remain (a crop rarely has most pairs swapped)
    with_flips = _flip_rate(LiftSampler(body, seed=7))
    without = _flip_rate(LiftSampler(body, seed=7, whole_body_flips=False))
    assert with_flips > 0.04
    assert without < with_flips / 3


def test_random_share_sets_the_bank(body):
    none = LiftSampler(body, seed=2, random_share=0.0)
    some = LiftSampler(body, seed=2, random_share=0.2)
    default = LiftSampler(body, seed=2)
    assert not none.bank_random.any()
    assert some.bank_random.float().mean().item() == pytest.approx(0.2, abs=0.01)
    assert default.bank_random.float().mean().item() == pytest.approx(1 / 3, abs=0.01)
    motion_only = LiftSampler(body, seed=2, random_share=0.0, uniform_p=0.0).sample(64)
    assert not motion_only.random_pose.any()
    assert default.sample(256).random_pose.float().mean() > 0.2
    with pytest.raises(ValueError, match="random_share"):
        LiftSampler(body, random_share=1.0)


def test_lean_tilts_the_whole_body_about_horizontal_axes(body):
    R = lean_rotations(4000, np.radians(12.0), torch.Generator().manual_seed(0))
    up = torch.tensor([0.0, 0.0, 1.0])
    tilt = torch.rad2deg(torch.arccos((R @ up)[:, 2].clamp(-1, 1)))
    # |N(0, 12 deg)|: median 0.674 x 12 = 8.1 deg
    assert abs(float(tilt.median()) - 8.1) < 0.5
    # about a horizontal axis: no turn about the vertical (a point on the up axis' side stays
    # in the plane through the up axis and itself)
    side = torch.tensor([1.0, 0.0, 0.0])
    assert torch.allclose(torch.linalg.det(R), torch.ones(4000), atol=1e-5)
    axis_z = R[:, 1, 0] - R[:, 0, 1]  # z of the rotation axis x 2 sin(angle)
    assert axis_z.abs().max() < 1e-5 and (R @ side).norm(dim=-1).sub(1).abs().max() < 1e-5
    # and the sampler's bodies change only when asked to lean
    same = LiftSampler(body, seed=5).sample(8)
    again = LiftSampler(body, seed=5, lean_deg=0.0).sample(8)
    leant = LiftSampler(body, seed=5, lean_deg=12.0).sample(8)
    assert torch.equal(same.joints_cam, again.joints_cam)
    assert not torch.allclose(same.rotmats_cam[:, 0], leant.rotmats_cam[:, 0])


def test_limb_mixing_swaps_whole_chains_from_other_bank_poses(body):
    B = 64
    base, _ = LiftSampler(body, seed=4)._angles(B)
    arms = LiftSampler(body, seed=4, arm_mix_p=1.0)
    mixed, _ = arms._angles(B)
    arm_joints = [j for chain in ARM_CHAINS for j in chain]
    rest = [j for j in range(24) if j not in arm_joints]
    # everything but the arms is the unmixed pose (the mixing draws come after it)
    assert torch.equal(mixed[:, rest], base[:, rest])
    # each arm is a whole chain of one bank pose, as authored or mirrored
    bank = arms.bank.numpy()
    donors = np.concatenate([bank, mirror_angles(bank.copy())])
    for chain in ARM_CHAINS:
        got = mixed[:, list(chain)].numpy()  # (B, 5, 3)
        gap = np.abs(got[:, None] - donors[None, :, list(chain)]).max(axis=(2, 3))  # (B, 2P)
        assert (gap.min(axis=1) < 1e-6).all()
        assert (np.abs(got - base[:, list(chain)].numpy()).max(axis=(1, 2)) > 1e-3).mean() > 0.9
    # legs likewise with leg_mix_p; off (the default) the batches are the unmixed sampler's
    legs, _ = LiftSampler(body, seed=4, leg_mix_p=1.0)._angles(B)
    leg_joints = [j for chain in LEG_CHAINS for j in chain]
    assert not torch.equal(legs[:, leg_joints], base[:, leg_joints])
    assert torch.equal(legs[:, arm_joints], base[:, arm_joints])
    off = LiftSampler(body, seed=4, arm_mix_p=0.0, leg_mix_p=0.0).sample(8)
    assert torch.equal(off.joints_cam, LiftSampler(body, seed=4).sample(8).joints_cam)
    with pytest.raises(ValueError, match="arm_mix_p"):
        LiftSampler(body, arm_mix_p=1.5)


def test_uniform_joint_limit_poses_bend_the_limbs_they_name(body):
    """`uniform_p`'s poses (every angle uniform within the joint limits, which are about the
    T-pose's axes) were applied as the body's local rotations directly; the open body's rest
    pose has the arms lowered, so an elbow 'flexion' turned the forearm across the body: the
    left wrist lay inside the torso in 3.9 % of them (0.6 % of the authored bank's poses). They
    now pass through the rest corrections as the authored angles do."""
    from gst.body.skeleton import SMPL_JOINT_NAMES

    sampler = LiftSampler(body, seed=5, uniform_p=1.0)
    b = sampler.sample(1500)
    joints = body(None, b.rotmats_cam[:, 1:], torch.eye(3).expand(len(b), 3, 3)).joints
    i = SMPL_JOINT_NAMES.index
    wrist, pelvis, chest = (joints[:, i(n)] for n in ("left_wrist", "pelvis", "spine3"))
    inside = (
        ((wrist[:, 0] - pelvis[:, 0]).abs() < 0.11)
        & ((wrist[:, 2] - chest[:, 2]).abs() < 0.09)
        & (wrist[:, 1] > pelvis[:, 1] - 0.05)
        & (wrist[:, 1] < chest[:, 1])
    )
    assert inside.float().mean() < 0.01


@pytest.mark.parametrize(
    "setting, value",
    [
        ("landmark_set", "hands"),
        ("crop_size", 0),
        ("zbuffer", 0),
        ("box_jitter", -0.1),
        ("lean_deg", -5.0),
        ("blend_p", 1.5),
        ("uniform_p", -0.1),
        ("occluder_p", 2.0),
    ],
)
def test_bad_settings_are_refused_by_name(body, setting, value):
    """A crop size of 0 gave NaN landmarks, a z-buffer of 0 an index error at the first batch,
    an unknown landmark set a bare KeyError, and probabilities outside [0, 1] were taken."""
    with pytest.raises(ValueError, match=setting):
        LiftSampler(body, **{setting: value})


def test_noise_models_must_cover_both_pose_kinds(body):
    from gst.lift.noise import load_models

    with pytest.raises(ValueError, match="pose kind"):
        LiftSampler(body, noise={"motion": load_models()["motion"]})


def test_a_body_moved_in_front_of_its_camera_keeps_r_t_consistent(body):
    """A camera inside the body (placed at the volume's centre, radius 0): the body is pushed
    in front of it; the batch's t moves with it, so R, t still map the world body (standing on
    the floor at the centre) to joints_cam. It kept the camera's own t."""
    from gst.lift.sampler import _CameraPool

    s = LiftSampler(body, seed=1)
    R = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # looks along +x
    K = torch.tensor([[300.0, 0.0, 240.0], [0.0, 300.0, 180.0], [0.0, 0.0, 1.0]])
    s.cams = _CameraPool(
        R[None], torch.tensor([[0.0, 1.0, 0.0]]), K[None], torch.zeros(1, 3), torch.zeros(1)
    )  # camera centre (0, 0, 1)
    b = s.sample(8)
    world = (b.joints_cam - b.t[:, None]) @ b.R
    assert torch.allclose(world[:, 0, :2], torch.zeros(8, 2), atol=1e-4)  # pelvis at the spot
    assert (world[..., 2].amin(1) > -1e-4).all()
