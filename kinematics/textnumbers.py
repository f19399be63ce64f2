"""Numbers in whitespace-separated text files (TUM trajectories and logs, BVH frames): which
field of a line that failed to parse is the one to name in the error message."""

from __future__ import annotations

from typing import Iterable


def is_float(text: str) -> bool:
    """Whether ``float(text)`` accepts ``text`` (so "nan" and "inf" are numbers here; callers
    that need finite values check that separately, with their own message)."""
    try:
        float(text)
        return True
    except ValueError:
        return False


def first_non_number(fields: Iterable[str]) -> str | None:
    """The first field that ``float`` refuses, or None if every field is a number."""
    return next((f for f in fields if not is_float(f)), None)
