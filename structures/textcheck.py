"""Line-level checks of the text formats people write by hand or convert between (PDB, GRO,
XYZ, PDBx/mmCIF, AMBER prmtop, LAMMPS dump).

MDAnalysis reports a damaged text file with whatever its parser tripped over ("index 0 is out
of bounds"). These checks run first and say which file, which line and what is wrong with it, in
one pass over the file; a file they accept is then read by MDAnalysis as before.
"""

from __future__ import annotations

import bz2
import gzip
import math
import os
import re
import shlex
from collections.abc import Callable, Iterator
from itertools import islice
from typing import IO, Any

from protocol.limits import MAX_COORDINATE_A
from structures.errors import StructureError

MAX_QUOTED = 60


def _open(path: str, text: bool) -> IO[Any]:
    """The file, unpacked where its name ends .gz or .bz2; as text, stray bytes replaced."""
    suffix = os.path.splitext(path)[1].lower()
    opener: Callable[..., IO[Any]] = open
    if suffix in (".gz", ".bz2"):
        opener = gzip.open if suffix == ".gz" else bz2.open
    if text:
        return opener(path, "rt", encoding="utf-8", errors="replace")
    return opener(path, "rb")


def _lines(path: str) -> Iterator[tuple[int, str]]:
    with _open(path, text=True) as fh:
        for number, line in enumerate(fh, 1):
            yield number, line.rstrip("\r\n")


BINARY_FORMATS = frozenset({"bcif", "tpr", "dcd", "xtc", "trr", "nc", "ncdf"})
"""The formats read here that are not text; every other one is."""
SNIFF_BYTES = 4096
"""How much of a text format's file is looked at for binary data before it is read."""


def refuse_binary(path: str, fmt: str) -> None:
    """Refuse a file of a text format (`fmt`, any but BINARY_FORMATS) whose first bytes are
    not text: a NUL, or more than 1 % control characters or bytes that are not UTF-8. Readers
    otherwise answer with the bytes they tripped over ("'utf-8' codec can't decode byte
    0xbd", or a prmtop check quoting forty of them)."""
    if fmt in BINARY_FORMATS:
        return
    try:
        with _open(path, text=False) as fh:
            head = fh.read(SNIFF_BYTES)
    except (OSError, EOFError):  # a damaged archive: its reader says what is wrong
        return
    if not head:
        return
    text = head.decode("utf-8", errors="replace")
    if len(head) == SNIFF_BYTES:  # a character cut at the end is not the file's fault
        text = text[:-1]
    odd = sum(1 for c in text if c == "\ufffd" or (ord(c) < 32 and c not in "\t\r\n\f"))
    if "\0" in text or odd > 0.01 * max(len(text), 1):
        raise StructureError(
            f"{os.path.basename(path)}: found binary data, not text (a .{fmt} file is text)"
        )


def _fail(path: str, number: int, line: str, why: str) -> StructureError:
    quoted = line if len(line) <= MAX_QUOTED else line[:MAX_QUOTED] + "..."
    return StructureError(f"{os.path.basename(path)}, line {number}: {why}: {quoted!r}")


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _coordinate(text: str) -> str | None:
    """What is wrong with a coordinate's text (None: nothing): not a number, not finite, or
    past `MAX_COORDINATE_A` from the origin, where no ray can be marched."""
    try:
        value = float(text)
    except ValueError:
        return "is not a number"
    if not math.isfinite(value):
        return "is not a finite number"
    if abs(value) > MAX_COORDINATE_A:
        return f"lies past {MAX_COORDINATE_A:g} A from the origin (the limit)"
    return None


def _check_xyz_values(path: str, number: int, line: str, values: list[str]) -> None:
    for axis, value in zip("xyz", values, strict=True):
        if (why := _coordinate(value)) is not None:
            raise _fail(path, number, line, f"{axis} {why}: {value!r}")


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
            if (why := _coordinate(line[a:b])) is not None:
                raise _fail(
                    path, number, line, f"{axis} (columns {a + 1}-{b}) {why}: {line[a:b]!r}"
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
        _check_xyz_values(path, number, line, fields[:3])
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
    if count < 1:
        raise _fail(path, number, count_line, "line 1 should be the number of atoms, at least 1")
    next(lines, None)  # the comment
    seen = 0
    for number, line in islice(lines, count):
        seen += 1
        fields = line.split()
        if len(fields) < 4 or not all(_number(f) for f in fields[1:4]):
            raise _fail(path, number, line, "an atom line should read 'element x y z'")
        _check_xyz_values(path, number, line, fields[1:4])
    if seen < count:
        raise StructureError(
            f"{os.path.basename(path)} declares {count} atoms on line 1 but has {seen} atom lines"
        )


def _cif_values(line: str) -> list[str] | None:
    """The values on one line of a CIF loop (quoted values kept whole); None if unbalanced."""
    try:
        return shlex.split(line, comments=False, posix=True)
    except ValueError:
        return None


def check_mmcif(path: str) -> None:
    """The atom_site loop: every row has one value per column, a group of ATOM or HETATM, and
    numeric Cartn_x, Cartn_y, Cartn_z; the file needs such a loop."""
    state = "out"  # out | tags (a loop's header) | rows (the atom_site loop's values)
    tags: list[str] = []
    pending: list[str] = []
    start, found = 0, False
    for number, line in _lines(path):
        text = line.strip()
        if state == "rows":
            if text and text[0] not in "#_;" and not text.startswith(("loop_", "data_")):
                values = _cif_values(text)
                if values is None:
                    raise _fail(path, number, line, "an atom_site row with an unclosed quote")
                if not pending:
                    start = number
                pending += values
                if len(pending) >= len(tags):
                    _check_atom_row(path, start, line, tags, pending)
                    pending = []
                continue
            if pending:
                raise _fail(
                    path, start, line,
                    f"an atom_site row with {len(pending)} values for {len(tags)} columns",
                )  # fmt: skip
            state = "out"
        if text == "loop_":
            state, tags = "tags", []
        elif state == "tags":
            if text.startswith("_"):
                tags.append(text.split()[0])
            elif tags and tags[0].startswith("_atom_site."):
                state, found, start = "rows", True, number
                values = _cif_values(text)
                if values is None:
                    raise _fail(path, number, line, "an atom_site row with an unclosed quote")
                pending = values
                if len(pending) >= len(tags):
                    _check_atom_row(path, start, line, tags, pending)
                    pending = []
            else:
                state = "out"
    if pending:
        raise StructureError(
            f"{os.path.basename(path)}, line {start}: the file ends inside an atom_site row"
        )
    if not found:
        raise StructureError(
            f"{os.path.basename(path)} has no atom_site loop; is it an mmCIF file?"
        )


def _check_atom_row(path: str, number: int, line: str, tags: list[str], values: list[str]) -> None:
    if len(values) != len(tags):
        raise _fail(
            path,
            number,
            line,
            f"an atom_site row with {len(values)} values for {len(tags)} columns",
        )
    row = dict(zip(tags, values, strict=True))
    group = row.get("_atom_site.group_PDB")
    if group is not None and group not in ("ATOM", "HETATM"):
        raise _fail(path, number, line, f"group_PDB is {group!r}, not ATOM or HETATM")
    for axis in ("Cartn_x", "Cartn_y", "Cartn_z"):
        value = row.get(f"_atom_site.{axis}")
        if value is not None and (why := _coordinate(value)) is not None:
            raise _fail(path, number, line, f"{axis} {why}: {value!r}")


_FORMAT = re.compile(r"%FORMAT\((\d+)([aAiIeEfF])(\d+)")
_COUNTS = {"ATOM_NAME": 0, "CHARGE": 0, "MASS": 0, "ATOM_TYPE_INDEX": 0, "RESIDUE_LABEL": 11,
           "RESIDUE_POINTER": 11, "RESIDUE_CHAINID": 11}  # fmt: skip
"""prmtop sections and the POINTERS entry (NATOM, NRES) that counts their values."""


def check_prmtop(path: str) -> None:
    """An AMBER prmtop: %VERSION first, %FLAG sections each with a %FORMAT, POINTERS, and as
    many atom names, charges, masses and residues as POINTERS declares."""
    lines = _lines(path)
    first = next(lines, None)
    if first is None or not first[1].startswith("%VERSION"):
        number, line = first if first is not None else (1, "")
        raise _fail(path, number, line, "a prmtop starts with %VERSION")
    sections: dict[str, tuple[int, int, str]] = {}  # name -> (line, values, the %FLAG line)
    pointers: list[int] = []
    flag, per_line, width, text = "", 0, 0, False
    for number, line in lines:
        if line.startswith("%"):
            head = line.split()[0] if line.split() else line
            if head == "%FLAG":
                name = line.split()[1] if len(line.split()) > 1 else ""
                flag, per_line, width, text = name, 0, 0, False
                sections[flag] = (number, 0, line)
            elif head.startswith("%FORMAT"):
                if not flag:
                    raise _fail(path, number, line, "a %FORMAT line before any %FLAG")
                match = _FORMAT.match(line.strip())
                # a composite format, (i2,a78), holds free text: its values are not counted
                per_line, width = (int(match[1]), int(match[3])) if match else (0, -1)
                text = match is not None and match[2] in "aA"
            elif head != "%COMMENT":
                raise _fail(
                    path, number, line, "a header line that is not %FLAG, %FORMAT or %COMMENT"
                )
            continue
        if not flag or not width:
            raise _fail(path, number, line, "values before a %FLAG and its %FORMAT")
        if width < 0:
            continue
        # a text value may be blank: trailing spaces count there, never after numbers
        length = len(line) if text else len(line.rstrip())
        count = (length + width - 1) // width if line.strip() else 0
        if count > per_line:
            raise _fail(path, number, line, f"{count} values on a line of %FORMAT({per_line}..)")
        at, seen, head_line = sections[flag]
        sections[flag] = (at, seen + count, head_line)
        slot = _COUNTS.get(flag)
        if slot is not None and slot < len(pointers) and seen + count > pointers[slot]:
            what = "NATOM" if slot == 0 else "NRES"
            raise _fail(
                path, number, line, f"{flag} goes on past the {what} = {pointers[slot]} values "
                "POINTERS declares",
            )  # fmt: skip
        if flag == "POINTERS":
            for i in range(count):
                field = line[i * width : (i + 1) * width]
                try:
                    pointers.append(int(field))
                except ValueError:
                    raise _fail(
                        path, number, line, f"POINTERS value {field!r} is not an integer"
                    ) from None
    if "TITLE" not in sections and "CTITLE" not in sections:  # CHAMBER files: CTITLE
        raise StructureError(f"{os.path.basename(path)} has no %FLAG TITLE section")
    if "POINTERS" not in sections:
        raise StructureError(f"{os.path.basename(path)} has no %FLAG POINTERS section")
    for name, slot in _COUNTS.items():
        if name in sections and slot < len(pointers):
            at, seen, head_line = sections[name]
            if seen != pointers[slot]:
                what = "NATOM" if slot == 0 else "NRES"
                raise _fail(
                    path, at, head_line,
                    f"{name} holds {seen} values, POINTERS declares {what} = {pointers[slot]}",
                )  # fmt: skip


def check_lammps_dump(path: str) -> None:
    """The first frame of a LAMMPS dump: ITEM: TIMESTEP, NUMBER OF ATOMS, BOX BOUNDS, then an
    ATOMS header naming coordinates and one numeric line per atom."""
    lines = _lines(path)
    expected = ("ITEM: TIMESTEP", None, "ITEM: NUMBER OF ATOMS", None, "ITEM: BOX BOUNDS")
    head: list[tuple[int, str]] = list(islice(lines, 5))
    for (number, line), want in zip(head, expected, strict=False):
        if want is not None and not line.startswith(want):
            raise _fail(path, number, line, f"a LAMMPS dump frame needs {want!r} here")
    if len(head) < 5:
        raise StructureError(f"{os.path.basename(path)} ends inside its first frame's header")
    number, count_line = head[3]
    try:
        count = int(count_line.split()[0])
    except (ValueError, IndexError):
        raise _fail(path, number, count_line, "the number of atoms is not an integer") from None
    for number, line in islice(lines, 3):
        if len(line.split()) < 2 or not all(_number(v) for v in line.split()):
            raise _fail(path, number, line, "a box bounds line should hold numbers")
    header = next(lines, None)
    if header is None or not header[1].startswith("ITEM: ATOMS"):
        number, line = header if header is not None else (0, "")
        raise _fail(path, number, line, "a LAMMPS dump frame needs 'ITEM: ATOMS ...' here")
    columns = header[1].split()[2:]
    axes = [c for c in columns if c in ("x", "y", "z", "xs", "ys", "zs", "xu", "yu", "zu",
                                         "xsu", "ysu", "zsu")]  # fmt: skip
    if len(axes) < 3:
        raise _fail(path, header[0], header[1], "the ATOMS columns name no x, y, z")
    seen = 0
    for number, line in islice(lines, count):
        seen += 1
        values = line.split()
        if len(values) < len(columns):
            raise _fail(path, number, line, f"{len(values)} values for {len(columns)} columns")
        for name, value in zip(columns, values, strict=False):
            if name in axes and (why := _coordinate(value)) is not None:
                raise _fail(path, number, line, f"{name} {why}: {value!r}")
    if seen < count:
        raise StructureError(
            f"{os.path.basename(path)} declares {count} atoms but its first frame has {seen}"
        )


CHECKS = {
    "pdb": check_pdb,
    "ent": check_pdb,
    "gro": check_gro,
    "xyz": check_xyz,
    "cif": check_mmcif,
    "mmcif": check_mmcif,
    "pdbx": check_mmcif,
    "prmtop": check_prmtop,
    "parm7": check_prmtop,
    "lammpsdump": check_lammps_dump,
    "lammpstrj": check_lammps_dump,
    "dump": check_lammps_dump,
}
