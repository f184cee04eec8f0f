"""MarkerModel's table checks."""

from __future__ import annotations

import json

import pytest

from gst.body.markers import MarkerModel


def test_a_table_with_non_finite_offsets_is_refused_naming_the_marker(tmp_path):
    """JSON reads NaN and Infinity: such a table loaded and put its markers at NaN."""
    doc = MarkerModel.fallback().to_json()
    doc["markers"][3]["offset"][1] = float("nan")
    path = tmp_path / "markers.json"
    path.write_text(json.dumps(doc))
    name = doc["markers"][3]["name"]
    with pytest.raises(
        ValueError, match=rf"markers.json: MarkerModel: offsets of \['{name}'\] are NaN or Inf"
    ):
        MarkerModel.load(path)
    doc["markers"][3]["offset"][1] = 0.01
    assert len(MarkerModel.from_json(doc)) == len(doc["markers"])
