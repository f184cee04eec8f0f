"""Markers shared by the stages' settings models (pydantic), read by whatever runs them."""

from __future__ import annotations

__all__ = ["NAMES_FILE", "names_file"]

# `Field(..., json_schema_extra=NAMES_FILE)`: a text setting that is either a built-in name
# ('anny', 'smpl') or a path to a file of the user's. A runner resolves such a text against the
# config's folder when a file of that name lies there; any other text setting (a method, a
# preset, a device) is never taken for a path.
NAMES_FILE = {"names_file": True}


def names_file(field) -> bool:
    """Whether a pydantic field (`FieldInfo`) carries the NAMES_FILE marker."""
    extra = field.json_schema_extra
    return isinstance(extra, dict) and all(extra.get(k) == v for k, v in NAMES_FILE.items())
