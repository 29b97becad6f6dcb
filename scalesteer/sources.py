"""Objects a notebook already holds, as sessions: MDAnalysis universes and atom groups, MDTraj
trajectories, ASE atoms, OpenMM simulations.

Trajectories (MDAnalysis, MDTraj, ASE) are played to the session by the trajectory replay
adapter (`simulation_adapters/replay.py`), on a thread of this process and from a reader of its
own (the user's `Universe` keeps its current frame), steerable from the dashboard and the
widget like any replay: pause, seek, speed, loop. An OpenMM `Simulation` gets the steering
reporter (`simulation_adapters/openmm_reporter.py`); it runs when the notebook steps it, or on
a thread of its own with `steps=`.

MDAnalysis reads the topology of every trajectory kind (elements, residues, bonds guessed where
the object has none): `pip install scalesteer[notebook]`; MDTraj and ASE only where installed.
"""

from __future__ import annotations

import os
import threading
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np


class SourceError(TypeError):
    """An object that cannot feed a session (the message says what would)."""


def kind_of(obj: Any) -> str:
    """`mdanalysis`, `mdtraj`, `ase` or `openmm`, from the object's type (without importing
    any of those packages)."""
    module = type(obj).__module__.split(".")[0]
    if module == "MDAnalysis":
        return "mdanalysis"
    if module == "mdtraj":
        return "mdtraj"
    if module == "ase" or (
        isinstance(obj, Sequence | list) and obj and type(obj[0]).__module__.startswith("ase")
    ):
        return "ase"
    if module == "openmm" and type(obj).__name__ == "Simulation":
        return "openmm"
    raise SourceError(
        f"cannot make a session of a {type(obj).__module__}.{type(obj).__name__}: give an "
        "MDAnalysis Universe or AtomGroup, an MDTraj Trajectory, ASE Atoms (or a list of "
        "them) or an OpenMM Simulation"
    )


# ---------------------------------------------------------------------- trajectories


class _Frames:
    """The `trajectory` a replay reads: frames `frames` of `reader` (a reader of its own),
    sliced to `indices` when the session shows part of the system."""

    def __init__(self, reader: Any, indices: np.ndarray | None, frames: Sequence[int]) -> None:
        self.reader = reader
        self.indices = indices
        self.frames = list(frames)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> Any:
        with warnings.catch_warnings():  # some readers warn on every frame (DCD's copies)
            warnings.simplefilter("ignore")
            ts = self.reader[self.frames[index]]
        return ts if self.indices is None else ts.copy_slice(self.indices)


class _Played:
    """What a `Structure` holds as its universe: the frames to play."""

    def __init__(self, frames: _Frames) -> None:
        self.trajectory = frames


def structure_of(obj: Any, frame: int | None = None) -> Any:
    """The replay adapter's `Structure` (topology message and frames) of a trajectory object;
    `frame` plays that frame alone."""
    from structures.reader import Structure

    kind = kind_of(obj)
    if kind == "mdanalysis":
        universe, atoms, title = _mdanalysis(obj)
    elif kind == "mdtraj":
        universe, title = _from_mdtraj(obj)
        atoms = universe.atoms
    elif kind == "ase":
        universe, title = _from_ase(obj)
        atoms = universe.atoms
    else:
        raise SourceError("an OpenMM Simulation is not a trajectory: use Client.open")
    n_frames = len(universe.trajectory)
    if n_frames == 0:
        raise SourceError(f"{title or 'the object'} has no coordinates")
    if frame is not None and not -n_frames <= frame < n_frames:
        raise SourceError(f"frame {frame} is out of range: the trajectory has {n_frames}")
    frames = range(n_frames) if frame is None else [frame % n_frames]
    whole = atoms.n_atoms == universe.atoms.n_atoms
    topology = _topology(universe if whole else atoms, title, whole)
    with warnings.catch_warnings():  # DCD's reader warns of its copies
        warnings.simplefilter("ignore", DeprecationWarning)
        reader = universe.trajectory.copy()  # the user's universe keeps its own current frame
    played = _Frames(reader, None if whole else np.asarray(atoms.indices), frames)
    return Structure(topology=topology, universe=_Played(played))


def _mdanalysis(obj: Any) -> tuple[Any, Any, str]:
    universe = obj.universe
    atoms = obj.atoms
    if atoms.n_atoms == 0:
        raise SourceError("the atom group is empty")
    name = getattr(universe, "filename", None)
    title = os.path.basename(name) if isinstance(name, str) else "MDAnalysis universe"
    return universe, atoms, title


class _Bonds:
    """Bonds as `topology_of` reads them: `indices` (pairs) and a length."""

    def __init__(self, indices: np.ndarray) -> None:
        self.indices = indices

    def __len__(self) -> int:
        return len(self.indices)


class _Part:
    """What `topology_of` reads of a universe, for a part of one: its atoms, and the bonds
    among them numbered within the part (an `mda.Merge` of the part builds the same, slowly:
    2 s for 10,000 atoms)."""

    def __init__(self, atoms: Any) -> None:
        self.atoms = atoms
        universe = atoms.universe
        try:
            pairs = np.asarray(universe.bonds.indices, dtype=np.int64).reshape(-1, 2)
        except Exception:  # no bonds in the topology: guessed from the positions instead
            pairs = np.zeros((0, 2), dtype=np.int64)
        local = np.full(universe.atoms.n_atoms, -1, dtype=np.int64)
        local[np.asarray(atoms.indices)] = np.arange(atoms.n_atoms)
        mapped = local[pairs]
        self.bonds = _Bonds(mapped[(mapped >= 0).all(axis=1)])


def _topology(source: Any, title: str, whole: bool) -> Any:
    from structures.reader import topology_of

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if whole:
            return topology_of(source, title=title)
        part = _Part(source)
        if len(part.bonds) < source.n_atoms // 2:  # bonds to guess: on a universe of the part
            import MDAnalysis as mda

            return topology_of(mda.Merge(source), title=title)
        return topology_of(part, title=title)


def _from_mdtraj(traj: Any) -> tuple[Any, str]:
    """An MDAnalysis universe (in memory) of an MDTraj trajectory: nm -> angstrom, its
    residues, chains and bonds."""
    import MDAnalysis as mda
    from MDAnalysis.coordinates.memory import MemoryReader

    top = traj.topology
    atoms = list(top.atoms)
    residues = list(top.residues)
    chains = list(top.chains)
    universe = mda.Universe.empty(
        len(atoms),
        n_residues=max(1, len(residues)),
        n_segments=max(1, len(chains)),
        atom_resindex=[a.residue.index for a in atoms],
        residue_segindex=[r.chain.index for r in residues] or [0],
        trajectory=False,
    )
    universe.add_TopologyAttr("names", [a.name for a in atoms])
    elements = [a.element.symbol if a.element is not None else "X" for a in atoms]
    universe.add_TopologyAttr("elements", elements)
    universe.add_TopologyAttr("types", elements)
    universe.add_TopologyAttr("resnames", [r.name for r in residues] or ["UNK"])
    universe.add_TopologyAttr("resids", [r.resSeq for r in residues] or [1])
    universe.add_TopologyAttr(
        "chainIDs", [_chain_id(a.residue.chain, i) for i, a in enumerate(atoms)]
    )
    bonds = [(b[0].index, b[1].index) for b in top.bonds]
    universe.add_TopologyAttr("bonds", bonds)
    dimensions = None
    if traj.unitcell_lengths is not None:
        dimensions = np.hstack([traj.unitcell_lengths * 10.0, traj.unitcell_angles])
    dt = float(traj.timestep) if traj.n_frames > 1 else 1.0
    universe.load_new(
        np.asarray(traj.xyz, dtype=np.float32) * 10.0,
        format=MemoryReader,
        dimensions=dimensions,
        dt=dt,
    )
    return universe, "MDTraj trajectory"


def _chain_id(chain: Any, _index: int) -> str:
    given = getattr(chain, "chain_id", None)
    if isinstance(given, str) and given.strip():
        return given.strip()[:4]
    return chr(ord("A") + chain.index % 26)


def _from_ase(obj: Any) -> tuple[Any, str]:
    """An MDAnalysis universe (in memory) of ASE `Atoms` or a sequence of them (a trajectory
    of one system): one residue, elements from the chemical symbols, bonds guessed."""
    import MDAnalysis as mda
    from MDAnalysis.coordinates.memory import MemoryReader

    frames = [obj] if type(obj).__name__ == "Atoms" else list(obj)
    if not frames:
        raise SourceError("the ASE trajectory holds no frames")
    first = frames[0]
    n = len(first)
    if n == 0:
        raise SourceError("the ASE Atoms hold no atoms")
    if any(len(f) != n for f in frames):
        raise SourceError("every frame of an ASE trajectory must hold the same atoms")
    symbols = list(first.get_chemical_symbols())
    universe = mda.Universe.empty(n, trajectory=False)
    universe.add_TopologyAttr("names", symbols)
    universe.add_TopologyAttr("elements", symbols)
    universe.add_TopologyAttr("types", symbols)  # the bond guesser looks radii up by type
    universe.add_TopologyAttr("resnames", ["MOL"])
    universe.add_TopologyAttr("resids", [1])
    positions = np.stack([np.asarray(f.get_positions(), dtype=np.float32) for f in frames])
    dimensions = None
    if any(first.pbc) and first.cell.rank == 3:
        dimensions = np.asarray([f.cell.cellpar() for f in frames], dtype=np.float32)
    universe.load_new(positions, format=MemoryReader, dimensions=dimensions)
    return universe, f"ASE {first.get_chemical_formula()}"


class ReplaySource:
    """A trajectory played to a session from this process (see `TrajectoryReplay`)."""

    def __init__(self, structure: Any, url: str, token: str | None, session: str, **options: Any):
        from simulation_adapters.replay import TrajectoryReplay

        self.replay = TrajectoryReplay(structure, url, token, session, **options)
        self.replay.start(daemon=True)  # it ends with the process, as the process's server does

    def close(self) -> None:
        self.replay.close()


# ---------------------------------------------------------------------- OpenMM


class OpenMMSource:
    """An OpenMM simulation with the steering reporter attached: it sends its topology now and
    a frame every `interval` steps while it runs. `run(steps)` runs it on a thread of its own
    (the notebook stays free); or step it yourself (`simulation.step`, `run_steered`)."""

    def __init__(self, simulation: Any, url: str, token: str | None, session: str, **options: Any):
        from simulation_adapters.openmm_reporter import SteeringReporter

        self.simulation = simulation
        self.reporter = SteeringReporter(url, token, session=session, **options)
        simulation.reporters.append(self.reporter)
        self.reporter.attach(simulation)  # the topology goes out before the first step
        self._thread: threading.Thread | None = None
        self.steps_done = 0
        self.error: BaseException | None = None

    def run(self, steps: int, wait: bool = False) -> OpenMMSource:
        """Advance `steps` MD steps honouring the session's steering (pause, step, stop), on a
        thread of its own; `wait=True` runs them here instead."""
        from simulation_adapters.openmm_reporter import run_steered

        if self.running:
            raise RuntimeError("the simulation is already running")

        def target() -> None:
            try:
                self.steps_done += run_steered(self.simulation, steps, self.reporter)
            except BaseException as exc:  # kept for the notebook to read
                self.error = exc

        if wait:
            target()
            if self.error is not None:
                raise self.error
            return self
        self._thread = threading.Thread(target=target, name="scalesteer-openmm", daemon=True)
        self._thread.start()
        return self

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for a `run` to end; whether it did."""
        if self._thread is not None:
            self._thread.join(timeout)
        return not self.running

    def close(self) -> None:
        self.reporter.stop_requested = True
        self.reporter.close()
        self.wait(30)
        if self.reporter in self.simulation.reporters:
            self.simulation.reporters.remove(self.reporter)
