"""OpenMM topologies and states as protocol messages (angstrom, ps, kJ/mol)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import openmm
import openmm.app as app
import openmm.unit as unit

from protocol import Topology, WireArray

#: the gas constant in kJ/(mol K), for the instantaneous temperature
R_KJ_PER_MOL_K = 0.00831446261815324


def topology_message(
    topology: app.Topology, system: openmm.System | None = None, title: str = ""
) -> Topology:
    """The `topology` message of an OpenMM topology; charges come from the system's
    NonbondedForce when there is one."""
    atoms = list(topology.atoms())
    n = len(atoms)
    elements = [(a.element.symbol if a.element is not None else "X")[:3] for a in atoms]
    resids = np.empty(n, dtype=np.int32)
    for i, atom in enumerate(atoms):
        rid = str(atom.residue.id).strip()
        resids[i] = int(rid) if rid.lstrip("-").isdigit() else atom.residue.index + 1
    bonds = np.array([(b[0].index, b[1].index) for b in topology.bonds()], dtype=np.int32).reshape(
        -1, 2
    )
    charges = _charges(system, n) if system is not None else None
    return Topology(
        n_atoms=n,
        elements=elements,
        names=[a.name[:8] for a in atoms],
        residue_ids=WireArray.from_numpy(resids, "<i4"),
        residue_names=[a.residue.name[:8] for a in atoms],
        chain_ids=[_chain_name(a.residue.chain) for a in atoms],
        bonds=WireArray.from_numpy(bonds, "<i4"),
        charges=WireArray.from_numpy(charges, "<f4") if charges is not None else None,
        title=title[:256],
        engine=f"openmm-{openmm.__version__}"[:64],
    )


def _chain_name(chain: app.Chain) -> str:
    """The chain's id, or a letter by its position when the file left it blank."""
    return str(chain.id).strip()[:4] or chr(ord("A") + chain.index % 26)


def _charges(system: openmm.System, n: int) -> npt.NDArray[np.float32] | None:
    if system.getNumParticles() != n:
        return None
    for force in system.getForces():
        if isinstance(force, openmm.NonbondedForce):
            q = [
                force.getParticleParameters(i)[0].value_in_unit(unit.elementary_charge)
                for i in range(n)
            ]
            return np.asarray(q, dtype=np.float32)
    return None


def degrees_of_freedom(system: openmm.System) -> int:
    """Kinetic degrees of freedom, counted as OpenMM's StateDataReporter does."""
    massive: list[bool] = [
        bool(system.getParticleMass(i).value_in_unit(unit.dalton) > 0)
        for i in range(system.getNumParticles())
    ]
    dof = 3 * int(sum(massive))
    for i in range(system.getNumConstraints()):
        p1, p2, _ = system.getConstraintParameters(i)
        if massive[p1] and massive[p2]:
            dof -= 1
    if any(isinstance(f, openmm.CMMotionRemover) for f in system.getForces()):
        dof -= 3
    return max(dof, 1)


def positions_angstrom(state: openmm.State) -> npt.NDArray[np.float32]:
    """A state's positions as a float32 (n, 3) array in angstrom."""
    pos: Any = state.getPositions(asNumpy=True).value_in_unit(unit.nanometer)
    return np.asarray(pos * 10.0, dtype=np.float32)


def box_angstrom(state: openmm.State) -> npt.NDArray[np.float32]:
    """A state's periodic box vectors as rows of a float32 (3, 3) array in angstrom."""
    box: Any = state.getPeriodicBoxVectors(asNumpy=True).value_in_unit(unit.nanometer)
    return np.asarray(box * 10.0, dtype=np.float32)
