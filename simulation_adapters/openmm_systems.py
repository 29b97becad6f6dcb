"""Ready-made OpenMM simulations: the villin headpiece used by the demo and the tests.

Villin ships inside the openmm wheel (`openmm/app/data/test.pdb`, solvated); removing water and
ions and using an implicit-solvent force field gives a ~580-atom protein that folds and unfolds
visibly at interactive rates on a GPU and still runs on a CPU.
"""

from __future__ import annotations

import os
import random

import openmm
import openmm.app as app
import openmm.unit as unit

VILLIN_PDB = os.path.join(os.path.dirname(app.__file__), "data", "test.pdb")
_NOT_PROTEIN = {"HOH", "WAT", "Cl", "CL", "Na", "NA", "K", "Cl-", "Na+"}


def choose_platform(name: str | None = None) -> openmm.Platform:
    """The named platform, or the fastest of CUDA, OpenCL, CPU that is present."""
    if name is not None:
        return openmm.Platform.getPlatformByName(name)
    available = {
        openmm.Platform.getPlatform(i).getName() for i in range(openmm.Platform.getNumPlatforms())
    }
    for candidate in ("CUDA", "OpenCL", "CPU", "Reference"):
        if candidate in available:
            return openmm.Platform.getPlatformByName(candidate)
    raise RuntimeError("no OpenMM platform available")


def build_villin_simulation(
    platform: str | None = None,
    temperature_K: float = 300.0,
    seed: int | None = 2024,
    *,
    properties: dict[str, str] | None = None,
    minimize_iterations: int = 500,
    friction_per_ps: float = 1.0,
    timestep_fs: float = 2.0,
) -> app.Simulation:
    """Villin headpiece in implicit solvent (amber99sb + OBC GB), Langevin middle integrator,
    minimised and with velocities drawn at `temperature_K`.

    `platform` None picks CUDA, then OpenCL, then CPU. `seed` fixes the integrator's and the
    velocities' random numbers (None: random). `properties` are platform properties, e.g.
    `{"Threads": "1"}` for the CPU platform or `{"Precision": "mixed"}` for CUDA.
    """
    pdb = app.PDBFile(VILLIN_PDB)
    modeller = app.Modeller(pdb.topology, pdb.positions)
    modeller.delete([r for r in modeller.topology.residues() if r.name in _NOT_PROTEIN])
    forcefield = app.ForceField("amber99sb.xml", "amber99_obc.xml")
    system = forcefield.createSystem(
        modeller.topology, nonbondedMethod=app.NoCutoff, constraints=app.HBonds
    )
    integrator = openmm.LangevinMiddleIntegrator(
        temperature_K * unit.kelvin,
        friction_per_ps / unit.picosecond,
        timestep_fs * unit.femtoseconds,
    )
    rng_seed = seed if seed is not None else random.randrange(1, 2**31 - 1)
    integrator.setRandomNumberSeed(rng_seed)
    plat = choose_platform(platform)
    simulation = app.Simulation(modeller.topology, system, integrator, plat, properties or {})
    simulation.context.setPositions(modeller.positions)
    if minimize_iterations > 0:
        simulation.minimizeEnergy(maxIterations=minimize_iterations)
    simulation.context.setVelocitiesToTemperature(temperature_K * unit.kelvin, rng_seed)
    return simulation
