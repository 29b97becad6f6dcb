"""The error every structure reader raises (the file readers and their line checks alike),
and what a reader's own exception says, as its message."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence


class StructureError(ValueError):
    """A structure or trajectory that cannot be used, with a message naming the problem."""


def reason(exc: BaseException, paths: Sequence[str]) -> str:
    """What a reader's error says: the innermost cause (MDAnalysis wraps a parser's own words
    in "Failed to construct topology from file ..."), its first line, with the files named by
    their names alone (never the server's directories)."""
    inner = exc
    while True:
        cause = inner.__cause__ or inner.__context__
        if cause is None or cause is inner or not str(cause).strip():
            break
        inner = cause
    lines = [line.strip() for line in str(inner).splitlines() if line.strip()]
    text = " ".join(lines[:2]) if lines else type(inner).__name__
    if isinstance(inner, IndexError) and "size 0" in text:  # a table of atoms with no rows
        return "it has no atom records the reader could use"
    if isinstance(inner, UnicodeDecodeError):  # a stray byte in mostly text (binary is sniffed)
        byte = inner.object[inner.start : inner.start + 1].hex()
        return f"it holds a byte that is not UTF-8 text (0x{byte}); save the file as UTF-8"
    if re.search(r"\\x[0-9a-f]{2}|[\x00-\x08\x0e-\x1f\x7f]", text):  # quoting binary bytes
        return "its contents are not text in the format its name says (binary data?)"
    for path in paths:
        text = text.replace(os.path.abspath(path), os.path.basename(path))
        text = text.replace(path, os.path.basename(path))
    return re.sub(r"(?:/[^/\s'\"]+)+/([^/\s'\"]+)", r"\1", text)
