"""The base of result records whose JSON form is their fields, as `dataclasses.asdict` gives."""

from __future__ import annotations

from dataclasses import asdict

__all__ = ["Record"]


class Record:
    """Mixin for dataclasses: `to_dict()` is `dataclasses.asdict(self)` (nested dataclasses
    become dicts too). Records with a different JSON layout override it."""

    __slots__ = ()

    def to_dict(self) -> dict:
        return asdict(self)
