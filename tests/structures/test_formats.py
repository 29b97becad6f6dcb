"""The formats chemists have, read through MDAnalysis (and gemmi for PDBx/mmCIF), each on files
MDAnalysisTests ships: GROMACS TPR with its XTC, AMBER prmtop/parm7 with NetCDF and ASCII
trajectories, LAMMPS data with dumps (a triclinic one too), PDBx/mmCIF, BinaryCIF (py-mmcif's
own test file) and multi-model PDB. A broken file of each is refused naming the file (and the
line, in a text format)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from structures.reader import StructureError, load

datafiles = pytest.importorskip("MDAnalysisTests.datafiles")
DATA = Path(datafiles.__file__).parent / "data"


@pytest.mark.parametrize(
    ("files", "atoms", "frames", "boxed"),
    [
        ((datafiles.TPR, datafiles.XTC), 47681, 10, True),
        ((datafiles.TPR2024,), 2263, 1, True),
        ((datafiles.PRMncdf, datafiles.NCDF), 2661, 30, True),
        ((datafiles.PRM7, datafiles.NCDFtruncoct), 5827, 10, True),
        ((datafiles.PRM, datafiles.TRJ), 252, 11, False),
        ((str(DATA / "lammps/chain_initial.data"), str(DATA / "lammps/chain_dump_1.lammpstrj")),
         22, 6, True),
        ((datafiles.LAMMPSdata_triclinic, datafiles.LAMMPSDUMP_triclinic), 17, 1, True),
        ((str(DATA / "mmcif/1YJP.cif"),), 66, 1, False),
        ((str(DATA / "mmcif/5PTI.cif.gz"),), 1104, 1, False),  # a crystal's cell: no box
        ((datafiles.PDBX,), 60, 1, False),
        ((datafiles.PDB_multiframe,), 392, 24, False),
    ],
    ids=["tpr-xtc", "tpr-2024", "prmtop-ncdf", "parm7-nc-truncoct", "prmtop-mdcrd",
         "lammps-data-dump", "lammps-triclinic-dump", "mmcif", "mmcif-gz", "pdbx",
         "pdb-models"],
)  # fmt: skip
def test_each_format_opens_with_its_topology_frames_and_box(
    files: tuple[str, ...], atoms: int, frames: int, boxed: bool
) -> None:
    s = load(files[0], files[1:])
    assert s.topology.n_atoms == atoms and s.n_frames == frames
    assert s.topology.bonds.shape[0] > 0  # from the file, or guessed
    last, box = s.frame(frames - 1)
    assert last.shape == (atoms, 3) and np.isfinite(last).all()
    assert (box is not None) == boxed
    if box is not None:
        assert box.shape == (3, 3) and abs(np.linalg.det(box)) > 0


def test_a_triclinic_lammps_dump_keeps_its_tilted_box() -> None:
    s = load(datafiles.LAMMPSdata_triclinic, [datafiles.LAMMPSDUMP_triclinic])
    _positions, box = s.frame(0)
    assert box is not None and abs(box[1, 0]) > 1.0 and abs(box[2, 0]) > 1.0  # xy and xz tilts


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        (("mmcif/1YJP_invalid.cif.gz",),
         r"1YJP_invalid\.cif\.gz, line 793: group_PDB is 'WRONG', not ATOM or HETATM"),
        (("Amber/ace_mbondi3.error1.parm7", "Amber/ace_mbondi3.nc"),
         r"ace_mbondi3\.error1\.parm7, line 1: a prmtop starts with %VERSION"),
        (("Amber/ace_mbondi3.error2.parm7", "Amber/ace_mbondi3.nc"),
         r"ace_mbondi3\.error2\.parm7 has no %FLAG TITLE section"),
        (("Amber/ace_mbondi3.error3.parm7", "Amber/ace_mbondi3.nc"),
         r"ace_mbondi3\.error3\.parm7, line 14: ATOM_NAME goes on past the NATOM = 6 values"),
        (("Amber/ace_mbondi3.error4.parm7", "Amber/ace_mbondi3.nc"),
         r"ace_mbondi3\.error4\.parm7, line 16: a header line that is not %FLAG"),
        (("Amber/ache_chainid.error5.prmtop.bz2", "Amber/ache.mdcrd"),
         r"ache_chainid\.error5\.prmtop\.bz2, line 4289: RESIDUE_CHAINID holds 37 values, "
         r"POINTERS declares NRES = 38"),
        (("lammps/chain_initial.data", "lammps/spce_no_coords.lammpstrj.bz2"),
         r"spce_no_coords\.lammpstrj\.bz2, line 9: the ATOMS columns name no x, y, z"),
    ],
    ids=["mmcif-group", "parm7-version", "parm7-title", "parm7-overrun", "parm7-header",
         "prmtop-chain-ids", "lammps-dump-columns"],
)  # fmt: skip
def test_a_broken_file_is_refused_naming_the_file_and_the_line(
    files: tuple[str, ...], expected: str
) -> None:
    paths = [str(DATA / f) for f in files]
    with pytest.raises(StructureError, match=expected) as caught:
        load(paths[0], paths[1:])
    assert str(DATA) not in str(caught.value)  # names, never the directories


def test_a_reader_error_says_its_cause_without_directories(tmp_path: Path) -> None:
    """What MDAnalysis wraps ("Failed to construct topology from file /full/path ...") is
    unwrapped to the parser's own words, with the file's name alone."""
    broken = tmp_path / "broken.prmtop"
    source = (DATA / "Amber/ace_mbondi3.parm7").read_text().splitlines(keepends=True)
    at = next(i for i, line in enumerate(source) if line.startswith("%FLAG CHARGE")) + 2
    source[at] = source[at].replace("2.04636429E+00", "not-a-charge!!", 1)  # same width
    broken.write_text("".join(source))
    with pytest.raises(StructureError) as caught:
        load(str(broken), [str(DATA / "Amber/ace_mbondi3.nc")])
    message = str(caught.value)
    assert "not-a-charge" in message and "broken.prmtop" in message, message
    assert str(tmp_path) not in message and "Failed to construct" not in message


BCIF = Path(__file__).parent / "data" / "1bna.bcif.gz"
"""B-DNA dodecamer 1BNA as the PDB packs it in BinaryCIF, from py-mmcif's own test data
(wwPDB, Apache-2.0)."""


def test_a_binarycif_model_opens_as_its_mmcif_does(tmp_path: Path) -> None:
    """The PDB's own packing (its column encodings) read by py-mmcif; and the same model as
    mmCIF text and as BinaryCIF written by py-mmcif open to the same atoms."""
    from mmcif.io.BinaryCifReader import BinaryCifReader
    from mmcif.io.BinaryCifWriter import BinaryCifWriter
    from mmcif.io.PdbxWriter import PdbxWriter

    s = load(str(BCIF))
    assert s.topology.n_atoms == 566 and s.n_frames == 1
    assert {"DA", "DC", "DG", "DT", "HOH"} == set(s.topology.residue_names)
    assert set(s.topology.chain_ids) == {"A", "B"} and s.topology.bonds.shape[0] > 500
    positions, box = s.frame(0)
    assert box is None and s.crystal  # a crystal's unit cell (24.87 x 40.39 x 66.2 A)
    assert np.allclose(s.universe.dimensions[:3], [24.87, 40.39, 66.2])
    np.testing.assert_allclose(positions[0], [18.935, 34.195, 25.617], atol=1e-3)
    block = BinaryCifReader().deserialize(str(BCIF))
    text = tmp_path / "1bna.cif"
    with open(text, "w") as fh:
        PdbxWriter(fh).write(block)
    np.testing.assert_array_equal(load(str(text)).positions(0), positions)
    packed = tmp_path / "1yjp.bcif"
    from mmcif.io.PdbxReader import PdbxReader

    source: list[object] = []
    with open(DATA / "mmcif/1YJP.cif") as fh:
        PdbxReader(fh).read(source)
    assert BinaryCifWriter(dictionaryApi=None).serialize(str(packed), source)
    np.testing.assert_array_equal(
        load(str(packed)).positions(0), load(str(DATA / "mmcif/1YJP.cif")).positions(0)
    )


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        ("rows", r"model\.bcif: atom_site declares 2,000,000,000 rows, the limit is 20,000,000"),
        ("runs", r"model\.bcif: atom_site\.id has run lengths outside 0-20,000,000"),
        ("wrap", r"model\.bcif: atom_site\.id has run lengths outside 0-20,000,000"),
        ("many", r"model\.bcif: it holds more than 25,000,000 values; convert it to mmCIF"),
        ("short", r"model\.bcif: atom_site\.id decodes to 3 values for 566 rows"),
        ("encoding", r"model\.bcif: atom_site\.id has an unknown encoding 'Zip'"),
    ],
)
def test_a_binarycif_that_declares_more_than_it_holds_is_refused_at_once(
    tmp_path: Path, damage: str, expected: str
) -> None:
    """A 600-byte file declaring two billion rows (a run-length column, or a row count) is
    refused before any column is expanded, as is a column that does not fill its rows."""
    import gzip

    import msgpack

    doc = msgpack.unpackb(gzip.decompress(BCIF.read_bytes()), raw=False)
    (atoms,) = [c for c in doc["dataBlocks"][0]["categories"] if c["name"] == "_atom_site"]
    column = next(c for c in atoms["columns"] if c["name"] == "id")
    if damage == "rows":
        atoms["rowCount"] = 2_000_000_000
    if damage == "many":  # 40 categories of 1M rows: each within its limit, not together
        for k in range(40):
            doc["dataBlocks"][0]["categories"].append(
                {**atoms, "name": f"_extra_{k}", "rowCount": 1_000_000}
            )
    pairs = {"runs": [1, 2_000_000_000], "short": [1, 3]}.get(damage, [1, 566])
    encoding = [
        {"kind": "Zip" if damage == "encoding" else "RunLength", "srcType": 3,
         "srcSize": pairs[1]},
        {"kind": "ByteArray", "type": 3},
    ]  # fmt: skip
    if damage == "wrap":  # counts that sum past 2^64 back to a small number
        pairs = [1, 0, 1, 0, 1, 0, 1, 0]
        encoding.insert(1, {"kind": "Delta", "origin": 1 << 62, "srcType": 3})
    column["data"] = {"data": np.asarray(pairs, "<i4").tobytes(), "encoding": encoding}
    bad = tmp_path / "model.bcif"
    bad.write_bytes(msgpack.packb(doc))
    with pytest.raises(StructureError, match=expected):  # by the check, before any expansion
        load(str(bad))


@pytest.mark.parametrize("damage", ["truncated", "not-msgpack", "no-atoms"])
def test_a_broken_binarycif_is_refused_naming_the_file(tmp_path: Path, damage: str) -> None:
    import gzip

    import msgpack

    raw = gzip.decompress(BCIF.read_bytes())
    bad = tmp_path / "model.bcif"
    if damage == "truncated":
        bad.write_bytes(raw[: len(raw) // 2])
        expected = r"cannot read model\.bcif: it is not BinaryCIF \(or it is damaged\)"
    elif damage == "not-msgpack":
        bad.write_bytes(b"data_1BNA\nloop_\n_atom_site.id\n1\n")
        expected = r"cannot read model\.bcif: it is not BinaryCIF \(or it is damaged\)"
    else:
        doc = msgpack.unpackb(raw, raw=False)
        for block in doc["dataBlocks"]:
            block["categories"] = [c for c in block["categories"] if c["name"] != "_atom_site"]
        bad.write_bytes(msgpack.packb(doc))
        expected = r"model\.bcif has no atom_site rows; is it a BinaryCIF model file\?"
    with pytest.raises(StructureError, match=expected) as caught:
        load(str(bad))
    assert str(tmp_path) not in str(caught.value)


def test_a_deposited_crystal_structure_keeps_its_chains_together() -> None:
    """A PDB entry read alone (it says how it was determined) is a crystal's asymmetric unit:
    its unit cell is no periodic box (wrapping each chain into it took 1BD2's complex apart),
    and no bond is guessed across it. A simulation's snapshot, and a trajectory, keep theirs."""
    s = load(str(DATA / "mmcif/1BD2.cif.gz"))
    assert s.crystal and s.universe.dimensions is not None  # the file has a cell
    positions, box = s.frame(0)
    assert box is None
    bonds = s.topology.bonds.to_numpy()
    lengths = np.linalg.norm(positions[bonds[:, 0]] - positions[bonds[:, 1]], axis=1)
    assert lengths.max() < 3.0  # no bond across the cell
    # a simulation's snapshot says nothing of an experiment: its box is a box, alone or not
    snapshot = load(datafiles.PDB_sub_sol)
    assert not snapshot.crystal and snapshot.frame(0)[1] is not None
    moving = load(datafiles.PDB_sub_sol, [datafiles.XTC_sub_sol])
    assert not moving.crystal and moving.frame(0)[1] is not None
