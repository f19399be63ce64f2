"""Reading the suite's TOML files (head, camera, sweep, mount, target) with one-line errors."""

from __future__ import annotations

import tomllib
from pathlib import Path


def read_toml(path: str | Path, error: type[Exception], what: str) -> dict:
    """Parse a TOML file, raising ``error`` with the path and a fix if it is missing or malformed.

    ``what`` completes "give ..." in the missing-file message, e.g. "the path of a camera.toml".
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such file; give {what}")
    try:
        # utf-8-sig: files saved by some editors start with a byte-order mark.
        return tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid TOML ({e})") from None
