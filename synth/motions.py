"""Procedural sports motions as per-joint Euler angles, a root path and a flight height.

Every motion is a function of time with per-person variation (tempo, amplitude, style, small
smooth noise), authored anatomically in degrees against the SMPL T-pose (see
`synth.skeleton` for the axis and sign conventions), then softly clipped to joint limits.
Keyframed motions are interpolated with PCHIP (C1, no overshoot); cyclic gaits are closed-form.
Motions are chained into a per-person program with crossfades, so the result is smooth in time.

Vertical placement is not decided here: `synth.animate` puts the lowest body point on the floor
(plus `lift`, the flight height of jumps and running strides) once the body model has posed
the person, so feet stay on the floor whatever the body shape.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from synth.skeleton import JOINT_LIMITS, JOINT_NAMES, NUM_JOINTS, J, clip_to_limits, mirror_angles

GRAVITY = 9.81


@dataclass(frozen=True)
class MotionClip:
    """A motion sampled at `fps`.

    angles:   (T, 24, 3) authored Euler XYZ angles in radians, model signs (right side
              mirrored), index 0 is the root tilt relative to upright.
    position: (T, 2) world XY of the pelvis.
    heading:  (T,) world heading in radians (see `synth.world`).
    lift:     (T,) height of the lowest body point above the floor, metres (0 = in contact).
    labels:   per-frame motion name.
    smooth:   False for independent random poses (no temporal coherence).
    """

    fps: float
    angles: np.ndarray
    position: np.ndarray
    heading: np.ndarray
    lift: np.ndarray
    labels: tuple[str, ...]
    smooth: bool = True

    def __post_init__(self):
        T = len(self.labels)
        expected = {"angles": (T, NUM_JOINTS, 3), "position": (T, 2), "heading": (T,), "lift": (T,)}
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(
                    f"MotionClip.{name} has shape {getattr(self, name).shape}, expected {shape}"
                )

    @property
    def n_frames(self) -> int:
        return len(self.labels)


@dataclass
class _Segment:
    """Output of one motion generator, in the mover's own frame (anatomical degrees)."""

    angles: np.ndarray  # (T, 24, 3) anatomical degrees
    forward: np.ndarray  # (T,) cumulative displacement along the heading, metres
    turn: np.ndarray  # (T,) cumulative heading change, radians
    lift: np.ndarray  # (T,) metres


# ----------------------------------------------------------------------------------------------
# Authoring helpers


def _pose(**joints) -> dict[str, tuple[float, float, float]]:
    """Pose dict from keyword args; `both_<joint>` sets left and right (anatomical signs)."""
    out: dict[str, tuple[float, float, float]] = {}
    for key, xyz in joints.items():
        xyz = tuple(float(v) for v in xyz)
        if key.startswith("both_"):
            base = key[5:]
            out[f"left_{base}"] = xyz
            out[f"right_{base}"] = xyz
        else:
            if key not in J:
                raise KeyError(f"unknown joint '{key}' in motion keyframe")
            out[key] = xyz
    return out


# Relaxed standing posture: arms hang slightly away from the body, soft knees and elbows.
STAND = _pose(
    both_shoulder=(0, 0, -78),
    both_elbow=(0, -12, 0),
    both_knee=(4, 0, 0),
    both_hip=(-3, 0, 2),
    both_ankle=(-1, 0, -2),
)


def _with(base: dict, **changes) -> dict:
    pose = dict(base)
    pose.update(_pose(**changes))
    return pose


def _swap_sides(pose: dict) -> dict:
    """The pose with its left and right joints exchanged, central joints kept as they are (not
    a mirror image: their twist and lean stay). Anatomical signs are alike on both sides, so
    the angles move over unchanged."""
    out = {}
    for name, xyz in pose.items():
        side, _, joint = name.partition("_")
        if side in ("left", "right"):
            name = f"{'right' if side == 'left' else 'left'}_{joint}"
        out[name] = xyz
    return out


def _to_array(pose: dict) -> np.ndarray:
    arr = np.zeros((NUM_JOINTS, 3))
    for name, xyz in pose.items():
        arr[J[name]] = xyz
    return arr


def _flat_feet(arr: np.ndarray, sides: tuple[str, ...]) -> np.ndarray:
    """Set the ankle flexion of planted legs so the sole is level: the sagittal angles of root,
    hip, knee and ankle add up to zero."""
    for side in sides:
        arr[J[f"{side}_ankle"], 0] = -(
            arr[0, 0] + arr[J[f"{side}_hip"], 0] + arr[J[f"{side}_knee"], 0]
        )
    return arr


@dataclass(frozen=True)
class _Key:
    time: float
    pose: dict
    forward: float = 0.0
    turn: float = 0.0
    planted: tuple[str, ...] = ("left", "right")


def _keyframed(keys: list[_Key], t: np.ndarray) -> _Segment:
    """Interpolate keyframes (looped with their period) at times t."""
    times = np.array([k.time for k in keys])
    period = times[-1]
    arrays = np.stack([_flat_feet(_to_array(k.pose), k.planted) for k in keys]).reshape(
        len(keys), -1
    )
    fwd = np.array([k.forward for k in keys])
    trn = np.array([k.turn for k in keys])
    if not np.allclose(arrays[0], arrays[-1]):
        raise ValueError("keyframed motion must end in its starting pose to loop")
    # Wrap one key around each end so the slopes at the loop seam agree (C1 when looping);
    # displacements accumulate over cycles (a turn turns further, a step moves on).
    ext_t = np.r_[times[-2] - period, times, period + times[1]]
    ext_a = np.concatenate([arrays[-2:-1], arrays, arrays[1:2]])
    ext_f = np.r_[fwd[-2] - fwd[-1], fwd, fwd[-1] + fwd[1]]
    ext_r = np.r_[trn[-2] - trn[-1], trn, trn[-1] + trn[1]]
    cycles, tau = np.divmod(t, period)
    ang = PchipInterpolator(ext_t, ext_a, axis=0)(tau).reshape(len(t), NUM_JOINTS, 3)
    f = PchipInterpolator(ext_t, ext_f)(tau) + cycles * fwd[-1]
    r = PchipInterpolator(ext_t, ext_r)(tau) + cycles * trn[-1]
    return _Segment(ang, f, r, np.zeros_like(t))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _bump(phase: np.ndarray, centre: float, power: float) -> np.ndarray:
    """Smooth periodic bump in [0, 1] peaking at `centre` (radians)."""
    return ((1 + np.cos(phase - centre)) / 2) ** power


def _gait(t: np.ndarray, cadence: np.ndarray, style: dict) -> tuple[np.ndarray, np.ndarray]:
    """Cyclic gait angles (T, 24, 3) in anatomical degrees, and the stride phase (T,).
    `cadence` is strides per second (T,); the left heel strikes at phase 0, left thigh forward."""
    phase = (
        2
        * np.pi
        * np.concatenate([[0.0], np.cumsum((cadence[1:] + cadence[:-1]) / 2 * np.diff(t))])
    )
    phase = phase + style.get("phase0", 0.0)
    a = np.tile(_to_array(STAND), (len(t), 1, 1))
    for side, off in (("left", 0.0), ("right", np.pi)):
        ph = phase + off
        a[:, J[f"{side}_hip"], 0] = style["hip_bias"] - style["hip_amp"] * np.cos(ph)
        a[:, J[f"{side}_hip"], 2] = 3.0
        a[:, J[f"{side}_knee"], 0] = (
            style["knee_stance"] * _bump(ph, 0.5, 2)
            + style["knee_swing"] * _bump(ph, style["swing_peak"], 3)
            + 3
        )
        a[:, J[f"{side}_ankle"], 0] = style["ankle_push"] * _bump(ph, 3.6, 4) - style[
            "ankle_dorsi"
        ] * _bump(ph, 0.9, 2)
        a[:, J[f"{side}_shoulder"], 0] = style["arm_amp"] * np.cos(ph) + style["arm_bias"]
        a[:, J[f"{side}_shoulder"], 2] = style["arm_abduction"]
        a[:, J[f"{side}_elbow"], 1] = -(style["elbow"] + style["elbow_amp"] * np.cos(ph + np.pi))
    a[:, J["spine2"], 1] = style["twist"] * np.cos(phase)
    a[:, J["spine3"], 1] = style["twist"] * 0.5 * np.cos(phase)
    a[:, 0, 1] = -style["twist"] * 0.6 * np.cos(phase)
    a[:, 0, 0] = style["lean"]
    a[:, J["neck"], 0] = -style["lean"] * 0.6  # keep the gaze level
    return a, phase


# ----------------------------------------------------------------------------------------------
# Motion generators: f(t, rng) -> _Segment, anatomical degrees, mover's frame


# `_gait` styles, one column per gait. A (low, high) pair is drawn uniformly per clip, row by
# row in this order; a number is used as is. Walk and run keep a steady cadence (strides/s) and
# speed (m/s); a sprint start accelerates (`_sprint_start`), so it has neither.
_GAIT_NAMES = ("walk", "run", "sprint")
# fmt: off
_GAIT_TABLE = {
    #                walk             run              sprint
    "cadence":       ((0.85, 1.0),    (1.3, 1.5),      None),
    "speed":         ((1.1, 1.5),     (2.6, 3.6),      None),
    "hip_bias":      (-5,             -12,             -22),
    "hip_amp":       ((20, 26),       (30, 38),        40),
    "knee_stance":   (15,             22,              40),
    "knee_swing":    ((50, 60),       (75, 95),        105),
    "swing_peak":    (4.5,            4.4,             4.4),
    "ankle_push":    (15,             25,              30),
    "ankle_dorsi":   (8,              10,              8),
    "arm_amp":       ((12, 22),       (35, 50),        55),
    "arm_bias":      (0,              -5,              -5),
    "arm_abduction": (-80,            -75,             -78),
    "elbow":         ((12, 25),       (80, 95),        85),
    "elbow_amp":     (6,              12,              15),
    "twist":         (5,              9,               8),
    "lean":          ((1, 4),         (5, 10),         0),
    "phase0":        ((0, 2 * np.pi), (0, 2 * np.pi),  np.pi),
}
# fmt: on
_GAITS = {
    gait: {key: row[col] for key, row in _GAIT_TABLE.items()}
    for col, gait in enumerate(_GAIT_NAMES)
}


def _steady_gait(
    t: np.ndarray, rng: np.random.Generator, gait: dict
) -> tuple[np.ndarray, np.ndarray, float]:
    """Gait angles and phase (`_gait`) at a constant cadence, and the speed, drawn from `gait`
    (a column of `_GAIT_TABLE`)."""
    style = {k: rng.uniform(*v) if isinstance(v, tuple) else v for k, v in gait.items()}
    ang, phase = _gait(t, np.full_like(t, style["cadence"]), style)
    return ang, phase, style["speed"]


def _walk(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    ang, _, speed = _steady_gait(t, rng, _GAITS["walk"])
    return _Segment(ang, speed * t, np.zeros_like(t), np.zeros_like(t))


def _run(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    ang, phase, speed = _steady_gait(t, rng, _GAITS["run"])
    flight = GRAVITY * 0.1**2 / 8  # peak height of a ~0.1 s flight phase, twice per stride
    lift = flight * np.clip(np.sin(2 * phase - 0.6), 0, None) ** 2
    return _Segment(ang, speed * t, np.zeros_like(t), lift)


def _sprint_start(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    t_set = rng.uniform(0.4, 0.7)
    vmax, tau = rng.uniform(6.0, 8.0), rng.uniform(0.9, 1.3)
    crouch = _to_array(
        _with(
            STAND,
            pelvis=(62, 0, 0),
            left_hip=(-112, 0, 5),
            left_knee=(105, 0, 0),
            right_hip=(-58, 0, 5),
            right_knee=(118, 0, 0),
            both_shoulder=(-70, 0, -86),
            both_elbow=(0, -5, 0),
            neck=(-30, 0, 0),
            spine1=(8, 0, 0),
        )
    )
    crouch = _flat_feet(crouch, ("left",))
    crouch[J["right_ankle"], 0] = 35  # rear foot on its toes
    drive = np.clip(t - t_set, 0, None)
    speed = vmax * (1 - np.exp(-drive / tau))
    cadence = 1.2 + 0.6 * (1 - np.exp(-drive / tau))
    gait, _ = _gait(t, cadence, _GAITS["sprint"])
    gait[:, 0, 0] = 12 + 38 * np.exp(-drive / 0.6)  # body lean decays while accelerating
    w = _smoothstep((t - t_set) / 0.35)[:, None, None]
    ang = (1 - w) * crouch[None] + w * gait
    forward = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) / 2 * np.diff(t))])
    return _Segment(ang, forward, np.zeros_like(t), np.zeros_like(t))


def _jump(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    depth = rng.uniform(0.8, 1.1)
    flight_time = rng.uniform(0.38, 0.5)
    s = dict(
        pelvis=(35 * depth, 0, 0),
        both_hip=(-85 * depth, 0, 4),
        both_knee=(95 * depth, 0, 0),
        both_shoulder=(55, 0, -82),
        both_elbow=(0, -15, 0),
        spine2=(10, 0, 0),
        neck=(-20, 0, 0),
    )
    t0, t1, t2 = 0.3, 0.75, 0.95
    t3 = t2 + flight_time
    keys = [
        _Key(0.0, STAND),
        _Key(t0, STAND),
        _Key(t1, _with(STAND, **s)),
        _Key(
            t2,
            _with(
                STAND,
                pelvis=(5, 0, 0),
                both_hip=(-5, 0, 3),
                both_knee=(5, 0, 0),
                both_shoulder=(-110, 0, -72),
                both_elbow=(0, -20, 0),
            ),
            planted=(),
        ),
        _Key(
            t2 + 0.5 * flight_time,
            _with(
                STAND,
                both_hip=(-12, 0, 4),
                both_knee=(15, 0, 0),
                both_ankle=(30, 0, 0),
                both_shoulder=(-140, 0, -70),
            ),
            planted=(),
        ),
        _Key(
            t3,
            _with(
                STAND,
                both_hip=(-20, 0, 4),
                both_knee=(20, 0, 0),
                both_ankle=(25, 0, 0),
                both_shoulder=(-60, 0, -75),
            ),
            planted=(),
        ),
        _Key(
            t3 + 0.25,
            _with(
                STAND,
                pelvis=(25, 0, 0),
                both_hip=(-60, 0, 4),
                both_knee=(70, 0, 0),
                both_shoulder=(-40, 0, -80),
            ),
        ),
        _Key(t3 + 0.75, STAND),
        _Key(t3 + 1.0, STAND),
    ]
    seg = _keyframed(keys, t)
    tau = np.mod(t, keys[-1].time)
    x = np.clip((tau - t2) / flight_time, 0, 1)
    seg.lift = GRAVITY * flight_time**2 / 2 * x * (1 - x)  # ballistic: h_max = g T^2 / 8
    return seg


def _squat(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    period = rng.uniform(2.0, 2.8)
    d = rng.uniform(0.8, 1.05)
    bottom = _with(
        STAND,
        pelvis=(35 * d, 0, 0),
        both_hip=(-112 * d, 0, 12),
        both_knee=(112 * d, 0, 0),
        both_shoulder=(-85 * d, 0, -88),
        both_elbow=(0, -5, 0),
        spine2=(8, 0, 0),
        neck=(-25, 0, 0),
    )
    keys = [
        _Key(0.0, STAND),
        _Key(0.15 * period, STAND),
        _Key(0.5 * period, bottom),
        _Key(0.6 * period, bottom),
        _Key(period, STAND),
    ]
    return _keyframed(keys, t)


def _lunge(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    p = rng.uniform(1.4, 1.8)
    step = rng.uniform(0.35, 0.45)
    hands = dict(both_shoulder=(-5, 0, -60), both_elbow=(0, -105, 0))
    low_l = _with(
        STAND,
        left_hip=(-85, 0, 3),
        left_knee=(92, 0, 0),
        right_hip=(22, 0, 3),
        right_knee=(80, 0, 0),
        right_ankle=(35, 0, 0),
        **hands,
    )
    low_r = _swap_sides(low_l)
    up = _with(STAND, **hands)
    keys = [
        _Key(0.0, up),
        _Key(0.45 * p, low_l, forward=step, planted=("left",)),
        _Key(0.6 * p, low_l, forward=step, planted=("left",)),
        _Key(p, up),
        _Key(1.45 * p, low_r, forward=step, planted=("right",)),
        _Key(1.6 * p, low_r, forward=step, planted=("right",)),
        _Key(2 * p, up),
    ]
    return _keyframed(keys, t)


def _kick(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    """Right-footed instep kick (mirror for left-footed players)."""
    power = rng.uniform(0.85, 1.1)
    arms_out = dict(
        left_shoulder=(-40, 0, -35), right_shoulder=(30, 0, -45), both_elbow=(0, -25, 0)
    )
    keys = [
        _Key(0.0, STAND),
        _Key(
            0.3,
            _with(STAND, left_hip=(-25, 0, 3), right_hip=(20, 0, 3), right_knee=(40, 0, 0)),
            forward=0.3,
        ),
        _Key(
            0.6,
            _with(
                STAND,
                left_hip=(-10, 0, 5),
                left_knee=(20, 0, 0),
                right_hip=(35 * power, 0, 5),
                right_knee=(105, 0, 0),
                right_ankle=(30, 0, 0),
                spine2=(0, 12, 0),
                pelvis=(0, 0, 6),
                **arms_out,
            ),
            forward=0.6,
            planted=("left",),
        ),
        _Key(
            0.78,
            _with(
                STAND,
                left_hip=(-8, 0, 5),
                left_knee=(12, 0, 0),
                right_hip=(-35 * power, 0, 5),
                right_knee=(65, 0, 0),
                right_ankle=(40, 0, 0),
                spine2=(-8, -10, 0),
                pelvis=(-5, 0, 6),
                **arms_out,
            ),
            forward=0.65,
            planted=("left",),
        ),
        _Key(
            0.98,
            _with(
                STAND,
                left_hip=(-5, 0, 5),
                left_knee=(15, 0, 0),
                right_hip=(-85 * power, 0, 5),
                right_knee=(10, 0, 0),
                right_ankle=(30, 0, 0),
                spine2=(10, -18, 0),
                left_shoulder=(-20, 0, -40),
                right_shoulder=(45, 0, -60),
            ),
            forward=0.7,
            planted=("left",),
        ),
        _Key(1.35, _with(STAND, right_hip=(-20, 0, 3), right_knee=(10, 0, 0)), forward=0.85),
        _Key(1.8, STAND, forward=0.9),
    ]
    return _keyframed(keys, t)


def _throw(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    """Right-handed overhand throw with a step of the left foot."""
    v = rng.uniform(0.85, 1.1)
    keys = [
        _Key(0.0, STAND),
        _Key(
            0.45,
            _with(
                STAND,
                left_hip=(-35, 0, 5),
                left_knee=(20, 0, 0),
                right_hip=(12, 0, 5),
                right_knee=(12, 0, 0),
                spine2=(-5, -25 * v, 0),
                spine3=(-5, -15 * v, 0),
                right_shoulder=(35, 60, 0),
                right_elbow=(0, -95, 0),
                left_shoulder=(-70, 0, -20),
                left_elbow=(0, -20, 0),
                neck=(0, 30, 0),
            ),
            forward=0.3,
        ),
        _Key(
            0.68,
            _with(
                STAND,
                left_hip=(-40, 0, 5),
                left_knee=(25, 0, 0),
                right_hip=(15, 0, 5),
                right_knee=(20, 0, 0),
                spine2=(15, 25 * v, 0),
                spine3=(10, 15 * v, 0),
                right_shoulder=(-120, 10, -25),
                right_elbow=(0, -25, 0),
                left_shoulder=(-20, 0, -75),
                left_elbow=(0, -40, 0),
            ),
            forward=0.4,
            planted=("left",),
        ),
        _Key(
            0.9,
            _with(
                STAND,
                left_hip=(-35, 0, 5),
                left_knee=(30, 0, 0),
                right_hip=(10, 0, 5),
                right_knee=(40, 0, 0),
                right_ankle=(35, 0, 0),
                spine2=(30, 30, 0),
                right_shoulder=(-60, 0, -75),
                right_elbow=(0, -20, 0),
                left_shoulder=(10, 0, -80),
            ),
            forward=0.45,
            planted=("left",),
        ),
        _Key(1.5, STAND, forward=0.55),
    ]
    return _keyframed(keys, t)


def _turn(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    angle = np.pi * rng.uniform(0.6, 1.0) * rng.choice([-1.0, 1.0])
    step_l = _with(
        STAND, left_hip=(-22, 0, 6), left_knee=(40, 0, 0), spine2=(0, 10 * np.sign(angle), 0)
    )
    step_r = _swap_sides(step_l)
    keys = [
        _Key(0.0, STAND),
        _Key(0.25, step_l, turn=0.25 * angle, planted=("right",)),
        _Key(0.5, STAND, turn=0.5 * angle),
        _Key(0.75, step_r, turn=0.75 * angle, planted=("left",)),
        _Key(1.0, STAND, turn=angle),
        _Key(1.6, STAND, turn=angle),
    ]
    return _keyframed(keys, t)


def _idle(t: np.ndarray, rng: np.random.Generator) -> _Segment:
    p = rng.uniform(3.0, 4.5)
    a = np.tile(_to_array(STAND), (len(t), 1, 1))
    w = 2 * np.pi * t / p
    a[:, 0, 2] = 2.5 * np.sin(w)  # weight shift
    a[:, J["left_hip"], 2] += -2.5 * np.sin(w)
    a[:, J["right_hip"], 2] += 2.5 * np.sin(w)
    a[:, J["neck"], 1] = 20 * np.sin(0.5 * w + 1.0)
    a[:, J["left_shoulder"], 0] = -10 * np.sin(w + 0.5) - 5
    a[:, J["right_shoulder"], 0] = 12 * np.sin(0.8 * w)
    a[:, J["left_elbow"], 1] = -20 - 15 * (1 + np.sin(w))
    return _Segment(a, np.zeros_like(t), np.zeros_like(t), np.zeros_like(t))


MOTIONS: dict[str, Callable[[np.ndarray, np.random.Generator], _Segment]] = {
    "idle": _idle,
    "walk": _walk,
    "run": _run,
    "sprint_start": _sprint_start,
    "jump": _jump,
    "squat": _squat,
    "lunge": _lunge,
    "kick": _kick,
    "throw": _throw,
    "turn": _turn,
}
LOCOMOTION = ("walk", "run", "sprint_start")
IN_PLACE = tuple(m for m in MOTIONS if m not in LOCOMOTION)
_LATERAL = ("kick", "throw", "lunge", "sprint_start")  # motions with a preferred side


# ----------------------------------------------------------------------------------------------
# Per-person variation and programs


def _smooth_noise(n: int, fps: float, rng: np.random.Generator, amplitude_deg: float) -> np.ndarray:
    """(n, 24, 3) low-frequency noise in degrees: a few random sinusoids per channel."""
    t = np.arange(n) / fps
    out = np.zeros((n, NUM_JOINTS * 3))
    for _ in range(3):
        f = rng.uniform(0.15, 0.8, NUM_JOINTS * 3)
        ph = rng.uniform(0, 2 * np.pi, NUM_JOINTS * 3)
        out += np.sin(2 * np.pi * f[None] * t[:, None] + ph[None])
    return (amplitude_deg / np.sqrt(3 * 0.5)) * out.reshape(n, NUM_JOINTS, 3)


_RIGHT = [i for i, n in enumerate(JOINT_NAMES) if n.startswith("right_")]


def _anatomical_to_model(angles_deg: np.ndarray) -> np.ndarray:
    """Degrees with anatomical signs -> radians with model signs (right side y, z negated)."""
    out = np.deg2rad(angles_deg)
    out[..., _RIGHT, 1:] *= -1.0
    return out


def motion_segment(
    name: str,
    n_frames: int,
    fps: float,
    rng: np.random.Generator,
    mirrored: bool | None = None,
    noise_deg: float = 2.0,
) -> _Segment:
    """One motion with per-person variation, in model signs (radians) and the mover's frame.

    `mirrored` picks the side for lateral motions (kick foot, throwing hand, lead leg); None
    draws it from `rng`.
    """
    if name not in MOTIONS:
        raise KeyError(f"unknown motion '{name}'; available: {sorted(MOTIONS)}")
    if n_frames < 1 or fps <= 0:
        raise ValueError(f"motion '{name}': need n_frames >= 1 and fps > 0, got {n_frames}, {fps}")
    tempo = rng.uniform(0.9, 1.1)
    amp = rng.uniform(0.88, 1.12)
    t = np.arange(n_frames) / fps * tempo
    seg = MOTIONS[name](t, rng)
    stand = _to_array(STAND)[None]
    ang = stand + amp * (seg.angles - stand) + _smooth_noise(n_frames, fps, rng, noise_deg)
    ang = _anatomical_to_model(ang)
    turn = seg.turn.copy()
    if mirrored is None:
        mirrored = bool(rng.random() < 0.5) if name in _LATERAL else False
    if mirrored:
        ang = mirror_angles(ang)
        turn = -turn
    return _Segment(clip_to_limits(ang), seg.forward, turn, seg.lift)


def generate_motion(
    names: list[str] | tuple[str, ...] | str,
    n_frames: int,
    fps: float,
    rng: np.random.Generator,
    start: tuple[float, float] = (0.0, 0.0),
    heading: float = 0.0,
    curvature: float = 0.0,
    blend_s: float = 0.35,
    noise_deg: float = 2.0,
) -> MotionClip:
    """A person's motion program: `names` played in turn over `n_frames`, crossfaded.

    The pelvis starts at world XY `start` facing `heading`; forward motion bends with
    `curvature` (1/m, positive turns left) so runners stay inside a capture volume.
    """
    names = [names] if isinstance(names, str) else list(names)
    if not names:
        raise ValueError("motion program is empty; give at least one motion name")
    blend = max(1, int(round(blend_s * fps)))
    seg_len = int(np.ceil(n_frames / len(names)))
    angles = np.zeros((n_frames, NUM_JOINTS, 3))
    dfwd = np.zeros(n_frames)
    dturn = np.zeros(n_frames)
    lift = np.zeros(n_frames)
    weight = np.zeros(n_frames)
    labels = np.empty(n_frames, dtype=object)
    label_w = np.zeros(n_frames)
    for k, name in enumerate(names):
        start_f = max(0, k * seg_len - (blend if k else 0))
        stop_f = min(n_frames, (k + 1) * seg_len + (blend if k < len(names) - 1 else 0))
        n = stop_f - start_f
        if n <= 0:
            continue
        seg = motion_segment(name, n, fps, rng, noise_deg=noise_deg)
        idx = np.arange(start_f, stop_f)
        w = np.ones(n)
        if k > 0:
            w *= _smoothstep((idx - start_f + 0.5) / (2 * blend))
        if k < len(names) - 1:
            w *= _smoothstep((stop_f - idx - 0.5) / (2 * blend))
        angles[idx] += w[:, None, None] * seg.angles
        dfwd[idx] += w * np.diff(seg.forward, prepend=seg.forward[0])
        dturn[idx] += w * np.diff(seg.turn, prepend=seg.turn[0])
        lift[idx] += w * seg.lift
        weight[idx] += w
        better = w > label_w[idx]
        labels[idx[better]] = name
        label_w[idx[better]] = w[better]
    angles /= weight[:, None, None]
    lift /= weight
    dfwd /= weight
    dturn /= weight
    heading_t = heading + np.cumsum(dturn + curvature * dfwd)
    step = dfwd[:, None] * np.stack([np.cos(heading_t), np.sin(heading_t)], -1)
    position = np.asarray(start, dtype=np.float64)[None] + np.cumsum(step, axis=0)
    # A convex blend of in-limit angles is in limits, so no second clip is needed.
    return MotionClip(
        fps=float(fps),
        angles=angles,
        position=position,
        heading=heading_t,
        lift=lift,
        labels=tuple(str(x) for x in labels),
    )


def random_static_poses(
    n_frames: int,
    rng: np.random.Generator,
    fps: float = 30.0,
    start: tuple[float, float] = (0.0, 0.0),
    spread: float = 0.8,
) -> MotionClip:
    """Independent random poses for training diversity (no temporal coherence).

    Each joint angle is drawn uniformly from a window `spread` times its range wide, centred
    half-way between the standing posture and the middle of the range (then clipped to the
    limits); the heading is uniform and the root tilt stays moderate.
    """
    stand = _anatomical_to_model(_to_array(STAND)[None])[0]
    lo, hi = JOINT_LIMITS[..., 0], JOINT_LIMITS[..., 1]
    centre = 0.5 * (stand + 0.5 * (lo + hi))
    u = rng.uniform(-1, 1, (n_frames, NUM_JOINTS, 3))
    angles = centre[None] + u * (spread * (hi - lo) / 2)[None]
    angles[:, 0] = np.deg2rad(rng.uniform(-15, 25, (n_frames, 3)) * np.array([1, 0, 0.4]))
    heading = rng.uniform(-np.pi, np.pi, n_frames)
    position = np.tile(np.asarray(start, dtype=np.float64), (n_frames, 1))
    return MotionClip(
        fps=float(fps),
        angles=clip_to_limits(angles),
        position=position,
        heading=heading,
        lift=np.zeros(n_frames),
        labels=("random_static",) * n_frames,
        smooth=False,
    )
