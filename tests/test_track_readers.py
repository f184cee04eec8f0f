"""The reading snippets in docs/formats/tracks_parquet.md run as written against real output.

pandas, polars and duckdb are not project dependencies: their snippets are skipped where the
library is not installed (the pyarrow snippet always runs)."""

import re
from pathlib import Path

import numpy as np
import pytest

from gst.track import SuppliedBoxes, TrackOptions
from tests.track_synthetic import crossing_clip, track_boxes, write_boxes_csv

DOC = Path(__file__).resolve().parents[1] / "docs" / "formats" / "tracks_parquet.md"
N = 12


def blocks(lang: str) -> dict[str, str]:
    """Code blocks of `lang`, keyed by the first line of the paragraph before each."""
    text = DOC.read_text()
    out = {}
    for m in re.finditer(rf"\n([^\n]+)\n\n```{lang}\n(.*?)```", text, re.S):
        out[m.group(1).strip()] = m.group(2)
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    d = tmp_path_factory.mktemp("readers")
    _, boxes, video = crossing_clip(d, N)
    det = SuppliedBoxes.from_file(write_boxes_csv(d / "boxes.csv", boxes, "clip"))
    for name in ("match_cam1", "match cam2"):
        track_boxes(video, d / "tracks", det, video_name=name, options=TrackOptions(prefetch=0))
    return d


def run_python(code: str, cwd: Path, monkeypatch) -> dict:
    monkeypatch.chdir(cwd)
    scope: dict = {}
    exec(compile(code, str(DOC), "exec"), scope)
    return scope


def test_pyarrow_and_helpers_snippet(dataset, monkeypatch):
    code = next(v for k, v in blocks("python").items() if k.startswith("pyarrow and the project"))
    s = run_python(code, dataset, monkeypatch)
    assert s["joints"].shape == (3 * N, 24, 3) and s["long"].shape[0] == 24 * 3 * N
    assert s["meta"]["joint_names"][4] == "left_knee"


def test_pandas_snippet(dataset, monkeypatch):
    pytest.importorskip("pandas")
    code = next(v for k, v in blocks("python").items() if k.startswith("pandas"))
    s = run_python(code, dataset, monkeypatch)
    assert set(s["df"]["video"]) == {"match_cam1"} and s["joints"].shape == (3 * N, 24, 3)
    np.testing.assert_array_equal(s["knee"], s["joints"][:, 4])


def test_polars_snippet(dataset, monkeypatch):
    pytest.importorskip("polars")
    code = next(v for k, v in blocks("python").items() if k.startswith("polars"))
    s = run_python(code, dataset, monkeypatch)
    long = s["long"]
    assert long.height == 2 * 24 * 3 * N and set(long["video"].unique()) == {
        "match_cam1",
        "match cam2",
    }
    assert long.filter(long["joint_index"] == 4)["joint"].unique().to_list() == ["left_knee"]


def test_video_names_as_text_snippet(dataset, monkeypatch):
    pytest.importorskip("polars")
    code = next(v for k, v in blocks("python").items() if k.startswith("Names as text"))
    s = run_python(code, dataset, monkeypatch)
    want = {"match_cam1", "match cam2"}
    assert set(s["t"].column("video").to_pylist()) == want
    assert set(s["df"]["video"].astype(str)) == want and set(s["lf"]["video"]) == want


def test_duckdb_snippet(dataset, monkeypatch):
    duckdb = pytest.importorskip("duckdb")
    sql = next(v for k, v in blocks("sql").items() if k.startswith("duckdb"))
    monkeypatch.chdir(dataset)
    sql = re.sub(r"--[^\n]*", "", sql)
    statements = [s.strip() for s in sql.split(";") if s.strip()]
    counts = duckdb.sql(statements[0]).fetchall()
    assert sorted(counts) == [("match cam2", 3 * N, 3), ("match_cam1", 3 * N, 3)]
    assert len(duckdb.sql(statements[1]).fetchall()) == 2 * 24 * 3 * N
    kv = dict(duckdb.sql(statements[2]).fetchall())
    assert kv["gst.fps"] == "30.0"


def test_the_installed_pyarrow_reads_null_fixed_size_lists(tmp_path):
    """The floor in pyproject (pyarrow >= 26): older readers refuse the null rows that
    `transl_world` and the landmark columns use (docs/formats/tracks_parquet.md)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    col = pa.array([[1.0, 2.0, 3.0], None, [4.0, 5.0, 6.0]], type=pa.list_(pa.float32(), 3))
    pq.write_table(pa.table({"transl_world": col}), tmp_path / "t.parquet")
    back = pq.read_table(tmp_path / "t.parquet").column("transl_world").to_pylist()
    assert back == [[1.0, 2.0, 3.0], None, [4.0, 5.0, 6.0]]


def _relabelled(src: Path, dst: Path, version: int, drop: tuple[str, ...] = ()) -> None:
    import json

    import pyarrow.parquet as pq

    table = pq.read_table(src, partitioning=None)
    table = table.drop_columns([c for c in drop if c in table.column_names])
    meta = dict(table.schema.metadata)
    meta[b"gst.format_version"] = json.dumps(version).encode()
    dst.parent.mkdir(parents=True)
    pq.write_table(table.replace_schema_metadata(meta), dst)


def test_a_folder_of_two_format_versions_keeps_every_column_and_a_newer_one_is_refused(
    dataset, tmp_path
):
    """A folder is read as one dataset, whose schema was its first file's: beside a version 1
    file (no landmarks) the landmark columns of the other videos were dropped without a word,
    and a file of a newer version was read as if it were this one."""
    from gst.track.read import read_metadata, read_tracks

    src = next((dataset / "tracks").rglob("tracks.parquet"))
    assert "landmarks2d" in read_tracks(src).column_names
    mixed = tmp_path / "mixed"
    _relabelled(src, mixed / "video=a_old" / "tracks.parquet", 1, ("landmarks2d", "landmarks_conf"))
    _relabelled(src, mixed / "video=b_new" / "tracks.parquet", 2)
    table = read_tracks(mixed)
    assert {"landmarks2d", "landmarks_conf"} <= set(table.column_names)
    old = table.filter(table.column("video").to_numpy(zero_copy_only=False) == "a_old")
    assert old.num_rows and old.column("landmarks2d").null_count == old.num_rows
    newer = tmp_path / "newer"
    _relabelled(src, newer / "video=a" / "tracks.parquet", 3)
    for read in (read_tracks, read_metadata):
        with pytest.raises(ValueError, match=r"tracks.parquet: tracks format version 3; .*update"):
            read(newer / "video=a" / "tracks.parquet")
    with pytest.raises(ValueError, match="tracks format version 3"):
        read_tracks(newer)


def test_one_videos_folder_reads_with_its_name(dataset):
    """Given `tracks/video=match cam2/` (an easy thing to pass), every row's video was null and
    `videos=["match cam2"]` found no row."""
    from gst.track import read_tracks
    from gst.track.writer import partition_dir

    folder = partition_dir(dataset / "tracks", "match cam2")
    table = read_tracks(folder)
    assert table.num_rows > 0 and set(table.column("video").to_pylist()) == {"match cam2"}
    assert read_tracks(folder, videos=["match cam2"]).num_rows == table.num_rows
    assert read_tracks(folder, videos=["match_cam1"]).num_rows == 0
    whole = read_tracks(dataset / "tracks", videos=["match cam2"])
    assert whole.equals(table)


def test_a_landmark_the_detector_could_not_place_leaves_the_others(tmp_path):
    """One NaN landmark of a detection nulled all 33 of that row."""
    from gst.track import column_array, read_tracks
    from gst.track.detection import Detection

    _, boxes, video = crossing_clip(tmp_path, 6)
    rng = np.random.default_rng(0)

    def landmarks(box, hole):
        x0, y0, x1, y1 = box
        lm = rng.uniform([x0, y0, 0.9], [x1, y1, 1.0], (33, 3)).astype(np.float32)
        if hole:
            lm[5] = np.nan
        return lm

    dets = {
        i: [
            Detection(boxes[i, k].astype(float), 0.9, landmarks=landmarks(boxes[i, k], i == 3))
            for k in range(boxes.shape[1])
        ]
        for i in range(6)
    }
    result = track_boxes(
        video, tmp_path / "tracks", SuppliedBoxes(dets), video_name="v",
        options=TrackOptions(prefetch=0),
    )  # fmt: skip
    table = read_tracks(result.path)
    assert table.column("landmarks2d").null_count == 0
    xy, conf = column_array(table, "landmarks2d"), column_array(table, "landmarks_conf")
    hit = table.column("frame").to_numpy() == 3
    assert (conf[hit][:, 5] == 0).all() and (xy[hit][:, 5] == 0).all()
    assert (conf[hit][:, 6] > 0.5).all() and (conf[~hit] > 0.5).all()
