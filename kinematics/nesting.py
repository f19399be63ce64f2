"""How deeply a text file nests its brackets, counted before a recursive parser reads it.

tomllib, json and our BVH reader recurse once per level: a file of 5000 nested arrays (or
3000 nested JOINTs) ends in a RecursionError, not in a message. Every reader of such a file
calls :func:`deeper_than` first and refuses a file nested beyond :data:`MAX_NESTING` with a
one-line error. The count skips strings and comments, so brackets inside them do not count.
This lives in ``kinematics`` only because every package may import it (the import rule).
"""

from __future__ import annotations

import re

#: Deepest nesting any of our files needs is under 40 (a BVH skeleton's chain from the hips to
#: a fingertip); 200 leaves room and stays far below Python's recursion limit.
MAX_NESTING = 200

_TOKENS = {
    # JSON: double-quoted strings with escapes; brackets and braces.
    "json": re.compile(r'"(?:\\.|[^"\\])*"|[\[\]{}]'),
    # TOML: multi-line and single-line basic and literal strings, comments; brackets and braces.
    "toml": re.compile(r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"(?:\\.|[^"\\\n])*"|\'[^\'\n]*\'|#[^\n]*|[\[\]{}]'),
    # BVH: braces only (no strings, no comments).
    "braces": re.compile(r"[{}]"),
}
_OPEN, _CLOSE = "[{", "]}"


def deeper_than(text: str, syntax: str, limit: int = MAX_NESTING) -> int | None:
    """The 1-based line where ``text`` first nests more than ``limit`` levels, or None.

    syntax : "json", "toml" or "braces" (what counts as a string or a comment). Unbalanced
    closing brackets are left to the parser to report.
    """
    depth = 0
    for m in _TOKENS[syntax].finditer(text):
        tok = m.group()
        if tok in _OPEN:
            depth += 1
            if depth > limit:
                return text.count("\n", 0, m.start()) + 1
        elif tok in _CLOSE:
            depth = max(depth - 1, 0)
    return None


def nesting_message(where: str, line: int, limit: int = MAX_NESTING) -> str:
    """The one-line refusal for a file nested beyond ``limit`` at ``line``."""
    return (f"{where} line {line}: nested more than {limit} levels deep (lists or tables inside each other); "
            f"no file of this kind needs that, so it is refused: check how it was made")
