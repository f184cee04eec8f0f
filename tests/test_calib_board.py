"""Boards: spec, rendering, detection (ChArUco and checkerboard, partial and blurred views),
frame sources (image folders and videos)."""

import cv2
import numpy as np
import pytest

from calibration.board import (
    BoardDetector,
    BoardError,
    BoardSpec,
    FrameDetection,
    detect_in_source,
    drop_blurred,
)
from calibration.camera import Camera, look_at_rotation
from calibration.frames import FrameSourceError, count_frames, iter_frames, source_image_size
from calibration.synthetic import BoardRenderer

CHARUCO = BoardSpec("charuco", 7, 5, 0.15, 0.11, "DICT_4X4_50")
CHECKER = BoardSpec("checkerboard", 8, 5, 0.1)


def camera_facing_board(
    board: BoardSpec, distance=1.6, offset=(0.0, 0.0), tilt_deg=20.0, size=(800, 600)
):
    """A camera looking at the centre of a board lying in the world plane z = 0 (printed side
    towards -z, so the camera sits at negative z), with some tilt."""
    w, h = board.size_m
    centre = np.array([w / 2 + offset[0], h / 2 + offset[1], 0.0])
    a = np.radians(tilt_deg)
    pos = centre + distance * np.array([np.sin(a), 0.0, -np.cos(a)])
    R = look_at_rotation(pos, centre, up=(0.0, -1.0, 0.0))  # board y is down the printed page
    K = [[750.0, 0, size[0] / 2 - 0.5], [0, 750.0, size[1] / 2 - 0.5], [0, 0, 1]]
    return Camera.create("cam", K, [-0.08, 0.02, 0, 0, 0], R, -R @ pos, *size)


def truth(camera, board, pose=None):
    pose = np.eye(4) if pose is None else pose
    return camera.project(board.object_points() @ pose[:3, :3].T + pose[:3, 3])


def test_board_spec_dict_round_trip_and_validation():
    d = CHARUCO.to_dict()
    assert set(d) == {"kind", "squares_x", "squares_y", "square_size", "marker_size", "dictionary"}
    assert BoardSpec.from_dict(d) == CHARUCO
    assert BoardSpec.from_dict(CHECKER.to_dict()) == CHECKER
    with pytest.raises(BoardError, match="unknown"):
        BoardSpec.from_dict({**d, "colour": "red"})
    with pytest.raises(BoardError, match="marker_size"):
        BoardSpec("charuco", 7, 5, 0.1, 0.12)
    with pytest.raises(BoardError, match="DICT_9X9"):
        BoardSpec("charuco", 7, 5, 0.1, 0.07, "DICT_9X9_50")
    with pytest.raises(BoardError, match="markers"):
        BoardSpec("charuco", 12, 12, 0.1, 0.07, "DICT_4X4_50")
    with pytest.raises(BoardError, match="odd"):
        BoardSpec("checkerboard", 7, 5, 0.1)
    assert CHARUCO.n_corners == 24 and CHARUCO.object_points()[7].tolist() == [0.3, 0.3, 0.0]
    # Our corner ids and OpenCV's ChArUco corner ids are the same corners.
    np.testing.assert_allclose(
        CHARUCO.create_cv_board().getChessboardCorners(), CHARUCO.object_points(), atol=1e-7
    )


def test_a_board_with_fewer_corners_than_a_detection_needs_is_refused():
    """A 3 x 3 ChArUco board passed the spec's checks, then every view of it was dropped (4
    corners, min_corners 6) and calibration failed later with 'no detections'."""
    board = BoardSpec("charuco", 3, 3, 0.1, 0.07)
    with pytest.raises(BoardError, match=r"has \d+ inner corners, fewer than the 6"):
        BoardDetector(board)
    BoardDetector(board, min_corners=4)  # asked for explicitly, it is allowed


def test_render_image_marks_square_zero_black():
    img = CHARUCO.render_image(40)
    assert img.shape == (200, 280) and img[20, 20] == 0 and img[2, 42] == 255
    chk = CHECKER.render_image(20)
    assert chk.shape == (100, 160) and chk[10, 10] == 0 and chk[10, 30] == 255


@pytest.mark.parametrize("board", [CHARUCO, CHECKER], ids=["charuco", "checkerboard"])
def test_detection_is_subpixel_accurate(board):
    cam = camera_facing_board(board)
    img = BoardRenderer(cam, board).render(
        np.eye(4), blur_sigma=0.6, noise_std=2.0, rng=np.random.default_rng(0)
    )
    det = BoardDetector(board).detect(img, frame=5)
    assert det is not None and det.frame == 5
    assert len(det.ids) == board.n_corners
    err = np.linalg.norm(det.corners - truth(cam, board)[det.ids], axis=1)
    assert err.max() < 0.4, err.max()
    assert np.sqrt(np.mean(err**2)) < 0.2


def test_checkerboard_orientation_is_resolved_when_upside_down():
    cam = camera_facing_board(CHECKER)
    w, h = CHECKER.size_m
    flip = np.eye(4)  # board turned 180 degrees in its plane about its centre
    flip[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    flip[:3, 3] = [w, h, 0.0]
    img = BoardRenderer(cam, CHECKER).render(flip, 0.5, 1.0, np.random.default_rng(1))
    det = BoardDetector(CHECKER).detect(img)
    err = np.linalg.norm(det.corners - truth(cam, CHECKER, flip)[det.ids], axis=1)
    assert err.max() < 0.4


@pytest.mark.parametrize("half_turn", [False, True])
@pytest.mark.parametrize("cut", [0, 20, 40, 45])
def test_checkerboard_ids_hold_when_outer_squares_are_cut_off(cut, half_turn):
    """The outer squares at one end cut off by the image's edge (OpenCV still finds every inner
    corner): the ids came back turned by half when the cut passed a square's centre (the colour
    of an outer square decided the order)."""
    board, px, margin = BoardSpec("checkerboard", 7, 6, 0.05), 60, 60
    img = board.render_image(px, margin_px=margin)
    obj = board.object_points()[:, :2] / board.square_size * px + margin - 0.5
    if cut:  # `cut` pixels of the last squares, beyond the white margin
        img = img[: -(margin + cut), : -(margin + cut)]
    if half_turn:  # the cut end at the top left: the grid starts elsewhere
        img = np.ascontiguousarray(img[::-1, ::-1])
        obj = np.array(img.shape[1::-1], float) - 1 - obj
    det = BoardDetector(board).detect(img)
    assert det is not None and len(det.ids) == board.n_corners
    assert np.linalg.norm(det.corners - obj[det.ids], axis=1).max() < 0.5


def test_partial_charuco_view_keeps_visible_corners_with_their_ids():
    cam = camera_facing_board(CHARUCO, distance=1.0, offset=(0.45, 0.0), tilt_deg=0.0)
    img = BoardRenderer(cam, CHARUCO).render(np.eye(4), 0.6, 2.0, np.random.default_rng(2))
    uv = truth(cam, CHARUCO)
    inside = (uv[:, 0] > 0) & (uv[:, 0] < cam.width - 1)
    assert 6 < inside.sum() < CHARUCO.n_corners  # a genuinely partial view
    det = BoardDetector(CHARUCO).detect(img)
    assert det is not None and set(det.ids) <= set(np.flatnonzero(inside))
    # Corners whose neighbouring markers are cut off by the image edge cannot be identified.
    assert len(det.ids) >= 0.6 * inside.sum()
    assert np.linalg.norm(det.corners - uv[det.ids], axis=1).max() < 0.5


def test_no_board_and_too_few_corners_give_none():
    assert BoardDetector(CHARUCO).detect(np.full((480, 640), 128, np.uint8)) is None
    cam = camera_facing_board(CHARUCO, distance=1.0, offset=(0.5, 0.0), tilt_deg=0.0)
    img = BoardRenderer(cam, CHARUCO).render(np.eye(4))  # 8 of the 24 corners show
    assert len(BoardDetector(CHARUCO, min_corners=8).detect(img).ids) == 8
    assert BoardDetector(CHARUCO, min_corners=9).detect(img) is None


def test_blur_lowers_sharpness_and_blurred_detections_are_dropped():
    cam = camera_facing_board(CHARUCO)
    r = BoardRenderer(cam, CHARUCO)
    det = BoardDetector(CHARUCO)
    sharp = det.detect(r.render(np.eye(4), 0.5, 1.0, np.random.default_rng(0)), 0)
    soft = det.detect(r.render(np.eye(4), 1.8, 1.0, np.random.default_rng(0)), 1)
    assert soft is not None and soft.sharpness < 0.5 * sharp.sharpness
    dets = [
        FrameDetection(i, [0, 1, 2, 3], np.zeros((4, 2)), s)
        for i, s in enumerate([100, 90, 110, 95, 5])
    ]
    assert [d.frame for d in drop_blurred(dets, 0.2)] == [0, 1, 2, 3]
    assert len(drop_blurred(dets, 0.0)) == 5


def test_sharpness_does_not_depend_on_the_boards_size_in_the_image():
    """Equally blurred views of the board at 1 m and at 5 m: the variance of the Laplacian
    alone read the close one as 7x blurrier, and `drop_blurred` dropped it."""
    cam = Camera.create(
        "c", [[700, 0, 399.5], [0, 700, 299.5], [0, 0, 1]], [], np.eye(3), np.zeros(3), 800, 600
    )
    r = BoardRenderer(cam, CHARUCO, px_per_square=120, supersample=2)
    det, rng = BoardDetector(CHARUCO), np.random.default_rng(0)
    w, h = CHARUCO.size_m
    found = []
    for i, z in enumerate([1.0, 4.5, 5.0, 5.5]):
        found.append(det.detect(r.render(_at(w, h, z), blur_sigma=0.7, noise_std=2.0, rng=rng), i))
    sharp = np.array([d.sharpness for d in found])
    assert sharp.max() < 2 * sharp.min(), sharp
    assert [d.frame for d in drop_blurred(found, 0.2)] == [0, 1, 2, 3]
    blurred = det.detect(r.render(_at(w, h, 1.0), blur_sigma=2.0, noise_std=2.0, rng=rng), 4)
    assert blurred.sharpness < 0.5 * sharp[0]


def _at(w: float, h: float, z: float) -> np.ndarray:
    """The board's pose facing the camera, centred, `z` metres away."""
    pose = np.eye(4)
    pose[:3, 3] = [-w / 2, -h / 2, z]
    return pose


@pytest.fixture
def footage(tmp_path):
    """Six frames of one camera as an image folder and as a lossless video; the board is
    visible in frames 1, 2 and 4 only."""
    cam = camera_facing_board(CHARUCO, size=(640, 480), distance=1.9)
    r = BoardRenderer(cam, CHARUCO)
    away = np.eye(4)
    away[:3, 3] = [0, 0, -50]  # far behind the camera: not visible
    frames = [
        r.render(np.eye(4) if i in (1, 2, 4) else away, 0.5, 1.0, np.random.default_rng(i))
        for i in range(6)
    ]
    folder = tmp_path / "cam"
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"img{i}.png"), f)  # natural order: img2 before img10
    video = tmp_path / "cam.mkv"
    writer = cv2.VideoWriter(
        str(video), cv2.VideoWriter_fourcc(*"FFV1"), 30, (640, 480), isColor=False
    )
    for f in frames:
        writer.write(f)
    writer.release()
    return folder, video, frames


def test_frame_sources_subsample_in_order(footage, tmp_path):
    folder, video, frames = footage
    for src in (folder, video):
        assert count_frames(src) == 6 and source_image_size(src) == (640, 480)
        got = list(iter_frames(src, frame_step=2))
        assert [i for i, _ in got] == [0, 2, 4]
        assert all(np.array_equal(img, frames[i]) for i, img in got)  # lossless sources
        assert [i for i, _ in iter_frames(src, frame_step=1, max_frames=4)] == [0, 1, 2, 3]
    with pytest.raises(FrameSourceError, match="does not exist"):
        count_frames(tmp_path / "missing.mp4")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FrameSourceError, match="no images"):
        count_frames(tmp_path / "empty")


def test_detect_in_source_reports_frames_searched(footage):
    folder, video, _ = footage
    for src in (folder, video):
        res = detect_in_source(src, CHARUCO, camera="A")
        assert res.camera == "A" and res.frames_searched == 6 and res.image_size == (640, 480)
        assert [d.frame for d in res.detections] == [1, 2, 4]
        res2 = detect_in_source(src, CHARUCO, frame_step=2)
        assert res2.frames_searched == 3 and [d.frame for d in res2.detections] == [2, 4]


def test_phone_photos_with_an_exif_rotation_keep_their_displayed_size(tmp_path):
    """The image size was read ignoring the EXIF orientation that the frames are read with: a
    portrait-stored, landscape-shown photo series gave the camera its width and height swapped
    (coverage and lens checks then wrong). A folder mixing sizes is refused."""
    Image = pytest.importorskip("PIL.Image")
    spec = BoardSpec("checkerboard", 8, 5, 0.04)
    shown = np.full((480, 640), 255, np.uint8)
    shown[100:380, 120:520] = spec.render_image(40, margin_px=40)
    stored = np.ascontiguousarray(np.rot90(shown, 1))  # 480 wide, 640 high on disk
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to display
    for i in range(2):
        Image.fromarray(stored).save(tmp_path / f"img{i}.jpg", exif=exif, quality=95)
    assert source_image_size(tmp_path) == (640, 480)
    assert next(iter_frames(tmp_path))[1].shape == (480, 640)
    cv2.imwrite(str(tmp_path / "img2.jpg"), stored)  # no EXIF: a portrait image among them
    with pytest.raises(FrameSourceError, match="img2.jpg' is 480x640, the folder's first 640x480"):
        list(iter_frames(tmp_path))


def test_hidden_files_in_an_image_folder_are_no_frames(footage):
    """A folder copied from a Mac onto an exFAT card holds `._img0.png` beside `img0.png`
    (AppleDouble metadata, not an image): it was taken for frame 0, and the folder was refused
    with "cannot read image" (and counted one frame too many)."""
    folder, _, frames = footage
    (folder / "._img0.png").write_bytes(b"\x00\x05\x16\x07" + bytes(100))
    (folder / ".hidden.png").write_bytes(b"")
    assert count_frames(folder) == 6 and source_image_size(folder) == (640, 480)
    got = list(iter_frames(folder))
    assert [i for i, _ in got] == list(range(6))
    assert all(np.array_equal(img, frames[i]) for i, img in got)


@pytest.mark.parametrize("bits", [16, 12, 10])
def test_16_bit_images_of_a_12_bit_camera_are_not_read_black(footage, tmp_path, bits):
    """A machine-vision camera's 12-bit frames saved as 16-bit PNGs (values 0..4095) were read
    by OpenCV's top-8-bits conversion as 0..15: no board found in any frame, and no word why."""
    folder, _, frames = footage
    deep = tmp_path / f"deep{bits}"
    deep.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(deep / f"img{i}.png"), (f.astype(np.uint16) << (bits - 8)))
    got = dict(iter_frames(deep))
    assert all(img.dtype == np.uint8 for img in got.values())
    assert all(np.array_equal(got[i], frames[i]) for i in (1, 2, 4))  # the board's white: full
    assert [d.frame for d in detect_in_source(deep, CHARUCO).detections] == [1, 2, 4]
    cv2.imwrite(str(deep / "img0.tif"), np.zeros((480, 640), np.float32))
    with pytest.raises(FrameSourceError, match="img0.tif' holds float32 pixels"):
        list(iter_frames(deep))


@pytest.mark.parametrize("board", [CHARUCO, CHECKER])
def test_detection_refuses_images_it_cannot_read_by_name(board):
    """uint16, float and (H, W, 1) images hit raw OpenCV assertions."""
    image = board.render_image(30, margin_px=30)
    detector = BoardDetector(board)
    for bad in (image.astype(np.uint16), image.astype(np.float32) / 255):
        with pytest.raises(
            BoardError, match=f"8-bit grey, BGR or BGRA image, got dtype {bad.dtype}"
        ):
            detector.detect(bad)
    assert detector.detect(image[..., None]) is not None  # one channel: read as grey
    assert detector.detect(cv2.cvtColor(image, cv2.COLOR_GRAY2BGRA)) is not None


@pytest.mark.parametrize("name", ["CORNER_REFINE_SUBPIX", "ArucoDetector", None])
def test_a_dictionary_must_be_an_aruco_dictionary(name):
    """hasattr(cv2.aruco, name) took any name: CORNER_REFINE_SUBPIX (an int equal to
    DICT_4X4_100's number) was used as that dictionary; others raised TypeError."""
    with pytest.raises(BoardError, match="is unknown to OpenCV"):
        BoardSpec("charuco", 7, 5, 0.04, 0.03, name)


def test_sizes_given_as_text_are_named():
    with pytest.raises(BoardError, match="must be numbers"):
        BoardSpec("charuco", 7, 5, "0.04", 0.03)
