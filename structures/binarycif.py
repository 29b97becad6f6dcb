"""BinaryCIF, the PDB's binary mmCIF (msgpack with column encodings), read by wwPDB's own
py-mmcif and handed to the mmCIF reader as text: one reader of models, whatever their packing.

py-mmcif expands what a file declares (a run-length column of two billion rows from a 541-byte
file) and logs and swallows a decoding failure; it also reads a locator that looks like a URL
from the network. So the file is checked first (`check`: every category's row count within the
limit and all values within `MAX_VALUES`, every column decoding to exactly its category's rows,
the lengths found by decoding only the integer encodings that set them, each run length
checked before any is summed), only absolute local paths are passed on, and an empty
result is refused here, naming the file.
"""

from __future__ import annotations

import gzip
import logging
import os
from typing import Any

import numpy as np
import numpy.typing as npt

from structures.errors import StructureError

logging.getLogger("mmcif").setLevel(logging.CRITICAL)  # a refusal is ours to word

MAX_ROWS = 20_000_000
"""Rows a category may declare when the caller sets no atom limit (the PDB's largest entries
hold a few million atoms)."""
MAX_BYTES = 1 << 30
"""The most a BinaryCIF may hold once inflated."""
MAX_VALUES = 25_000_000
"""Values (rows times columns, over every category) a BinaryCIF may decode to: py-mmcif keeps
each as a Python object (about 75 bytes), so this is about 2 GB, a model of about a million
atoms; a larger one is refused (convert it to mmCIF)."""

_BYTE_TYPES = {1: "<i1", 2: "<i2", 3: "<i4", 4: "<u1", 5: "<u2", 6: "<u4", 32: "<f4", 33: "<f8"}
"""ByteArray's type codes."""
_SAME_LENGTH = ("Delta", "FixedPoint", "IntervalQuantization")


class _BadError(Exception):
    """What is wrong with the file (worded for the user)."""


def to_mmcif(path: str, folder: str, max_rows: int | None = None) -> str:
    """`path`'s first data block written as mmCIF text into `folder` (the path returned), once
    `check` passes with `max_rows` (None: `MAX_ROWS`)."""
    name = os.path.basename(path)
    check(path, MAX_ROWS if max_rows is None else max_rows)
    try:
        from mmcif.io.BinaryCifReader import BinaryCifReader
        from mmcif.io.PdbxWriter import PdbxWriter
    except ImportError:  # pragma: no cover - depends on the install
        raise StructureError("reading BinaryCIF needs py-mmcif: pip install mmcif") from None
    containers = BinaryCifReader().deserialize(os.path.abspath(path))
    if not containers:
        raise StructureError(f"cannot read {name}: it is not BinaryCIF (or it is damaged)")
    block = containers[0]
    if not block.exists("atom_site") or block.getObj("atom_site").getRowCount() == 0:
        raise StructureError(f"{name} has no atom_site rows; is it a BinaryCIF model file?")
    stem = name[: -len(".gz")] if name.lower().endswith(".gz") else name
    out = os.path.join(folder, f"{stem}.cif")
    with open(out, "w", encoding="utf-8") as fh:
        PdbxWriter(fh).write([block])
    return out


def check(path: str, max_rows: int) -> None:
    """Refuse a file that is not BinaryCIF, declares more than `max_rows` rows in a category
    or more than `MAX_VALUES` values in all, or has a column that does not decode to its
    category's rows."""
    import msgpack

    name = os.path.basename(path)
    try:
        doc = msgpack.unpackb(_read(path), raw=False, strict_map_key=False)
        blocks = doc["dataBlocks"] if isinstance(doc, dict) else None
        if not isinstance(blocks, list):
            raise _BadError("it has no data blocks")
        categories = [c for block in blocks for c in block.get("categories") or []]
        # what each category and all of them declare, before any column is decoded
        declared = sum(_rows(c, max_rows) * len(c.get("columns") or []) for c in categories)
        if declared > MAX_VALUES:
            raise _BadError(f"it holds more than {MAX_VALUES:,} values; convert it to mmCIF")
        for category in categories:
            _check_category(category, max_rows)
    except _BadError as exc:
        raise StructureError(f"cannot read {name}: {exc}") from None
    except StructureError:
        raise
    except Exception:
        raise StructureError(
            f"cannot read {name}: it is not BinaryCIF (or it is damaged)"
        ) from None


def _read(path: str) -> bytes:
    opener: Any = gzip.open if path.lower().endswith(".gz") else open
    with opener(path, "rb") as fh:
        data: bytes = fh.read(MAX_BYTES + 1)
    if len(data) > MAX_BYTES:
        raise _BadError(f"it holds more than {MAX_BYTES:,} bytes")
    return data


def _rows(category: dict[str, Any], max_rows: int) -> int:
    """The rows a category declares, refused past `max_rows`."""
    label = str(category.get("name", "?")).lstrip("_")
    rows = category.get("rowCount")
    if not isinstance(rows, int) or rows < 0:
        raise _BadError(f"{label} has no row count")
    if rows > max_rows:
        raise _BadError(f"{label} declares {rows:,} rows, the limit is {max_rows:,}")
    return rows


def _check_category(category: dict[str, Any], max_rows: int) -> None:
    label = str(category.get("name", "?")).lstrip("_")
    rows = _rows(category, max_rows)
    for column in category.get("columns") or []:
        where = f"{label}.{column.get('name', '?')}"
        for part in ("data", "mask"):
            encoded = column.get(part)
            if encoded is None:
                continue
            n = _length(encoded["data"], encoded["encoding"], max_rows, where)
            if n != rows:
                raise _BadError(f"{where} decodes to {n:,} values for {rows:,} rows")


def _length(data: bytes, encodings: list[dict[str, Any]], limit: int, where: str) -> int:
    """How many values `data` decodes to, decoding (in numpy) only what sets the length."""
    values: npt.NDArray[Any] | None = None
    length = len(data)
    for enc in reversed(encodings):
        kind = enc.get("kind")
        if kind == "ByteArray":
            dtype = np.dtype(_BYTE_TYPES.get(enc.get("type"), "V"))
            if dtype.kind == "V" or len(data) % dtype.itemsize:
                raise _BadError(f"{where} has a byte array of unknown type or size")
            values = np.frombuffer(data, dtype=dtype)
        elif kind == "IntegerPacking":
            values = _unpack(_ints(values, where), int(enc["byteCount"]), bool(enc["isUnsigned"]))
        elif kind == "RunLength":
            pairs = _ints(values, where)
            counts = pairs[1::2]
            if len(pairs) % 2 or (counts < 0).any() or (counts > limit).any():
                raise _BadError(f"{where} has run lengths outside 0-{limit:,}")
            total = int(counts.sum())  # each at most `limit`: no overflow
            if total > limit:
                raise _BadError(f"{where} expands to {total:,} values, the limit is {limit:,}")
            values = np.repeat(pairs[0::2], counts)
        elif kind == "Delta":
            values = np.cumsum(_ints(values, where)) + int(enc.get("origin", 0))
        elif kind in _SAME_LENGTH:
            values = np.zeros(len(_any(values, where)), np.int64)
        elif kind == "StringArray":
            offsets = _length(enc["offsets"], enc["offsetEncoding"], limit, where)
            if offsets > len(enc.get("stringData", "")) + 2:  # the empty string and an end
                raise _BadError(f"{where} has more string offsets than characters")
            return _length(data, enc["dataEncoding"], limit, where)
        else:
            raise _BadError(f"{where} has an unknown encoding {kind!r}")
        length = len(values)
    return length


def _any(values: npt.NDArray[Any] | None, where: str) -> npt.NDArray[Any]:
    if values is None:
        raise _BadError(f"{where} decodes from raw bytes without a byte array")
    return values


def _ints(values: npt.NDArray[Any] | None, where: str) -> npt.NDArray[np.int64]:
    found = _any(values, where)
    if found.dtype.kind not in "iu":
        raise _BadError(f"{where} packs integers from non-integers")
    return found.astype(np.int64)


def _unpack(values: npt.NDArray[np.int64], byte_count: int, unsigned: bool) -> npt.NDArray[Any]:
    """IntegerPacking's decode: a value at the packed type's limit carries on into the next."""
    bits = 8 * byte_count
    upper = (1 << bits) - 1 if unsigned else (1 << (bits - 1)) - 1
    lower = 0 if unsigned else -(1 << (bits - 1))
    carry = (values == upper) | ((values == lower) & (not unsigned))
    ends = ~carry
    group = np.concatenate([[0], np.cumsum(ends)[:-1]]) if len(values) else values
    out = np.bincount(group, weights=values.astype(np.float64), minlength=int(ends.sum()))
    return out[: int(ends.sum())].astype(np.int64)
