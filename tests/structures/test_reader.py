"""Reading structures into topologies: formats, guessed elements and bonds, readable errors."""

from __future__ import annotations

import gzip
import os
import re
from pathlib import Path

import numpy as np
import pytest
from MDAnalysisTests.datafiles import DCD, GRO, MMCIF, PDBX, PSF, XTC, PDB_multiframe, PDB_small

from structures.errors import StructureError
from structures.reader import lammps_atom_style, load
from tests.adapters.lammps_helpers import write_argon_data


def test_lammps_data_with_only_masses(tmp_path: Path) -> None:
    data = tmp_path / "argon.data"
    write_argon_data(data, 3)
    assert lammps_atom_style(str(data)) == "id type x y z"
    s = load(str(data))
    assert s.topology.n_atoms == 27 and s.n_frames == 1
    assert set(s.topology.elements) == {"Ar"}  # named from the mass, 39.948
    assert s.topology.names[:2] == ["Ar1", "Ar2"] and s.topology.bonds.shape == (0, 2)
    assert s.positions(0)[0].tolist() == pytest.approx([1.95, 1.95, 1.95])


def test_lammps_data_without_a_style_comment_names_the_fix(tmp_path: Path) -> None:
    data = tmp_path / "bare.data"
    write_argon_data(data, 2)
    data.write_text(data.read_text().replace("Atoms # atomic", "Atoms"))
    with pytest.raises(StructureError, match="Atoms # full"):
        load(str(data))
    assert load(str(data), atom_style="id type x y z").topology.n_atoms == 8


def test_formats_and_guessed_bonds() -> None:
    assert load(PSF, [DCD]).n_frames == 98
    assert load(GRO, [XTC], guess_bonds=False).n_frames == 10
    pdb = load(PDB_multiframe)
    assert pdb.n_frames == 24 and pdb.topology.bonds.shape[0] > 380
    cif = load(os.path.join(MMCIF, "1YJP.cif"))
    assert cif.topology.n_atoms == 66 and cif.topology.bonds.shape[0] >= 55
    assert cif.topology.elements[:3] == ["N", "C", "C"]
    assert load(PDBX).topology.n_atoms == 60


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("/nope.pdb", ()), "no such file"),
        ((PSF, ()), "has no coordinates"),
        ((PSF, (XTC,)), "same number of atoms"),
        ((__file__, ()), "unsupported structure format 'py'"),
        ((PSF, (__file__,)), "unsupported trajectory format 'py'"),
    ],
)
def test_unreadable_input_is_a_structure_error(args: tuple, message: str) -> None:
    with pytest.raises(StructureError, match=message):
        load(args[0], args[1])


def test_garbage_file_is_a_structure_error(tmp_path: Path) -> None:
    junk = tmp_path / "junk.pdb"
    junk.write_bytes(b"\x00\x01 not a structure \xff" * 10)
    with pytest.raises(StructureError):
        load(str(junk))


def test_a_bare_topology_is_enough_for_the_imd_bridge() -> None:
    s = load(PSF, require_coordinates=False)
    assert s.n_frames == 0 and s.topology.n_atoms == 3341
    assert s.topology.bonds.shape[0] == 3365  # from the PSF, nothing guessed


@pytest.mark.parametrize(
    ("name", "text", "says"),
    [
        (
            "coords.pdb",
            "HEADER x\nATOM      1  N   ALA A   1      1x.000  2.000   3.000  1.00  0.00\n",
            "coords.pdb, line 2: x (columns 31-38) is not a number",
        ),
        ("prose.pdb", "hello world\nthis is not a pdb\n", "no ATOM or HETATM records"),
        (
            "far.pdb",
            "ATOM      1  CA  ALA A   1    1.00e+30   0.000   0.000  1.00  0.00           C\n",
            "far.pdb, line 1: x (columns 31-38) lies past 1e+06 A from the origin",
        ),
        (
            "far.xyz",
            "1\ncomment\nC 0 0 -5e7\n",
            "far.xyz, line 3: z lies past 1e+06 A",
        ),
        (
            "short.gro",
            "t\n  2\n    1ALA      N    1   0.1   0.2   0.3\n",
            "declares 2 atoms on line 2 but has 1",
        ),
        (
            "letters.gro",
            "t\n  1\n    1ALA      N    1   0.1   abc   0.3\n 1 1 1\n",
            "letters.gro, line 3: an atom line without numeric x, y, z",
        ),
        (
            "count.xyz",
            "three\ncomment\nC 0 0 0\n",
            "count.xyz, line 1: line 1 should be the number",
        ),
        (
            "atom.xyz",
            "2\ncomment\nC 0 0 0\nN 1 x 0\n",
            "atom.xyz, line 4: an atom line should read",
        ),
    ],
)
def test_damaged_text_files_name_the_file_the_line_and_the_problem(
    tmp_path: Path, name: str, text: str, says: str
) -> None:
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(StructureError, match=re.escape(says)):
        load(str(path))


def test_bonds_are_guessed_across_the_periodic_box() -> None:
    """A GRO file has no bonds: they are guessed from distances, the box's minimum image
    included, so a molecule the box cuts stays one molecule (every bond of the TPR found)."""
    import MDAnalysis as mda
    from MDAnalysisTests.datafiles import TPR

    guessed = load(GRO).topology.bonds.to_numpy()
    found = {tuple(sorted(b)) for b in guessed.tolist()}
    u = mda.Universe(TPR, GRO)
    x = u.atoms.positions
    bonds = u.atoms.bonds.indices
    cut = bonds[np.linalg.norm(x[bonds[:, 0]] - x[bonds[:, 1]], axis=1) > 40.0]
    assert len(cut) > 10  # the box cuts these
    assert all(tuple(sorted(b)) in found for b in cut.tolist())
    assert all(tuple(sorted(b)) in found for b in bonds.tolist())


def test_an_xtc_declaring_more_atoms_than_the_limit_is_refused_before_reading(
    tmp_path: Path,
) -> None:
    """The server's isolated reader checks an XTC's header against its atom limit (a header
    claiming two billion atoms had the reader try to allocate 24 GiB)."""
    from structures.isolated import IsolatedStructure, ReadLimits

    data = bytearray(Path(XTC).read_bytes())
    data[4:8] = (2_000_000_000).to_bytes(4, "big")
    bad = tmp_path / "huge.xtc"
    bad.write_bytes(bytes(data))
    with pytest.raises(StructureError, match=r"huge\.xtc declares 2000000000 atoms a frame"):
        IsolatedStructure(GRO, [str(bad)], ReadLimits(max_atoms=100_000))
    with IsolatedStructure(GRO, [XTC], ReadLimits(max_atoms=100_000)) as fine:
        assert fine.n_frames == 10


def test_unreadable_files_are_told_in_words_not_in_the_readers_internals(tmp_path: Path) -> None:
    """A negative atom count was "the reader crashed on it (... likely out of memory)"; atoms
    all at one point "Cutoff 3.4 too large for box (max 0.0)"; an empty atom table "index 0
    is out of bounds for axis 0 with size 0"; a DCD named .xyz had its bytes quoted."""
    from structures.isolated import IsolatedStructure, ReadLimits

    (tmp_path / "neg.xyz").write_text("-5\ncomment\nC 0 0 0\n")
    atom = "ATOM  {:5d}  CA  ALA A{:4d}       0.000   0.000   0.000  1.00  0.00           C\n"
    (tmp_path / "point.pdb").write_text("".join(atom.format(i, i) for i in range(1, 200)))
    (tmp_path / "empty.cif").write_text("data_x\nloop_\n_atom_site.id\n1\n")
    (tmp_path / "dcd.xyz").write_bytes(Path(DCD).read_bytes())
    said = {
        "neg.xyz": "line 1 declares -5 atoms, not at least 1",
        "point.pdb": "its 199 atoms span 0.00 A, less than a bond",
        "empty.cif": "it has no atom records the reader could use",
        "dcd.xyz": "should be the number of atoms, found binary data, not text",
    }
    for name, words in said.items():
        with pytest.raises(StructureError, match=re.escape(words)) as err:
            IsolatedStructure(str(tmp_path / name), [], ReadLimits(max_atoms=100_000))
        assert "\\x" not in str(err.value) and "crashed" not in str(err.value)
    with pytest.raises(StructureError, match="found binary data, not text"):
        IsolatedStructure(PSF, [str(tmp_path / "dcd.xyz")], ReadLimits(max_atoms=100_000))


def test_binary_bytes_in_a_text_format_are_named_as_such(tmp_path: Path) -> None:
    """Random bytes named .prmtop were refused quoting forty of them, named .mol2 with
    "'utf-8' codec can't decode byte 0xbd in position 0"; every text format now says what it
    found, and a text file with a stray byte that is not UTF-8 is told so by that byte."""
    from structures.isolated import IsolatedStructure, ReadLimits

    noise = np.random.default_rng(7).integers(0, 256, 20_000, dtype=np.uint8).tobytes()
    for name in ("x.prmtop", "x.mol2", "x.psf", "x.crd", "x.pqr", "x.data"):
        (tmp_path / name).write_bytes(noise)
        with pytest.raises(StructureError) as err:
            IsolatedStructure(str(tmp_path / name), [], ReadLimits(max_atoms=100_000))
        suffix = name.split(".")[1]
        assert f"{name}: found binary data, not text (a .{suffix} file is text)" in str(err.value)
    (tmp_path / "x.pdb.gz").write_bytes(gzip.compress(noise))
    with pytest.raises(StructureError, match=re.escape("x.pdb: found binary data, not text")):
        IsolatedStructure(str(tmp_path / "x.pdb.gz"), [], ReadLimits(max_atoms=100_000))
    with pytest.raises(StructureError, match=re.escape("x.mdcrd: found binary data, not text")):
        (tmp_path / "x.mdcrd").write_bytes(noise)
        IsolatedStructure(PSF, [str(tmp_path / "x.mdcrd")], ReadLimits(max_atoms=100_000))
    stray = Path(PDB_small).read_bytes().replace(b"REMARK", b"REMARK \xe9", 1)
    (tmp_path / "stray.pdb").write_bytes(stray)  # text with one latin-1 byte: named, not sniffed
    with pytest.raises(StructureError) as err:
        IsolatedStructure(str(tmp_path / "stray.pdb"), [], ReadLimits(max_atoms=100_000))
    assert "stray.pdb" in str(err.value) and "binary" not in str(err.value)
    assert "a byte that is not UTF-8 text (0xe9); save the file as UTF-8" in str(err.value)


def test_a_dcd_cut_inside_a_frame_is_noted(tmp_path: Path) -> None:
    """MDAnalysis reads the whole frames of a DCD cut short and drops the rest in silence: the
    reader says so, in one file or in a chain of them."""
    whole = load(PSF, [DCD])
    assert whole.n_frames == 98 and whole.notes == ()
    cut = tmp_path / "cut.dcd"
    cut.write_bytes(Path(DCD).read_bytes()[:50_000])
    short = load(PSF, [str(cut)])
    assert short.n_frames == 1
    (note,) = short.notes
    assert note.startswith("cut.dcd ends inside a frame after 1 whole frame(s)") and (
        "cut short" in note
    )
    chained = load(PSF, [DCD, str(cut)])
    assert chained.n_frames == 99 and len(chained.notes) == 1
