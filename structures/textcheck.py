"""Line-level checks of the text formats people write by hand (PDB, GRO, XYZ).

MDAnalysis reports a damaged text file with whatever its parser tripped over ("index 0 is out
of bounds"). These checks run first and say which file, which line and what is wrong with it, in
one pass over the file; a file they accept is then read by MDAnalysis as before.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from itertools import islice

from structures.errors import StructureError

MAX_QUOTED = 60


def _lines(path: str) -> Iterator[tuple[int, str]]:
    with open(path, encoding="utf-8", errors="replace") as fh:
        for number, line in enumerate(fh, 1):
            yield number, line.rstrip("\r\n")


def _fail(path: str, number: int, line: str, why: str) -> StructureError:
    quoted = line if len(line) <= MAX_QUOTED else line[:MAX_QUOTED] + "..."
    return StructureError(f"{os.path.basename(path)}, line {number}: {why}: {quoted!r}")


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def check_pdb(path: str) -> None:
    """ATOM/HETATM records need numeric x, y, z in columns 31-54; the file needs at least one."""
    atoms = 0
    for number, line in _lines(path):
        if not line.startswith(("ATOM", "HETATM")):
            continue
        atoms += 1
        if len(line) < 54:
            raise _fail(
                path, number, line, "an atom record shorter than its coordinates (54 columns)"
            )
        for axis, (a, b) in zip("xyz", ((30, 38), (38, 46), (46, 54)), strict=True):
            if not _number(line[a:b]):
                raise _fail(
                    path,
                    number,
                    line,
                    f"{axis} (columns {a + 1}-{b}) is not a number: {line[a:b]!r}",
                )
    if atoms == 0:
        raise StructureError(
            f"{os.path.basename(path)} has no ATOM or HETATM records; is it a PDB file?"
        )


def check_gro(path: str) -> None:
    """Line 2 is the atom count; each atom line has numeric x, y, z after column 20."""
    lines = _lines(path)
    head = list(islice(lines, 2))
    if len(head) < 2:
        raise StructureError(f"{os.path.basename(path)} ends before its atom count (line 2)")
    number, count_line = head[1]
    try:
        count = int(count_line.split()[0])
    except (ValueError, IndexError):
        raise _fail(path, number, count_line, "line 2 should be the number of atoms") from None
    seen = 0
    for number, line in lines:
        if seen == count:
            return  # the box line
        seen += 1
        fields = line[20:].split()
        if len(fields) < 3 or not all(_number(f) for f in fields[:3]):
            raise _fail(path, number, line, "an atom line without numeric x, y, z after column 20")
    if seen < count:
        raise StructureError(
            f"{os.path.basename(path)} declares {count} atoms on line 2 but has {seen} atom lines"
        )


def check_xyz(path: str) -> None:
    """Line 1 is the atom count, line 2 a comment, then `element x y z` per atom."""
    lines = _lines(path)
    first = next(lines, None)
    if first is None:
        raise StructureError(f"{os.path.basename(path)} is empty")
    number, count_line = first
    try:
        count = int(count_line.split()[0])
    except (ValueError, IndexError):
        raise _fail(path, number, count_line, "line 1 should be the number of atoms") from None
    next(lines, None)  # the comment
    seen = 0
    for number, line in islice(lines, count):
        seen += 1
        fields = line.split()
        if len(fields) < 4 or not all(_number(f) for f in fields[1:4]):
            raise _fail(path, number, line, "an atom line should read 'element x y z'")
    if seen < count:
        raise StructureError(
            f"{os.path.basename(path)} declares {count} atoms on line 1 but has {seen} atom lines"
        )


CHECKS = {"pdb": check_pdb, "ent": check_pdb, "gro": check_gro, "xyz": check_xyz}
