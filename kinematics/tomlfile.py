"""Reading the suite's TOML files (head, camera, sweep, mount, target) with one-line errors, and
short echoes of their values for those messages."""

from __future__ import annotations

import tomllib
from pathlib import Path

from .nesting import deeper_than, nesting_message


def read_toml(path: str | Path, error: type[Exception], what: str) -> dict:
    """Parse a TOML file, raising ``error`` with the path and a fix if it is missing or malformed.

    ``what`` completes "give ..." in the missing-file message, e.g. "the path of a camera.toml".
    """
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: is a folder, not a file; give {what}")
    if not path.is_file():
        raise error(f"{path}: no such file; give {what}")
    try:
        # utf-8-sig: files saved by some editors start with a byte-order mark.
        text = path.read_text(encoding="utf-8-sig")
        line = deeper_than(text, "toml")
        if line is not None:
            raise error(nesting_message(str(path), line))
        return tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid TOML ({e})") from None


def brief(value, limit: int = 60) -> str:
    """``repr(value)`` cut to about ``limit`` characters, for messages: a value echoed from a
    file may be a list of millions of numbers."""
    if isinstance(value, (list, tuple)) and len(value) > 8:
        return f"[{len(value)} items: {brief(list(value[:3]), limit)[1:-1]}, ...]"
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 4] + " ..."
