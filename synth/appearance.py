"""Procedural per-part appearance: kits (jersey, shorts, socks, shoes), skin, hair and a face.

Colours are evaluated per ray hit from the hit's position on the *rest* body, so patterns
(stripes, hoops, a sash, the shirt number) are crisp at any resolution and move with the body.
Body parts come from the nearest bone of the SMPL skeleton in the rest pose, refined by the body
model's own part labels for head, hands and feet where it has them (matched by substring).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from synth.sampling import sample_image
from synth.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS, PRIMARY_CHILD, J

REGIONS = ("trunk", "neck", "head", "upperarm", "forearm", "hand", "upperleg", "lowerleg", "foot")
_R = {name: i for i, name in enumerate(REGIONS)}

# Region of the bone that starts at each joint.
_BONE_REGION = {
    "pelvis": "trunk",
    "spine1": "trunk",
    "spine2": "trunk",
    "spine3": "trunk",
    "collar": "trunk",
    "neck": "neck",
    "head": "head",
    "shoulder": "upperarm",
    "elbow": "forearm",
    "wrist": "hand",
    "hand": "hand",
    "hip": "upperleg",
    "knee": "lowerleg",
    "ankle": "foot",
    "foot": "foot",
}
# Substrings of a body model's part names that identify extremities.
_PART_KEYWORDS = {
    "head": ("head", "face", "skull", "eye"),
    "hand": ("hand", "finger", "thumb", "palm"),
    "foot": ("foot", "toe", "heel"),
}

SKIN_TONES = (
    (255, 224, 196),
    (241, 194, 167),
    (224, 172, 138),
    (198, 134, 98),
    (161, 102, 72),
    (120, 78, 55),
    (86, 56, 41),
)
HAIR_COLOURS = (
    (28, 24, 22),
    (55, 38, 28),
    (95, 65, 42),
    (190, 155, 100),
    (135, 62, 30),
    (150, 148, 145),
)
KIT_COLOURS = (
    (200, 20, 30),
    (20, 60, 170),
    (235, 235, 235),
    (15, 25, 60),
    (245, 200, 20),
    (20, 130, 60),
    (240, 110, 20),
    (25, 25, 25),
    (110, 175, 225),
    (100, 40, 140),
    (120, 20, 40),
)
SHOE_COLOURS = ((240, 240, 240), (30, 30, 30), (200, 240, 40), (230, 60, 40), (40, 90, 200))
PATTERNS = ("solid", "stripes", "hoops", "sash")
HAIR_STYLES = ("short", "long", "shaved")


def _bone_region(j: int) -> str:
    name = JOINT_NAMES[j].replace("left_", "").replace("right_", "")
    return _BONE_REGION[name]


@dataclass(frozen=True)
class Outfit:
    """One person's look. Colours are sRGB 0-255 triples."""

    skin: tuple[int, int, int]
    hair: tuple[int, int, int]
    hair_style: str
    jersey: tuple[int, int, int]
    jersey_second: tuple[int, int, int]
    pattern: str
    trim: tuple[int, int, int]  # number, collar and cuffs
    number: int | None
    sleeve: float  # fraction of the upper arm covered (0 = sleeveless, >1 = long sleeves)
    shorts: tuple[int, int, int]
    shorts_length: float  # fraction of the thigh covered
    socks: tuple[int, int, int]
    sock_height: float  # fraction of the shin covered
    shoes: tuple[int, int, int]
    team: int

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def _contrast(rgb) -> tuple[int, int, int]:
    lum = 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
    return (20, 20, 20) if lum > 150 else (245, 245, 245)


def team_kits(n_teams: int, rng: np.random.Generator) -> list[dict]:
    """Distinct kit colour sets per team."""
    order = rng.permutation(len(KIT_COLOURS))
    kits = []
    for k in range(n_teams):
        main = KIT_COLOURS[order[(2 * k) % len(order)]]
        second = KIT_COLOURS[order[(2 * k + 1) % len(order)]]
        kits.append(
            dict(
                jersey=main,
                jersey_second=second,
                pattern=str(rng.choice(PATTERNS)),
                shorts=second
                if rng.random() < 0.6
                else (25, 25, 25)
                if sum(main) > 300
                else (235, 235, 235),
                socks=main if rng.random() < 0.5 else second,
                trim=_contrast(main),
                sleeve=float(rng.choice([0.5, 0.5, 0.0, 1.5])),
            )
        )
    return kits


def sample_outfit(rng: np.random.Generator, kit: dict, team: int) -> Outfit:
    """A person's outfit: team kit plus individual skin, hair, number, lengths and shoes."""
    return Outfit(
        skin=SKIN_TONES[rng.integers(len(SKIN_TONES))],
        hair=HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))],
        hair_style=str(rng.choice(HAIR_STYLES, p=[0.6, 0.25, 0.15])),
        jersey=kit["jersey"],
        jersey_second=kit["jersey_second"],
        pattern=kit["pattern"],
        trim=kit["trim"],
        number=int(rng.integers(1, 99)) if rng.random() < 0.85 else None,
        sleeve=kit["sleeve"],
        shorts=kit["shorts"],
        shorts_length=float(rng.uniform(0.3, 0.55)),
        socks=kit["socks"],
        sock_height=float(rng.uniform(0.45, 0.8)),
        shoes=SHOE_COLOURS[rng.integers(len(SHOE_COLOURS))],
        team=team,
    )


def _segments(rest_joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bone segments (start, end, owning joint) in the rest pose; leaves get a virtual end."""
    starts, ends, owner = [], [], []
    extend = {"head": 1.5, "left_hand": 1.2, "right_hand": 1.2, "left_foot": 0.4, "right_foot": 0.4}
    for j in range(NUM_JOINTS):
        a = rest_joints[j]
        children = [c for c, p in enumerate(PARENTS) if p == j]
        if j == 0:
            children = [J["left_hip"], J["right_hip"], J["spine1"]]
        elif PRIMARY_CHILD[j] >= 0:
            children = [PRIMARY_CHILD[j]]
        for c in children:
            starts.append(a)
            ends.append(rest_joints[c])
            owner.append(j if j != 0 or c == J["spine1"] else 0)
        if not children:
            name = JOINT_NAMES[j]
            starts.append(a)
            ends.append(a + extend[name] * (a - rest_joints[PARENTS[j]]))
            owner.append(j)
    return np.array(starts), np.array(ends), np.array(owner)


def _nearest_segment(points: np.ndarray, starts, ends, allowed: np.ndarray | None = None):
    d = ends - starts
    rel = points[:, None, :] - starts[None]
    t = np.clip((rel * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-12)[None], 0, 1)
    dist = np.linalg.norm(rel - t[..., None] * d[None], axis=-1)
    if allowed is not None:
        dist = np.where(allowed, dist, np.inf)
    k = dist.argmin(axis=1)
    return k, t[np.arange(len(points)), k]


@dataclass(frozen=True)
class BodyAtlas:
    """Per-vertex body part, bone and position along the bone, on the rest body (SMPL axes)."""

    rest: np.ndarray  # (V, 3)
    region: np.ndarray  # (V,) index into REGIONS
    segment: np.ndarray  # (V,) index of the nearest bone segment
    seg_start: np.ndarray  # (S, 3) bone segments in the rest pose
    seg_end: np.ndarray  # (S, 3)
    landmarks: dict  # named heights/positions used by the patterns
    is_eye: np.ndarray  # (V,) vertices of the model's own eyeballs (from part labels), if any

    def along(self, segment: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Position of rest points along their bone segment, 0 at its start joint, 1 at its end."""
        a, b = self.seg_start[segment], self.seg_end[segment]
        d = b - a
        return np.clip(((points - a) * d).sum(1) / np.maximum((d * d).sum(1), 1e-12), 0, 1)

    @classmethod
    def build(
        cls, rest_vertices: np.ndarray, rest_joints: np.ndarray, part_labels=None, part_names=None
    ) -> BodyAtlas:
        rest = np.asarray(rest_vertices, dtype=np.float64)
        joints = np.asarray(rest_joints, dtype=np.float64)
        starts, ends, owner = _segments(joints)
        seg_region = np.array([_R[_bone_region(o)] for o in owner])
        k, _ = _nearest_segment(rest, starts, ends)
        region = seg_region[k]
        is_eye = np.zeros(len(rest), bool)
        if part_labels is not None and part_names is not None:
            labels = np.asarray(part_labels).ravel()
            if labels.shape[0] != rest.shape[0]:
                raise ValueError(
                    f"body model part_labels has {labels.shape[0]} entries for {rest.shape[0]} "
                    "vertices"
                )
            for reg, words in _PART_KEYWORDS.items():
                ids = [
                    i for i, n in enumerate(part_names) if any(w in str(n).lower() for w in words)
                ]
                sel = np.isin(labels, ids)
                if sel.any():
                    k[sel], _ = _nearest_segment(
                        rest[sel], starts, ends, (seg_region == _R[reg])[None]
                    )
                    region[sel] = _R[reg]
            eye_ids = [
                i
                for i, n in enumerate(part_names)
                if "eye" in str(n).lower() and "cavity" not in str(n).lower()
            ]
            is_eye = np.isin(labels, eye_ids)
        head = rest[region == _R["head"]]
        feet = rest[region == _R["foot"]]
        if len(head) < 4 or len(feet) < 4:
            raise ValueError(
                "body model rest mesh has no recognisable head or feet near the SMPL joints"
            )
        top = head[:, 1].max()
        chin = np.percentile(head[:, 1], 3)
        eye_y, eye_dx, eye_front = top - 0.48 * (top - chin), 0.033, float(head[:, 2].max())
        if is_eye.sum() >= 8:  # the model has eyeballs: put brows and mouth around them
            eyes = rest[is_eye]
            eye_y = float(eyes[:, 1].mean())
            eye_dx = float(np.abs(eyes[:, 0] - joints[J["head"], 0]).mean())
            eye_front = float(eyes[:, 2].max())
        landmarks = dict(
            top=top,
            chin=chin,
            eye_y=eye_y,
            eye_dx=eye_dx,
            eye_front=eye_front,
            front_z=head[:, 2].max(),
            back_z=head[:, 2].min(),
            head_x=float(joints[J["head"], 0]),
            waist_y=joints[J["spine1"], 1] - 0.02,
            neck_y=joints[J["neck"], 1],
            spine2_y=joints[J["spine2"], 1],
            spine3_y=joints[J["spine3"], 1],
            chest_z=joints[J["spine3"], 2],
            sole_y=feet[:, 1].min(),
        )
        return cls(
            rest=rest,
            region=region,
            segment=k,
            seg_start=starts,
            seg_end=ends,
            landmarks=landmarks,
            is_eye=is_eye,
        )


def _digits_bitmap(number: int) -> np.ndarray:
    """Float mask (h, w) of the shirt number, 1 on the digits."""
    text = str(number)
    h = 64
    canvas = np.zeros((h, 44 * len(text) + 8), np.uint8)
    cv2.putText(canvas, text, (4, h - 8), cv2.FONT_HERSHEY_DUPLEX, 2.0, 255, 7, cv2.LINE_AA)
    return canvas.astype(np.float32) / 255.0


def _sample_mask(mask: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear sample of a mask at normalised coords u, v in [0, 1] (0 outside)."""
    h, w = mask.shape
    x = u * w - 0.5
    y = v * h - 0.5
    inside = (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    out = sample_image(mask, x, y)
    return np.where(inside, out, 0.0)


def srgb_to_linear(rgb) -> np.ndarray:
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def albedo(
    outfit: Outfit, atlas: BodyAtlas, tri_vertices: np.ndarray, bary: np.ndarray
) -> np.ndarray:
    """Linear RGB albedo (N, 3) at N hits given each hit's triangle vertex ids (N, 3) and
    barycentric weights (N, 3)."""
    n = len(bary)
    p = (atlas.rest[tri_vertices] * bary[..., None]).sum(1)
    main = tri_vertices[np.arange(n), bary.argmax(1)]
    region = atlas.region[main]
    # Position along the bone of the hit's dominant vertex, from the exact hit point (not
    # interpolated: a triangle can straddle two bones).
    along = atlas.along(atlas.segment[main], p)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    L = atlas.landmarks
    col = np.zeros((n, 3))

    def paint(sel, rgb):
        col[sel] = srgb_to_linear(rgb)

    skin, is_ = outfit.skin, lambda r: region == _R[r]
    paint(np.ones(n, bool), skin)

    # Jersey body and sleeves, with the pattern in its second colour.
    trunk = is_("trunk")
    jersey = trunk & (y >= L["waist_y"])
    neckline = jersey & (y > L["neck_y"] - 0.03 - 0.04 * (z > L["chest_z"]))
    jersey &= ~neckline
    sleeve = is_("upperarm") & (along < outfit.sleeve) | is_("forearm") & (outfit.sleeve > 1.0)
    paint(jersey | sleeve, outfit.jersey)
    garment = jersey | sleeve
    if outfit.pattern == "stripes":
        paint(garment & (np.mod(x + 0.035, 0.14) < 0.07), outfit.jersey_second)
    elif outfit.pattern == "hoops":
        paint(garment & (np.mod(y - L["waist_y"], 0.16) < 0.08), outfit.jersey_second)
    elif outfit.pattern == "sash":
        paint(jersey & (np.abs(x * 0.9 - (y - L["spine2_y"])) < 0.06), outfit.jersey_second)
    cuff = (
        is_("upperarm")
        & (np.abs(along - outfit.sleeve) < 0.05)
        & (outfit.sleeve <= 1.0)
        & (outfit.sleeve > 0)
    )
    paint(
        cuff | (trunk & neckline & (y < L["neck_y"] - 0.01 - 0.04 * (z > L["chest_z"]))),
        outfit.trim,
    )
    if outfit.number is not None:
        digits = _digits_bitmap(outfit.number)
        aspect = digits.shape[1] / digits.shape[0]
        back = jersey & (z < L["chest_z"])
        hgt = 0.22
        cy = L["spine2_y"] + 0.05
        u = x / (hgt * aspect) + 0.5
        v = (cy + hgt / 2 - y) / hgt
        u_back = 1.0 - u  # seen from behind, +x (body left) is on the viewer's right
        m = _sample_mask(digits, u_back[back], v[back])
        col[back] = col[back] * (1 - m[:, None]) + srgb_to_linear(outfit.trim)[None] * m[:, None]
        front = jersey & (z >= L["chest_z"])
        hf = 0.1
        cyf = L["spine3_y"] + 0.01
        uf = x / (hf * aspect) + 0.5  # seen from the front, +x is on the viewer's right
        vf = (cyf + hf / 2 - y) / hf
        m = _sample_mask(digits, uf[front], vf[front])
        col[front] = col[front] * (1 - m[:, None]) + srgb_to_linear(outfit.trim)[None] * m[:, None]

    paint(trunk & (y < L["waist_y"]), outfit.shorts)
    paint(is_("upperleg") & (along < outfit.shorts_length), outfit.shorts)
    paint(is_("lowerleg") & (along > 1 - outfit.sock_height), outfit.socks)
    foot = is_("foot")
    paint(foot, outfit.shoes)
    paint(
        foot & (y < L["sole_y"] + 0.018),
        (60, 60, 60) if sum(outfit.shoes) > 300 else (235, 235, 235),
    )

    head = is_("head")
    depth = np.clip((L["front_z"] - z) / max(L["front_z"] - L["back_z"], 1e-6), 0, 1)
    drop = {"short": 0.09, "long": 0.2, "shaved": 0.07}[outfit.hair_style]
    hair = head & (y > L["eye_y"] + 0.05 - drop * depth**0.7)
    if outfit.hair_style == "shaved":
        col[hair] = 0.5 * col[hair] + 0.5 * srgb_to_linear(outfit.hair)[None]
    else:
        paint(hair, outfit.hair)
    if outfit.hair_style == "long":
        paint(
            (is_("neck") | trunk)
            & (z < L["chest_z"] - 0.04)
            & (y > L["neck_y"] - 0.08)
            & (np.abs(x) < 0.09),
            outfit.hair,
        )
    face = head & (z > L["front_z"] - 0.05)
    real_eyes = atlas.is_eye.any()
    for sx in (-1.0, 1.0):
        ex = L["head_x"] + sx * L["eye_dx"]
        brow = face & (((x - ex) / 0.018) ** 2 + ((y - L["eye_y"] - 0.02) / 0.004) ** 2 < 1)
        col[brow] = 0.45 * col[brow] + 0.55 * srgb_to_linear(outfit.hair)[None] * 0.6
        if not real_eyes:  # painted eyes on bodies without eyeballs
            paint(
                face & (((x - ex) / 0.013) ** 2 + ((y - L["eye_y"]) / 0.007) ** 2 < 1), (35, 30, 30)
            )
    if real_eyes:  # eyeballs: dark iris facing forward, white around it
        eye = atlas.is_eye[main]
        paint(eye, (225, 220, 210))
        paint(eye & (z > L["eye_front"] - 0.006), (45, 35, 30))
    mouth = face & (
        ((x - L["head_x"]) / 0.022) ** 2 + ((y - (L["eye_y"] - 0.065)) / 0.005) ** 2 < 1
    )
    col[mouth] = col[mouth] * np.array([0.75, 0.45, 0.45])
    return col
