"""Periodic frames on the device held against MDAnalysis' own transformations (unwrap,
center_in_box, wrap, NoJump, fit_rot_trans) on MDAnalysisTests' solvated systems: adenylate
kinase in a rhombic dodecahedron (GROMACS TPR/XTC, molecules cut by the box) and tz2 in a
truncated octahedron (AMBER parm7/NetCDF), both triclinic."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from server.render.boxes import Options, usable_box
from server.render.periodic import Molecules, PeriodicTransform
from structures.reader import topology_of

mda = pytest.importorskip("MDAnalysis")
datafiles = pytest.importorskip("MDAnalysisTests.datafiles")
from MDAnalysis import transformations as T  # noqa: E402, N812

TOLERANCE_A = 2e-3
"""float32 positions of up to 100 A, moved by float32 box vectors and a rotation."""


def universe(kind: str) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kind == "adk":
            return mda.Universe(datafiles.TPR, datafiles.XTC)
        return mda.Universe(datafiles.PRM7, datafiles.NCDFtruncoct)


@pytest.fixture(scope="module", params=["adk", "tz2"])
def system(request: pytest.FixtureRequest) -> tuple[str, Any, Any]:
    u = universe(request.param)
    return request.param, u, topology_of(u, guess_bonds=False)


def oracle(kind: str, steps: Callable[[Any], list[Any]]) -> Any:
    """A universe of the same files with MDAnalysis' transformations `steps(u)` on."""
    u = universe(kind)
    u.trajectory.add_transformations(*steps(u))
    return u


_CUT: dict[str, npt.NDArray[np.int64]] = {}


def cut(u: Any) -> Any:
    """The molecules a bond of which the box cuts in the first frames: MDAnalysis' `unwrap`
    of the others leaves them as they are (and costs a second per frame over 20,000 waters)."""
    kind = "adk" if u.atoms.n_atoms == 47681 else "tz2"
    if kind not in _CUT:
        bonds = u.atoms.bonds.indices
        found: set[int] = set()
        for _ts in frames(u, 10):
            x = u.atoms.positions
            long = np.linalg.norm(x[bonds[:, 0]] - x[bonds[:, 1]], axis=1) > 4.0
            found.update(bonds[long, 0].tolist())
        fragments = {int(u.atoms[i].fragindex) for i in found}
        atoms = [f.indices for f in u.atoms.fragments if int(f[0].fragindex) in fragments]
        _CUT[kind] = np.concatenate(atoms) if atoms else np.zeros(0, np.int64)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            u.trajectory[0]
    return u.atoms[_CUT[kind]]


def wrap_fragments(u: Any) -> Callable[[Any], Any]:
    """MDAnalysis' wrap of whole molecules by their centres of geometry."""

    def step(ts: Any) -> Any:
        u.atoms.wrap(compound="fragments", center="cog")
        return ts

    return step


def frames(u: Any, count: int) -> Iterator[Any]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield from u.trajectory[:count]


def protein(u: Any) -> Any:
    return np.asarray(u.select_atoms("protein").indices, dtype=np.int32)


def test_molecules_are_the_bond_graphs_connected_parts(system: tuple[str, Any, Any]) -> None:
    _kind, u, topology = system
    mol = Molecules.of(topology)
    fragments = u.atoms.fragments
    assert mol.n_molecules == len(fragments)
    for frag in fragments[:50] + fragments[-50:]:
        ids = mol.molecule[frag.indices]
        assert (ids == ids[0]).all()
        assert mol.parent[frag.indices[0]] == frag.indices[0]  # the lowest index is the root
    # every tree edge is a bond
    bonds = {tuple(sorted(b)) for b in u.atoms.bonds.indices.tolist()}
    child = np.flatnonzero(mol.parent != np.arange(mol.n_atoms))
    assert all(tuple(sorted((int(i), int(mol.parent[i])))) in bonds for i in child)


@pytest.mark.parametrize(
    ("mode", "centred", "steps"),
    [
        ("whole", False, lambda u: [T.unwrap(cut(u))]),
        ("wrap", False, lambda u: [T.wrap(u.atoms)]),
        (
            "wrap",
            True,
            lambda u: [
                T.unwrap(cut(u)),
                T.center_in_box(u.select_atoms("protein")),
                T.wrap(u.atoms),
            ],
        ),
        (
            "molecules",
            True,
            lambda u: [
                T.unwrap(cut(u)),
                T.center_in_box(u.select_atoms("protein")),
                wrap_fragments(u),
            ],
        ),
        ("molecules", False, lambda u: [T.unwrap(cut(u)), wrap_fragments(u)]),
    ],
    ids=["whole", "wrap", "wrap-centred", "molecules-centred", "molecules"],
)
def test_each_frame_as_mdanalysis_transforms_it(
    device: str,
    system: tuple[str, Any, Any],
    mode: Any,
    centred: bool,
    steps: Callable[[Any], list[Any]],
) -> None:
    kind, u, topology = system
    ref = oracle(kind, steps)
    transform = PeriodicTransform(device)
    transform.set_topology(topology)
    options = Options(mode=mode, centre=protein(u) if centred else None)
    for ts in frames(u, 2):
        raw = ts.positions.copy()
        shown = transform.apply(raw, ts.triclinic_dimensions, options)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref.trajectory[ts.frame]
        error = np.abs(shown.positions - ref.atoms.positions).max()
        assert error < TOLERANCE_A, (ts.frame, error)


def test_unwrap_follows_every_atom_as_nojump_does(
    device: str, system: tuple[str, Any, Any]
) -> None:
    kind, u, topology = system
    ref = oracle(kind, lambda r: [T.unwrap(cut(r)), T.NoJump(check_continuity=False)])
    transform = PeriodicTransform(device)
    transform.set_topology(topology)
    for ts in frames(u, 10):
        shown = transform.apply(ts.positions.copy(), ts.triclinic_dimensions, Options("unwrap"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref.trajectory[ts.frame]
        error = np.abs(shown.positions - ref.atoms.positions).max()
        assert error < TOLERANCE_A, (ts.frame, error)


@pytest.mark.parametrize("fit", ["rotation", "translation"])
def test_the_fit_superposes_a_selection_on_the_first_frame_as_mdanalysis_does(
    device: str, system: tuple[str, Any, Any], fit: str
) -> None:
    kind, u, topology = system
    text = "backbone"

    def steps(r: Any) -> list[Any]:
        return [
            T.unwrap(cut(r)),
            T.center_in_box(r.select_atoms("protein")),
            wrap_fragments(r),
        ]

    reference = oracle(kind, steps)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reference.trajectory[0]
    target = reference.select_atoms(text)
    fitted = T.fit_rot_trans if fit == "rotation" else T.fit_translation
    ref = oracle(kind, lambda r: [*steps(r), fitted(r.select_atoms(text), target)])
    transform = PeriodicTransform(device)
    transform.set_topology(topology)
    atoms = np.asarray(u.select_atoms(text).indices, dtype=np.int32)
    options = Options(mode="molecules", centre=protein(u), fit=fit, fit_atoms=atoms)  # type: ignore[arg-type]
    moved = 0.0
    for ts in frames(u, 3):
        shown = transform.apply(ts.positions.copy(), ts.triclinic_dimensions, options)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref.trajectory[ts.frame]
        error = np.abs(shown.positions - ref.atoms.positions).max()
        assert error < TOLERANCE_A, (ts.frame, error)
        moved = max(moved, float(np.abs(shown.rotation - np.eye(3)).max()))
    if fit == "rotation":
        assert moved > 1e-3  # the frames really were rotated


def test_a_box_that_is_no_cell_leaves_the_frame_as_sent(device: str) -> None:
    """A PDB's placeholder CRYST1 (1 A) would tear every molecule apart: it is no box."""
    u = universe("adk")
    topology = topology_of(u, guess_bonds=False)
    transform = PeriodicTransform(device)
    transform.set_topology(topology)
    raw = u.atoms.positions.copy()
    assert usable_box(np.eye(3)) is None and usable_box(np.eye(3) * np.nan) is None
    shown = transform.apply(raw, np.eye(3), Options(mode="molecules"))
    np.testing.assert_array_equal(shown.positions, raw)
    assert shown.cell is None


def test_a_displayed_frame_is_never_written_again(device: str) -> None:
    """A shown frame lives on (the session's newest positions, a temporal filter's frames, a
    movie's queue): the next frame's display must not write into it."""
    u = universe("tz2")
    topology = topology_of(u, guess_bonds=False)
    transform = PeriodicTransform(device)
    transform.set_topology(topology)
    box = np.asarray(mda.lib.mdamath.triclinic_vectors(u.dimensions), np.float32)
    first = transform.apply(u.atoms.positions.copy(), box, Options(mode="molecules"))
    kept = first.positions.copy()
    for shift in (3.0, 7.0):
        later = transform.apply(u.atoms.positions + shift, box, Options(mode="molecules"))
        assert not np.shares_memory(later.positions, first.positions)
    np.testing.assert_array_equal(first.positions, kept)


def test_a_rotation_fit_on_atoms_along_a_line_translates_only(device: str) -> None:
    """Atoms on one line leave the turn about it free: the fit moves the frame onto the
    reference without turning it (it had turned frames by arbitrary angles)."""
    u = universe("tz2")
    topology = topology_of(u, guess_bonds=False)
    transform = PeriodicTransform(device)
    transform.set_topology(topology)
    line = np.arange(0, 40, 10, dtype=np.int32)
    raw = u.atoms.positions.copy()
    raw[line] = np.array([[10.0, 10.0, 10.0]]) + np.outer(np.arange(4), [1.5, 0.0, 0.0])
    options = Options(mode="off", fit="rotation", fit_atoms=line)
    first = transform.apply(raw, None, options)
    np.testing.assert_allclose(first.rotation, np.eye(3), atol=1e-6)
    turned = raw.copy()
    turned[line] = raw[line][:, [1, 0, 2]] + 3.0  # the line turned by 90 degrees and moved
    later = transform.apply(turned, None, options)
    np.testing.assert_allclose(later.rotation, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(
        later.positions[line].mean(axis=0), raw[line].mean(axis=0), atol=1e-3
    )
