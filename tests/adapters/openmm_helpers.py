"""Small OpenMM systems for the adapter tests (real OpenMM, CPU or Reference platform)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import openmm
import openmm.app as app
import openmm.unit as unit

from simulation_adapters.openmm_systems import build_villin_simulation

CPU_ONE_THREAD = {"Threads": "1"}


@dataclass
class SystemRecipe:
    """Everything needed to make identical fresh simulations quickly."""

    topology: app.Topology
    system_xml: str
    integrator_xml: str
    state_xml: str

    def make(self, platform: str = "CPU") -> app.Simulation:
        props = CPU_ONE_THREAD if platform == "CPU" else {}
        sim = app.Simulation(
            self.topology,
            openmm.XmlSerializer.deserialize(self.system_xml),
            openmm.XmlSerializer.deserialize(self.integrator_xml),
            openmm.Platform.getPlatformByName(platform),
            props,
        )
        sim.context.setState(openmm.XmlSerializer.deserialize(self.state_xml))
        return sim


def recipe_of(sim: app.Simulation) -> SystemRecipe:
    state = sim.context.getState(getPositions=True, getVelocities=True)
    return SystemRecipe(
        topology=sim.topology,
        system_xml=openmm.XmlSerializer.serialize(sim.system),
        integrator_xml=openmm.XmlSerializer.serialize(sim.integrator),
        state_xml=openmm.XmlSerializer.serialize(state),
    )


def villin_recipe() -> SystemRecipe:
    sim = build_villin_simulation("CPU", properties=CPU_ONE_THREAD, minimize_iterations=100)
    return recipe_of(sim)


def argon_recipe(n_side: int = 6, spacing_nm: float = 0.38, seed: int = 7) -> SystemRecipe:
    """A periodic Lennard-Jones argon lattice with a Langevin thermostat at 120 K."""
    n = n_side**3
    box = n_side * spacing_nm
    system = openmm.System()
    vectors = (openmm.Vec3(box, 0, 0), openmm.Vec3(0, box, 0), openmm.Vec3(0, 0, box))
    system.setDefaultPeriodicBoxVectors(*vectors)
    nb = openmm.NonbondedForce()
    nb.setNonbondedMethod(openmm.NonbondedForce.CutoffPeriodic)
    nb.setCutoffDistance(min(0.8, 0.49 * box))
    topology = app.Topology()
    chain = topology.addChain()
    argon = app.Element.getBySymbol("Ar")
    for _ in range(n):
        system.addParticle(39.948)
        nb.addParticle(0.0, 0.3405, 0.996)
        topology.addAtom("AR", argon, topology.addResidue("AR", chain))
    system.addForce(nb)
    topology.setPeriodicBoxVectors(vectors)
    grid = np.arange(n_side) * spacing_nm + spacing_nm / 2
    pos = np.array(np.meshgrid(grid, grid, grid, indexing="ij")).reshape(3, -1).T
    integrator = openmm.LangevinMiddleIntegrator(120 * unit.kelvin, 1 / unit.picosecond, 0.005)
    integrator.setRandomNumberSeed(seed)
    context = openmm.Context(system, integrator, openmm.Platform.getPlatformByName("Reference"))
    context.setPositions(pos * unit.nanometer)
    context.setVelocitiesToTemperature(120 * unit.kelvin, seed)
    state = context.getState(getPositions=True, getVelocities=True)
    return SystemRecipe(
        topology=topology,
        system_xml=openmm.XmlSerializer.serialize(system),
        integrator_xml=openmm.XmlSerializer.serialize(integrator),
        state_xml=openmm.XmlSerializer.serialize(state),
    )
