"""Columnar records: a dataclass whose fields are equal-length arrays, one row per element."""

from __future__ import annotations

from dataclasses import fields


class Columns:
    """Mixin for a dataclass of N rows held as equal-length arrays (first axis N): `len()` is N,
    the length of its first field."""

    __slots__ = ()

    def __len__(self) -> int:
        return len(getattr(self, fields(self)[0].name))
