"""Interactive pulling in OpenMM: constant per-atom forces from the server, as one
CustomExternalForce in its own force group.

The server turns a user's spring pull into constant force vectors (kJ/mol/A) that it re-sends as
frames arrive; here they become per-particle parameters (kJ/mol/nm, hence x10) of the energy
`-(fx*x + fy*y + fz*z)`. Every particle is registered once, when the force is installed (the one
context reinitialisation this needs happens before the run); afterwards only parameters change,
and `updateParametersInContext` runs only when a value actually changed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import openmm
import openmm.app as app

from protocol.forces import cap_forces

log = logging.getLogger("scalesteer.openmm")

ENERGY = "-(fx*x + fy*y + fz*z)"
NAME = "scalesteer pull"
KJ_PER_A_TO_KJ_PER_NM = 10.0


@dataclass
class PullResult:
    """What one `apply` did: atoms now pulled, how many vectors were capped, whether the
    context was updated."""

    atoms: int
    capped: int
    updated: bool


class PullForce:
    """The pull force of one simulation. Create it before running (it reinitialises the context
    once, preserving the state)."""

    def __init__(
        self, simulation: app.Simulation, max_force: float = 1000.0, group: int | None = None
    ) -> None:
        if max_force <= 0:
            raise ValueError("max_force must be positive (kJ/mol/A)")
        self.max_force = float(max_force)
        system = simulation.system
        self.n_particles = system.getNumParticles()
        self.group = _free_group(system) if group is None else int(group)
        if not 0 <= self.group <= 31:
            raise ValueError("force group must be in 0..31")
        force = openmm.CustomExternalForce(ENERGY)
        for name in ("fx", "fy", "fz"):
            force.addPerParticleParameter(name)
        for i in range(self.n_particles):
            force.addParticle(i, (0.0, 0.0, 0.0))
        force.setForceGroup(self.group)
        force.setName(NAME)
        self.force_index = system.addForce(force)
        self.force = force
        integrator = simulation.context.getIntegrator()
        if hasattr(integrator, "getIntegrationForceGroups"):
            groups = int(integrator.getIntegrationForceGroups())
            if not groups & (1 << self.group):
                log.warning(
                    "the integrator does not integrate force group %d; pulling has no effect",
                    self.group,
                )
        simulation.context.reinitialize(preserveState=True)
        self.active: dict[int, tuple[float, float, float]] = {}  # kJ/mol/nm
        self.updates = 0

    def apply(
        self,
        context: openmm.Context,
        indices: npt.NDArray[np.integer],
        forces_kJmolA: npt.NDArray[np.floating],
    ) -> PullResult:
        """Make these the only pulled atoms (an empty array releases all). Raises ValueError for
        an index outside the system."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_particles):
            raise ValueError(f"atom index out of range [0, {self.n_particles})")
        vec, capped = cap_forces(forces_kJmolA, self.max_force)
        wanted: dict[int, tuple[float, float, float]] = {}
        for i, f in zip(idx.tolist(), vec * KJ_PER_A_TO_KJ_PER_NM, strict=True):
            if np.any(f != 0.0):
                fx, fy, fz = (float(c) for c in f)
                wanted[i] = (fx, fy, fz)
        changed = [i for i in set(self.active) | set(wanted) if self.active.get(i) != wanted.get(i)]
        for i in changed:
            self.force.setParticleParameters(i, i, wanted.get(i, (0.0, 0.0, 0.0)))
        if changed:
            self.force.updateParametersInContext(context)
            self.updates += 1
        self.active = wanted
        return PullResult(atoms=len(wanted), capped=capped, updated=bool(changed))

    def clear(self, context: openmm.Context) -> None:
        """Release every pulled atom."""
        self.apply(context, np.zeros(0, dtype=np.int64), np.zeros((0, 3)))

    def energy_groups(self, integration_groups: int = 0xFFFFFFFF) -> int:
        """The force-group mask that leaves the pull out (for reporting physical energies)."""
        return int(integration_groups) & ~(1 << self.group) & 0xFFFFFFFF


def _free_group(system: openmm.System) -> int:
    used = {f.getForceGroup() for f in system.getForces()}
    for group in range(31, -1, -1):
        if group not in used:
            return group
    return 31
