"""Selections on protocol topologies equal MDAnalysis's own on the files they came from; bad
selections name their position; the default layers hide solvent and single out ligands."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import protocol as p
from structures.reader import topology_of
from structures.selection import (
    SelectionError,
    Selector,
    check_syntax,
    default_layers,
    is_dynamic,
    parse,
    polymer_atoms,
    solvent_atoms,
)

mda = pytest.importorskip("MDAnalysis")
pytest.importorskip("MDAnalysisTests")
from MDAnalysis.lib.mdamath import triclinic_vectors  # noqa: E402
from MDAnalysisTests.datafiles import DCD, GRO, PSF, XTC  # noqa: E402

from tests.fresh import python_c  # noqa: E402

STATIC = [
    "protein",
    "backbone",
    "name CA",
    "resname LYS ARG",
    "resid 10-20 and not name H*",
    "protein and not backbone",
    "not (resname SOL WAT HOH TIP3 NA CL)",
    "same residue as name OG1",
    "byres name NZ",
    "(resid 1:30 or resname GLY) and not name C* N*",
    "nucleic",
]


def _universe(*files: str) -> object:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mda.Universe(*files)


def test_adk_psf_selections_equal_mdanalysis() -> None:
    u = _universe(PSF, DCD)
    topo = topology_of(u, guess_bonds=False)
    sel = Selector(topo)
    for text in [*STATIC, "segid 4AKE and name CA", "bonded name SG"]:
        want = u.select_atoms(text).indices  # type: ignore[attr-defined]
        assert np.array_equal(sel.select(text), want), text


def test_solvated_gro_selections_equal_mdanalysis_frame_by_frame() -> None:
    u = _universe(GRO, XTC)
    topo = topology_of(u, guess_bonds=False)
    assert topo.n_atoms == 47681
    sel = Selector(topo)
    for text in [*STATIC, "water", "resname NA+"]:
        want = u.select_atoms(text).indices  # type: ignore[attr-defined]
        assert np.array_equal(sel.select(text), want), text
    dynamic = [
        "byres around 4 protein",
        "around 3.5 resname NA+",
        "protein and prop z > 30",
        "same x as (resname NA+)",
    ]
    for ts in u.trajectory[:3]:  # type: ignore[attr-defined]
        box = triclinic_vectors(ts.dimensions)
        for text in dynamic:
            assert is_dynamic(text)
            want = u.select_atoms(text).indices  # type: ignore[attr-defined]
            assert np.array_equal(sel.select(text, ts.positions, box), want), text


def test_villin_demo_selections_equal_mdanalysis() -> None:
    """The demo's villin as OpenMM ships it: solvated, before the demo removes the water."""
    pytest.importorskip("openmm")
    from simulation_adapters.openmm_systems import VILLIN_PDB

    u = _universe(VILLIN_PDB)
    topo = topology_of(u, guess_bonds=False)
    sel = Selector(topo)
    for text in [*STATIC, "resid 1-10 and name CA", "water", "resname HOH"]:
        want = u.select_atoms(text).indices  # type: ignore[attr-defined]
        assert np.array_equal(sel.select(text), want), text
    assert default_layers(topo, 1.5) == [{"name": "polymer", "selection": "protein or nucleic"}]
    protein = u.select_atoms("protein")  # type: ignore[attr-defined]
    dry = topology_of(mda.Merge(protein), guess_bonds=False)
    assert default_layers(dry, 1.5) == []  # the demo's dry villin: every atom, one layer


@pytest.mark.parametrize(
    ("text", "where", "says"),
    [
        ("protien or name CA", 0, "protien"),
        ("name CA and (resid 4", 20, "ends too soon. Expected: ')'"),
        ("name CA or", 10, "ends too soon"),
        ("name CA)", 7, ")"),
        ("resid 1- and name CA", 6, "1-"),
        ("around 5 foo", 9, "foo"),
        ("   ", 0, "empty"),
    ],
)
def test_a_bad_selection_names_its_position(text: str, where: int, says: str) -> None:
    topo = topology_of(_universe(PSF), guess_bonds=False)
    with pytest.raises(SelectionError) as info:
        Selector(topo).select(text, np.zeros((topo.n_atoms, 3), np.float32))
    assert info.value.position == where
    assert says in info.value.reason
    assert f"at character {where + 1}" in str(info.value)
    with pytest.raises(SelectionError):
        check_syntax(text)


def test_syntax_check_without_a_topology() -> None:
    for text in [*STATIC, "around 5 resname LIG", "byres (around 3 name CA)"]:
        check_syntax(text)
    for deep in ("(" * 600 + "name CA" + ")" * 600, "not " * 500 + "all"):
        with pytest.raises(SelectionError, match="deeper than the parser can follow") as info:
            check_syntax(deep)
        assert "`not`" in str(info.value) and "fewer of them" in str(info.value)
    with pytest.raises(SelectionError, match="or around D sel"):
        check_syntax("within 3 of resname LIG")  # VMD's form: the error says how to write it


def _rename(topo: p.Topology, residues: set[int], name: str) -> p.Topology:
    resids = topo.residue_ids.to_numpy()
    names = [
        name if int(r) in residues else n for r, n in zip(resids, topo.residue_names, strict=True)
    ]
    return topo.model_copy(update={"residue_names": names})


def test_default_layers_hide_solvent_and_single_out_a_ligand() -> None:
    u = _universe(GRO)
    topo = topology_of(u, guess_bonds=False)
    assert default_layers(topo, 1.5) == [{"name": "polymer", "selection": "protein or nucleic"}]
    # the last protein residue renamed: a ligand among protein and water, at a finer scale
    last = int(topo.residue_ids.to_numpy()[u.select_atoms("protein").indices[-1]])  # type: ignore[attr-defined]
    with_ligand = _rename(topo, {last}, "LIG")
    layers = default_layers(with_ligand, 2.0)
    assert layers == [
        {"name": "polymer", "selection": "protein or nucleic"},
        {"name": "ligand", "selection": "resname LIG", "sigma_A": 1.0},
    ]
    sel = Selector(with_ligand)
    shown = np.union1d(sel.select("protein or nucleic"), sel.select("resname LIG"))
    hidden = solvent_atoms(with_ligand)
    assert len(np.intersect1d(shown, hidden)) == 0
    assert len(shown) + len(hidden) == topo.n_atoms


def test_polymer_atoms_are_mdanalysis_protein_or_nucleic() -> None:
    for files in [(GRO,), (PSF,)]:
        u = _universe(*files)
        topo = topology_of(u, guess_bonds=False)
        want = u.select_atoms("protein or nucleic").indices  # type: ignore[attr-defined]
        assert np.array_equal(polymer_atoms(topo), want)


def test_a_box_of_water_alone_stays_whole() -> None:
    u = _universe(GRO)
    water = u.select_atoms("water")  # type: ignore[attr-defined]
    topo = topology_of(mda.Merge(water), guess_bonds=False)
    assert default_layers(topo, 1.5) == []


def test_secondary_structure_is_mdanalysis_dssp_per_atom() -> None:
    from MDAnalysis.analysis.dssp import DSSP

    u = _universe(PSF, DCD)
    topo = topology_of(u, guess_bonds=False)
    codes = Selector(topo).secondary(u.atoms.positions)  # type: ignore[attr-defined]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        found = DSSP(u).run(stop=1).results.dssp[0]
    want = np.array([{"H": 1, "E": 2}.get(str(c), 0) for c in found], np.uint8)
    residues = u.select_atoms("protein").residues  # type: ignore[attr-defined]
    assert len(residues) == len(want)
    for residue, code in zip(residues, want, strict=True):
        assert (codes[residue.atoms.indices] == code).all()
    assert (want == 1).sum() > 50 and (want == 2).sum() > 20  # adk: helices and a sheet


@pytest.mark.parametrize(
    ("text", "at"),
    [("around nan name CA", 7), ("around inf name CA", 7), ("point 1 2 nan 3", 10)],
)
def test_a_number_that_is_not_finite_is_refused_by_name(text: str, at: int) -> None:
    """`around nan` answered "ValueError: cannot convert float NaN to integer" (the pricing's
    arithmetic), `around inf` an OverflowError."""
    with pytest.raises(SelectionError) as info:
        parse(text)
    assert info.value.reason == "a distance or coordinate is not a finite number"
    assert info.value.position == at
    parse("around 5 name CA")  # the control


HELD_IMPORT = """
'''A thread imports MDAnalysis, held just after its selection module has loaded (before the
topology attributes that register keywords such as `index`); the main thread parses then.'''
import importlib.abc
import importlib.util
import sys
import threading
import time

HOLD_S = 1.5


class Hold(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != "MDAnalysis.core.selection":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        sys.meta_path.insert(0, self)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            time.sleep(HOLD_S)  # the rest of MDAnalysis has not registered its keywords yet

        spec.loader.exec_module = exec_module
        return spec


sys.meta_path.insert(0, Hold())
importer = threading.Thread(target=lambda: __import__("MDAnalysis"))
importer.start()
deadline = time.monotonic() + 60
while not hasattr(sys.modules.get("MDAnalysis.core.selection"), "Parser"):
    assert time.monotonic() < deadline
    time.sleep(0.01)
from structures.selection import parse  # noqa: E402

parse("around 3 index 0:9")
importer.join()
print("parsed")
"""


def test_a_selection_parsed_while_another_thread_imports_mdanalysis_waits_for_it() -> None:
    """A fresh server's first selection check could run while another thread was importing
    MDAnalysis: its selection module was loaded but not yet the topology attributes that
    register `index`, `name`, `resid`, ... and a valid layer was refused ("Unknown selection
    token: 'index'"). In a fresh interpreter a thread's import is held just there while the
    main thread parses."""
    run = python_c(HELD_IMPORT, timeout=120)
    assert run.returncode == 0 and "parsed" in run.stdout, run.stderr[-2000:]
