"""The ChArUco calibration board: its spec, printed texture and a path through the volume.

Board frame (OpenCV's): origin at the top-left outer corner of the checker pattern, x along
`squares_x`, y along `squares_y` (down the printed image), z into the board, so the printed
side faces -z. Chessboard corners are `CharucoBoard.getChessboardCorners()`. The printed sheet
has a white margin of `margin` metres around the pattern. A board pose maps board to world:
X_world = R X_board + t.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from calibration.board import BoardSpec
from synth.world import WORLD_UP

_BOARD_KEYS = ("kind", "squares_x", "squares_y", "square_size", "marker_size", "dictionary")


@dataclass(frozen=True)
class ChArUcoSpec:
    """A ChArUco board, with the same fields as `calibration.board.BoardSpec`."""

    squares_x: int = 5
    squares_y: int = 4
    square_size: float = 0.3
    marker_size: float = 0.24
    dictionary: str = "DICT_4X4_50"
    margin: float = 0.06  # white border of the printed sheet, metres (not part of board.json)

    def __post_init__(self):
        if self.squares_x < 3 or self.squares_y < 3:
            raise ValueError(
                f"ChArUco board needs at least 3x3 squares, got {self.squares_x}x{self.squares_y}"
            )
        if not 0 < self.marker_size < self.square_size:
            raise ValueError(
                f"marker_size {self.marker_size} must be in (0, square_size={self.square_size})"
            )
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(
                f"unknown ArUco dictionary '{self.dictionary}' (expected e.g. DICT_4X4_50)"
            )
        n_markers = (self.squares_x * self.squares_y) // 2
        dict_size = (
            int(self.dictionary.rsplit("_", 1)[-1])
            if self.dictionary.rsplit("_", 1)[-1].isdigit()
            else 1000
        )
        if n_markers > dict_size:
            raise ValueError(
                f"board needs {n_markers} markers but {self.dictionary} has only {dict_size}"
            )

    def to_dict(self) -> dict:
        """board.json content: exactly the keys of calibration.board.BoardSpec.to_dict()."""
        return {
            "kind": "charuco",
            "squares_x": int(self.squares_x),
            "squares_y": int(self.squares_y),
            "square_size": float(self.square_size),
            "marker_size": float(self.marker_size),
            "dictionary": self.dictionary,
        }

    @property
    def size(self) -> tuple[float, float]:
        """Pattern width and height in metres (without the margin)."""
        return self.squares_x * self.square_size, self.squares_y * self.square_size

    @cached_property
    def cv_board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_size, self.marker_size, d
        )

    @cached_property
    def corners(self) -> np.ndarray:
        """(N, 3) chessboard corners in the board frame (OpenCV order = ChArUco ids)."""
        return np.asarray(self.cv_board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def texture(self, px_per_square: int = 48) -> BoardTexture:
        """The printed sheet, margin included; pixel edges align with the squares."""
        m = int(round(self.margin / self.square_size * px_per_square))
        w = self.squares_x * px_per_square + 2 * m
        h = self.squares_y * px_per_square + 2 * m
        image = self.cv_board.generateImage((w, h), marginSize=m, borderBits=1)
        return BoardTexture(
            image=image, px_per_square=px_per_square, margin_px=m, square_size=self.square_size
        )


@dataclass(frozen=True)
class BoardTexture:
    """Printed board image and its mapping from board metres to image pixels."""

    image: np.ndarray  # (h, w) uint8
    px_per_square: int
    margin_px: int
    square_size: float

    @property
    def margin(self) -> float:
        """Printed white margin in metres (as rendered)."""
        return self.margin_px / self.px_per_square * self.square_size

    def pixel_coords(self, bx: np.ndarray, by: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (pixel centres at integers) of board points in metres."""
        s = self.px_per_square / self.square_size
        return self.margin_px + bx * s - 0.5, self.margin_px + by * s - 0.5


def board_json(spec: ChArUcoSpec) -> dict:
    """board.json dict, cross-checked with calibration.board.BoardSpec, which reads it back."""
    d = spec.to_dict()
    other = BoardSpec(**d).to_dict()
    if set(other) != set(_BOARD_KEYS) or any(other[k] != d[k] for k in _BOARD_KEYS):
        raise ValueError(
            f"calibration.board.BoardSpec disagrees with synth's board: {other} vs {d}"
        )
    return other


@dataclass(frozen=True)
class BoardPose:
    """Board-to-world rotation R (3, 3) and translation t (3,)."""

    R: np.ndarray
    t: np.ndarray

    @property
    def front_normal(self) -> np.ndarray:
        """World direction the printed side faces (board -z)."""
        return -self.R[:, 2]

    def to_world(self, points_board: np.ndarray) -> np.ndarray:
        return np.asarray(points_board) @ self.R.T + self.t


# Board lying flat on the floor, printed side up, its origin at the world origin: board x is
# world x, board y is world -y, board z (into the board) is world -z. A board calibration that
# takes its world from this pose (calibration.solve with floor_world) recovers synth's world.
FLOOR_BOARD_R = np.diag([1.0, -1.0, -1.0])
FLOOR_LIFT = 0.001  # metres above the floor (keeps the board in front of the floor for rays)


def board_clip(
    spec: ChArUcoSpec,
    n_frames: int,
    volume_center,
    volume_radius: float,
    rng: np.random.Generator,
    camera_centers: np.ndarray | None = None,
    floor_frames: int = 3,
    lift_frames: int | None = None,
) -> list[BoardPose]:
    """The calibration clip: `floor_frames` frames with the board flat on the floor (see
    FLOOR_BOARD_R), `lift_frames` frames (default a tenth of the rest, at least 4) lifting it, up
    first, then turning into the path, and the rest along `board_path`. Short clips are like a
    long hand-held clip sampled sparsely: the board moves further between frames."""
    floor_frames = min(floor_frames, n_frames)
    rest = n_frames - floor_frames
    lift = min(max(4, round(0.1 * rest)) if lift_frames is None else lift_frames, rest)
    floor = BoardPose(R=FLOOR_BOARD_R.copy(), t=np.array([0.0, 0.0, FLOOR_LIFT]))
    path = board_path(spec, rest, volume_center, volume_radius, rng, camera_centers) if rest else []
    poses = [floor] * floor_frames
    if lift:
        mid = np.array([spec.size[0] / 2, spec.size[1] / 2, 0.0])
        start_c = floor.to_world(mid)
        end = path[lift] if lift < rest else path[-1]
        end_c = end.to_world(mid)
        half_diag = 0.5 * np.hypot(*spec.size) + spec.margin + 0.05
        up_c = np.array([start_c[0], start_c[1], max(end_c[2], half_diag)])
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([floor.R, end.R])))
        for i in range(lift):
            s = (i + 1) / (lift + 1)
            if s <= 0.5:  # lift flat, straight up
                w = _ease(2 * s)
                R, c = floor.R, (1 - w) * start_c + w * up_c
            else:  # turn into the path pose while moving to its place
                w = _ease(2 * s - 1)
                R, c = slerp([w]).as_matrix()[0], (1 - w) * up_c + w * end_c
            poses.append(BoardPose(R=R, t=c - R @ mid))
    return poses + path[lift:]


def _ease(x: float) -> float:
    return x * x * (3 - 2 * x)


def board_path(
    spec: ChArUcoSpec,
    n_frames: int,
    volume_center,
    volume_radius: float,
    rng: np.random.Generator,
    camera_centers: np.ndarray | None = None,
) -> list[BoardPose]:
    """A smooth hand-held path: the board wanders through the volume at about 0.9-1.6 m and
    turns its printed side once around. With `camera_centers` it faces each camera in turn
    (sorted by azimuth), so every camera gets frontal and oblique views; without, it faces the
    horizon tilted slightly up. Tilt and roll wobble smoothly on top."""
    if n_frames < 1:
        raise ValueError(f"board clip needs at least one frame, got {n_frames}")
    c = np.asarray(volume_center, dtype=np.float64)
    tau = np.arange(n_frames) / n_frames
    ph = rng.uniform(0, 2 * np.pi, 4)
    r = 0.5 * volume_radius
    half_diag = 0.5 * np.hypot(*spec.size) + spec.margin
    zc = max(1.25, half_diag + 0.15)
    centre = np.stack(
        [
            c[0] + r * np.sin(2 * np.pi * 1.0 * tau + ph[0]),
            c[1] + r * np.sin(2 * np.pi * 2.0 * tau + ph[1]),
            zc + 0.3 * np.sin(2 * np.pi * 1.5 * tau + ph[2]),
        ],
        -1,
    )
    direction = rng.choice([-1.0, 1.0])
    azimuth = ph[3] + 2 * np.pi * tau * direction
    wobble_tilt = np.deg2rad(12 * np.sin(2 * np.pi * 3.0 * tau + ph[0]))
    wobble_yaw = np.deg2rad(15 * np.sin(2 * np.pi * 2.0 * tau + ph[2]))
    roll = np.deg2rad(20 * np.sin(2 * np.pi * 2.5 * tau + ph[1]))
    if camera_centers is not None and len(camera_centers):
        cams = np.asarray(camera_centers, dtype=np.float64)
        cam_az = np.arctan2(cams[:, 1] - c[1], cams[:, 0] - c[0])
        order = np.argsort(cam_az)
        cam_az, cams = cam_az[order], cams[order]
    poses = []
    for i in range(n_frames):
        if camera_centers is not None and len(camera_centers):
            # Aim at the camera ring point at this azimuth (linear between neighbours).
            a = np.mod(azimuth[i] - cam_az[0], 2 * np.pi) + cam_az[0]
            k = np.searchsorted(cam_az, a) % len(cams)
            j = (k - 1) % len(cams)
            span = np.mod(cam_az[k] - cam_az[j], 2 * np.pi) or 2 * np.pi
            w = np.mod(a - cam_az[j], 2 * np.pi) / span
            target = (1 - w) * cams[j] + w * cams[k]
            front = target - centre[i]
            front /= np.linalg.norm(front)
        else:
            front = np.array([np.cos(azimuth[i]), np.sin(azimuth[i]), np.tan(np.deg2rad(12))])
            front /= np.linalg.norm(front)
        yaw_axis = np.array(WORLD_UP)
        front = _rotate(front, yaw_axis, wobble_yaw[i])
        side = np.cross(front, WORLD_UP)
        side /= np.linalg.norm(side)
        front = _rotate(front, side, wobble_tilt[i])
        z = -front  # board z points into the board, away from the viewer
        x = np.cross(z, WORLD_UP)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        cr, sr = np.cos(roll[i]), np.sin(roll[i])
        x, y = cr * x + sr * y, -sr * x + cr * y
        R = np.stack([x, y, z], -1)
        mid = np.array([spec.size[0] / 2, spec.size[1] / 2, 0.0])  # pattern centre on the path
        poses.append(BoardPose(R=R, t=centre[i] - R @ mid))
    return poses


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation of vector v about a unit axis."""
    return (
        v * np.cos(angle)
        + np.cross(axis, v) * np.sin(angle)
        + axis * np.dot(axis, v) * (1 - np.cos(angle))
    )


def visible_corners(
    spec: ChArUcoSpec, pose: BoardPose, camera, radius: float | None = None, room=None
) -> tuple[np.ndarray, np.ndarray]:
    """Ids and distorted pixel positions of the chessboard corners a camera sees: printed side
    facing it, in front of it, inside the image and, with `room` (the `synth.stage.Stage` the
    board is rendered in), inside the room: a large board reaches through the ceiling or a wall,
    which hide that part of it in the render. Nothing else can hide the board.
    `radius` is the camera's undistorted field radius (`synth.projection.field_radius`)."""
    from synth.projection import project_in_view

    world = pose.to_world(spec.corners)
    ids = np.arange(len(world))
    if np.dot(camera.center - pose.t, pose.front_normal) <= 0:
        return ids[:0], np.zeros((0, 2))
    uv, inside = project_in_view(camera, world, radius)
    if room is not None:  # the camera is inside the (convex) room: only the room's box hides
        inside &= room.contains(world)
    return ids[inside], uv[inside]
