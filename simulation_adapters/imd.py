"""`scalesteer imd`: bridge an MD engine serving IMD (GROMACS, NAMD, LAMMPS) to scalesteer.

    gmx mdrun -imdport 8888 -imdwait -imdpull ...   (IMD v2, or v3 where the build has it)
    namd3 sim.namd                                  (IMDon yes, IMDport 8888, IMDversion 3)
    lmp -in in.lmp                                  (fix 1 all imd 8888 version 3 unwrap on)
    scalesteer imd --connect localhost:8888 --topology system.pdb --url ws://127.0.0.1:8000/ws/sim

The engine streams coordinates (and time, energies, box); the bridge forwards them as frames
(latest wins, so the engine never waits on the render server) and sends the dashboard's steering
back: pulling forces (MDCOMM), pause/resume, the transmission rate (TRATE), and KILL only when
started with `--allow-kill`. IMD carries no atom names, so the topology comes from a file.

Kept whole: `IMDBridge` is one translation between an IMD engine and scalesteer (the units, the
steering each engine accepts, the two threads that carry them), and the command that starts it is
its only caller.
"""

from __future__ import annotations

import argparse
import functools
import logging
import math
import os
import sys
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import (
    Control,
    EngineInfo,
    ErrorCode,
    Event,
    Forces,
    Frame,
    Message,
    ParamRange,
    PullLimits,
    SimParams,
    WireArray,
)
from protocol.forces import cap_forces
from protocol.messages import ControlAction
from simulation_adapters.cli_support import add_retry, configure_logging, parse
from simulation_adapters.connection import ConnectionState, SimulationConnection
from simulation_adapters.imd_session import (
    EngineFrame,
    IMDDisconnectedError,
    IMDError,
    IMDSession,
)
from simulation_adapters.runaway import RunawayGuard
from structures.errors import StructureError
from structures.reader import Structure, element_mass, load

log = logging.getLogger("scalesteer.imd")

KCAL = 4.184  # kJ per kcal
R_KJ_PER_MOL_K = 0.00831446261815324  # the gas constant
EV = 96.48533212  # kJ/mol per eV


@dataclass(frozen=True)
class EngineUnits:
    """How an engine's IMD numbers relate to scalesteer's (angstrom, ps, kJ/mol)."""

    name: str
    length_A: float = 1.0  # engine length unit in angstrom
    time_ps: float = 1.0  # engine time unit in ps
    energy_kJmol: float = 1.0  # engine energy unit in kJ/mol
    force_unit: str = "kJ/mol/A"

    def force_factor(self) -> float:
        """Factor turning kJ/mol/A into the engine's force unit."""
        return self.length_A / self.energy_kJmol


UNITS: dict[str, EngineUnits] = {
    # IMD v3 fixes its units: angstrom, ps, kJ/mol, kJ/mol/A
    "imdv3": EngineUnits("imdv3"),
    # IMD v2 (NAMD, VMD convention): angstrom, kcal/mol, forces in kcal/mol/A, no time
    "imdv2": EngineUnits("imdv2", energy_kJmol=KCAL, force_unit="kcal/mol/A"),
    # GROMACS' IMD v2 reports energies in kJ/mol but takes forces in kcal/mol/A like VMD
    "gromacs-v2": EngineUnits("gromacs-v2", force_unit="kcal/mol/A"),
    # LAMMPS' fix imd sends and applies its native units
    "lammps-real": EngineUnits(
        "lammps-real", time_ps=1e-3, energy_kJmol=KCAL, force_unit="kcal/mol/A"
    ),
    "lammps-metal": EngineUnits("lammps-metal", energy_kJmol=EV, force_unit="eV/A"),
}


def units_for(name: str, version: int) -> EngineUnits:
    """The units preset `name`, or for "auto" the protocol's own convention."""
    if name == "auto":
        return UNITS["imdv3" if version >= 3 else "imdv2"]
    return UNITS[name]


class BridgeError(Exception):
    """The bridge stopped because of the engine (cut connection, NaN, wrong atom count)."""


class IMDBridge:
    """Connects one IMD engine to one scalesteer session.

    `run()` blocks until the engine ends the session (returns) or fails (raises BridgeError);
    `start()` runs it on a background thread, `close()` stops either and joins every thread.
    """

    def __init__(
        self,
        host: str,
        port: int,
        topology: str | Structure,
        url: str,
        token: str | None = None,
        session: str = "default",
        *,
        allow_kill: bool = False,
        units: str = "auto",
        lossless: bool = False,
        takeover: bool = False,
        max_force: float = 50.0,
        max_spring_k: float = 10.0,
        runaway_K: float | None = None,
        thermostat_K: float | None = None,
        connect_timeout: float = 30.0,
        handshake_timeout: float = 30.0,
        give_up_after: float | None = None,
    ) -> None:
        if units != "auto" and units not in UNITS:
            raise ValueError(f"unknown units {units!r}; one of auto, {', '.join(UNITS)}")
        if isinstance(topology, str):
            self.structure = load(topology, require_coordinates=False)
        else:
            self.structure = topology
        self.n_atoms = self.structure.topology.n_atoms
        self.host, self.port = host, int(port)
        self.allow_kill = allow_kill
        self.units_name = units
        self.units = UNITS["imdv3"]
        self.max_force = float(max_force)
        self.max_spring_k = float(max_spring_k)
        self.runaway = RunawayGuard(runaway_K)
        self.thermostat_K = thermostat_K
        """The engine's thermostat target, when the user knows it (IMD does not say)."""
        self._mass_cache: npt.NDArray[np.float64] | None = None
        self.guard_trips = 0
        self._guarded = False  # the guard paused the engine; cleared by resume
        self.connect_timeout = connect_timeout
        self.handshake_timeout = handshake_timeout
        self.connection = SimulationConnection(
            url,
            token=token,
            session=session,
            client="imd-bridge",
            lossless=lossless,
            on_steer=self._on_steer,
            takeover=takeover,
            give_up_after=give_up_after,
        )
        self.imd: IMDSession | None = None
        self.error: Exception | None = None
        self.frames_forwarded = 0
        self.last_step: int | None = None
        self.last_time_ps: float | None = None
        self._active_forces: dict[int, np.ndarray] = {}
        self._cond = threading.Condition()
        self._wakeups = 0
        self._stopping = False
        self._cancel = threading.Event()
        self._thread: threading.Thread | None = None
        self._steer_thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle

    def run(self) -> None:
        """Bridge until the engine ends the session; raises BridgeError if it fails."""
        try:
            self._run()
        finally:
            self._shutdown()

    def start(self) -> IMDBridge:
        """Run the bridge on a background thread; see `wait` and `close`."""

        def target() -> None:
            try:
                self.run()
            except Exception as exc:  # kept for wait()
                self.error = exc

        self._thread = threading.Thread(target=target, name="scalesteer-imd-bridge")
        self._thread.start()
        return self

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for a started bridge to finish; True if it did."""
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def close(self, timeout: float = 10.0) -> None:
        """Stop bridging: disconnect from the engine (it keeps running) and the server."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        self._cancel.set()
        imd = self.imd
        if imd is not None:
            imd.close()
        if self._thread is not None:
            self._thread.join(timeout)
        self._shutdown()

    def __enter__(self) -> IMDBridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the bridge

    def _run(self) -> None:
        self.connection.start()
        self.connection.send_topology(self.structure.topology)
        imd = IMDSession.connect(
            self.host,
            self.port,
            self.n_atoms,
            connect_timeout=self.connect_timeout,
            handshake_timeout=self.handshake_timeout,
            cancel=self._cancel,
        )
        with self._cond:
            if self._stopping:
                imd.close()
                return
            self.imd = imd
        self.units = units_for(self.units_name, imd.version)
        self.connection.send_engine(self.engine_info(imd.version))
        self._steer_thread = threading.Thread(
            target=self._steer_loop, name="scalesteer-imd-steering", daemon=True
        )
        self._steer_thread.start()
        while True:
            try:
                raw = imd.read_frame()
            except IMDDisconnectedError as exc:
                if self._stopping or not exc.mid_frame:
                    log.info("scalesteer imd: %s", exc)
                    return
                self.connection.send_error(ErrorCode.INTERNAL, f"IMD engine: {exc}")
                raise BridgeError(str(exc)) from None
            except IMDError as exc:
                self.connection.send_error(ErrorCode.INVALID_MESSAGE, f"IMD engine: {exc}")
                raise BridgeError(str(exc)) from None
            if self.connection.state is ConnectionState.FAILED:
                raise BridgeError(f"render server: {self.connection.error}")
            frame = self._frame(raw)
            if frame is None:
                continue
            self.connection.send_frame(frame)
            self.frames_forwarded += 1

    def engine_info(self, version: int) -> EngineInfo:
        """What an IMD engine can be steered with through this bridge."""
        controls: list[ControlAction] = ["pause", "resume"]
        unavailable = {
            name: "IMD cannot change it" for name in ("temperature_K", "timestep_fs",
                                                      "friction_per_ps")
        }  # fmt: skip
        for action in ("step", "seek", "speed", "loop", "reset"):
            unavailable[action] = f"IMD has no {action}"
        if self.allow_kill:
            controls.append("stop")
        else:
            unavailable["stop"] = "KILL is not allowed; start the bridge with --allow-kill"
        return EngineInfo(
            name=f"IMD v{version} engine ({self.units.name})",
            kind="imd",
            controls=controls,
            params={"frame_interval": ParamRange(min=1, max=1_000_000, unit="steps")},
            unavailable=unavailable,
            pull=PullLimits(max_force=self.max_force, max_spring_k=self.max_spring_k),
            guard="on NaN or a temperature runaway (far above the thermostat and the run's recent "
            "temperature): release the forces and pause the engine",
        )

    def _guard(self, step: int, problem: str) -> None:
        """The run blew up: release every force, pause the engine, tell the session (once per
        pause; the engine cannot be rolled back over IMD)."""
        if self._guarded:
            return
        self._guarded = True
        self.guard_trips += 1
        imd = self.imd
        action = "forces released, engine paused"
        try:
            if imd is not None:
                if self._active_forces:
                    zeros = np.zeros((len(self._active_forces), 3))
                    imd.send_forces(np.array(sorted(self._active_forces), dtype=np.int32), zeros)
                    self._active_forces = {}
                imd.pause()
        except IMDError as exc:
            action = f"could not reach the engine to pause it ({exc})"
        text = f"the simulation blew up at step {step} ({problem}); {action}"
        log.error("scalesteer imd: %s", text)
        self.connection.send_event(Event(level="error", code="guard", message=text, step=step))

    def _runaway(self, temperature: float | None) -> str:
        """Why the engine's temperature is a runaway ('' if it is not): judged against the
        thermostat target the user gave, else against the run's own recent level, so a cold
        start heating to its thermostat is no blow-up (`simulation_adapters.runaway`)."""
        if temperature is None:
            return ""
        return self.runaway.check(temperature, self.thermostat_K)

    def _frame(self, raw: EngineFrame) -> Frame | None:
        """The frame to forward, or None for one the guard stopped (non-finite)."""
        u = self.units
        step = raw.step if raw.step is not None and raw.step >= 0 else self.frames_forwarded
        pos = raw.positions * np.float32(u.length_A) if u.length_A != 1.0 else raw.positions
        if not np.isfinite(pos).all():
            self._guard(int(step), "non-finite coordinates")
            return None
        temperature = raw.energies.get("temperature") if raw.energies else None
        kinetic = None
        if temperature is None and "velocities" in raw.extras:
            kinetic = self._kinetic_energy(raw.extras["velocities"])
            if kinetic is not None:
                temperature = 2.0 * kinetic / (self._dof() * R_KJ_PER_MOL_K)
        problem = self._runaway(temperature)
        if problem:
            self._guard(int(step), problem)
        time_ps = raw.time * u.time_ps if raw.time is not None else 0.0
        box = None
        if raw.box is not None and np.isfinite(raw.box).all() and np.any(raw.box):
            box = WireArray.from_numpy(raw.box * u.length_A, "<f4")
        self.last_step, self.last_time_ps = int(step), float(time_ps)
        return Frame(
            step=int(step),
            time_ps=float(time_ps) if math.isfinite(time_ps) else 0.0,
            positions=WireArray.from_numpy(pos, "<f4"),
            box=box,
            observables=self._observables(raw.energies, temperature, kinetic),
        )

    def _masses(self) -> npt.NDArray[np.float64] | None:
        """Each atom's mass (g/mol) from the topology file, or from its element; None when
        an atom has neither."""
        if self._mass_cache is None:
            atoms = self.structure.universe.atoms
            try:
                masses = np.asarray(atoms.masses, dtype=np.float64)
            except Exception:  # a format without masses: MDAnalysis raises NoDataError
                masses = np.zeros(self.n_atoms)
            if masses.shape != (self.n_atoms,) or not (masses > 0).all():
                by_element = [element_mass(e) for e in self.structure.topology.elements]
                masses = np.where(masses > 0, masses, np.asarray(by_element, dtype=np.float64))
            self._mass_cache = masses
        return self._mass_cache if (self._mass_cache > 0).all() else None

    def _dof(self) -> int:
        """Degrees of freedom as the engines count them without constraints (3N - 3)."""
        return max(3 * self.n_atoms - 3, 1)

    def _kinetic_energy(self, velocities: npt.NDArray[np.float32]) -> float | None:
        """The kinetic energy of the engine's velocities (engine units), for engines that send
        velocities but no energies (LAMMPS): None without masses or for non-finite ones."""
        masses = self._masses()
        if masses is None or velocities.shape != (self.n_atoms, 3):
            return None
        u = self.units
        v = velocities.astype(np.float64) * (u.length_A / u.time_ps)  # A/ps
        # (g/mol) (A/ps)^2 = 0.01 kJ/mol
        value = float(0.5 * 0.01 * np.einsum("i,ij,ij->", masses, v, v))
        return value if math.isfinite(value) else math.inf

    def _observables(
        self, energies: dict[str, float] | None, temperature: float | None, kinetic: float | None
    ) -> dict[str, float]:
        values: dict[str, float | None] = {"temperature_K": temperature, "kinetic_kJmol": kinetic}
        if energies:
            e = self.units.energy_kJmol
            values = {
                "temperature_K": energies["temperature"],
                "potential_kJmol": energies["potential_energy"] * e,
                "kinetic_kJmol": (energies["total_energy"] - energies["potential_energy"]) * e,
            }
        return {k: float(v) for k, v in values.items() if v is not None and math.isfinite(v)}

    def _shutdown(self) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self.imd is not None:
            self.imd.close()
        if self._steer_thread is not None and self._steer_thread is not threading.current_thread():
            self._steer_thread.join(10)
        if self.connection.state is not ConnectionState.CLOSED:
            self.connection.close()

    # ------------------------------------------------------------------ steering

    def _on_steer(self, _msg: Message) -> None:  # connection I/O thread
        with self._cond:
            self._wakeups += 1
            self._cond.notify_all()

    def _woken(self, seen: int) -> bool:
        return self._stopping or self._wakeups != seen

    def _steer_loop(self) -> None:
        seen = -1
        while True:
            with self._cond:
                self._cond.wait_for(functools.partial(self._woken, seen))
                if self._stopping:
                    return
                seen = self._wakeups
            for msg in self.connection.poll_steering():
                self._apply(msg)

    def _apply(self, msg: Message) -> None:
        imd = self.imd
        assert imd is not None
        try:
            if isinstance(msg, Forces):
                ok, applied, detail = self._apply_forces(imd, msg)
            elif isinstance(msg, Control):
                ok, applied, detail = self._apply_control(imd, msg)
            elif isinstance(msg, SimParams):
                ok, applied, detail = self._apply_params(imd, msg)
            else:
                return
        except IMDError as exc:
            ok, applied, detail = False, {}, f"engine unreachable: {exc}"
        except ValueError as exc:
            ok, applied, detail = False, {}, str(exc)
        if isinstance(msg, Control):
            applied = {"action": msg.action, **applied}  # the server tracks pause by it
        self.connection.ack(
            msg.seq, self.last_step, self.last_time_ps, ok=ok, applied=applied, detail=detail
        )

    def _apply_forces(self, imd: IMDSession, msg: Forces) -> tuple[bool, dict[str, Any], str]:
        idx = msg.indices.to_numpy().astype(np.int64)
        if idx.size and int(idx.max()) >= self.n_atoms:
            raise ValueError(f"atom index out of range [0, {self.n_atoms})")
        vec, capped = cap_forces(msg.forces.to_numpy(), self.max_force)
        wanted = {int(i): v for i, v in zip(idx, vec, strict=True) if np.any(v != 0)}
        # released atoms get an explicit zero: NAMD forgets a force only when told zero
        send = sorted(set(wanted) | set(self._active_forces))
        if not send:
            return True, {"atoms": 0}, ""
        factor = self.units.force_factor()
        forces = np.array([wanted.get(i, np.zeros(3)) for i in send]) * factor
        imd.send_forces(np.array(send, dtype=np.int32), forces)
        self._active_forces = wanted
        applied = {"atoms": len(wanted), "capped": capped, "unit": self.units.force_unit}
        return True, applied, ""

    def _apply_control(self, imd: IMDSession, msg: Control) -> tuple[bool, dict[str, Any], str]:
        if msg.action == "pause":
            changed = imd.pause()
            return True, {"paused": True}, "" if changed else "already paused"
        if msg.action == "resume":
            self._guarded = False
            changed = imd.resume()
            return True, {"paused": False}, "" if changed else "not paused"
        if msg.action == "stop":
            if not self.allow_kill:
                return False, {}, "KILL is not allowed; start the bridge with --allow-kill"
            imd.kill()
            return True, {"killed": True}, ""
        return False, {}, f"IMD has no {msg.action!r}"

    def _apply_params(self, imd: IMDSession, msg: SimParams) -> tuple[bool, dict[str, Any], str]:
        applied: dict[str, Any] = {}
        problems = []
        if msg.frame_interval is not None:
            imd.set_rate(msg.frame_interval)
            applied["frame_interval"] = msg.frame_interval
        for name in ("temperature_K", "timestep_fs", "friction_per_ps"):
            if getattr(msg, name) is not None:
                problems.append(f"IMD cannot change {name}")
        if msg.engine:
            problems.append(f"engine parameters not supported: {', '.join(sorted(msg.engine))}")
        return not problems, applied, "; ".join(problems)


# ---------------------------------------------------------------------- command line


def parse_address(text: str) -> tuple[str, int]:
    """'host:port' (or 'imd://host:port', or just 'port') -> (host, port)."""
    value = text.removeprefix("imd://")
    host, _, port = value.rpartition(":")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    return host.strip("[]") or "localhost", int(port)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="scalesteer imd",
        description="Bridge an MD engine serving IMD (GROMACS, NAMD, LAMMPS) to scalesteer.",
    )
    ap.add_argument("--connect", required=True, metavar="HOST:PORT", help="the engine's IMD port")
    ap.add_argument(
        "--topology",
        required=True,
        help="structure of the atoms the engine sends (PDB, GRO, PSF, LAMMPS data, mmCIF)",
    )
    ap.add_argument(
        "--url",
        default="ws://127.0.0.1:8000/ws/sim",
        help="render server: ws://HOST:PORT/ws/sim, or the dashboard link it prints",
    )
    ap.add_argument("--token", default=os.environ.get("SCALESTEER_TOKEN"), help="access token")
    ap.add_argument("--session", default="default", help="session name on the server")
    ap.add_argument(
        "--takeover", action="store_true", help="replace the session's current simulation"
    )
    ap.add_argument("--allow-kill", action="store_true", help="let the dashboard stop the engine")
    ap.add_argument(
        "--units",
        default="auto",
        choices=["auto", *UNITS],
        help="the engine's IMD units (auto: IMD v3 -> imdv3, v2 -> imdv2)",
    )
    ap.add_argument("--lossless", action="store_true", help="never drop frames (engine may wait)")
    ap.add_argument(
        "--max-force", type=float, default=50.0, help="cap per atom, kJ/mol/A (default 50)"
    )
    ap.add_argument(
        "--thermostat-K",
        type=float,
        default=None,
        help="the engine's thermostat temperature (IMD does not send it): the guard judges "
        "runaways against it as well as against the run's own recent temperature",
    )
    ap.add_argument("--connect-timeout", type=float, default=30.0, help="seconds to keep trying")
    add_retry(ap)
    ap.add_argument("-v", "--verbose", action="store_true")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parse(build_parser(), argv)
    if isinstance(args, int):
        return args
    configure_logging(args.verbose)
    try:
        host, port = parse_address(args.connect)
        if not args.max_force > 0:
            raise ValueError("--max-force must be positive")
        if args.thermostat_K is not None and not args.thermostat_K > 0:
            raise ValueError("--thermostat-K must be positive")
        bridge = IMDBridge(
            host,
            port,
            args.topology,
            args.url,
            args.token,
            args.session,
            allow_kill=args.allow_kill,
            units=args.units,
            lossless=args.lossless,
            max_force=args.max_force,
            thermostat_K=args.thermostat_K,
            connect_timeout=args.connect_timeout,
            takeover=args.takeover,
            give_up_after=args.retry,
        )
    except (StructureError, ValueError) as exc:
        print(f"scalesteer imd: error: {exc}", file=sys.stderr)
        return 2
    print(
        f"scalesteer imd: {bridge.n_atoms} atoms from {os.path.basename(args.topology)}; "
        f"engine {host}:{port} -> {args.url}",
        file=sys.stderr,
    )
    try:
        bridge.run()
    except (BridgeError, IMDError) as exc:
        print(f"scalesteer imd: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        bridge.close()
        return 130
    if bridge.connection.error:
        print(f"scalesteer imd: server: {bridge.connection.error}", file=sys.stderr)
    print(f"scalesteer imd: engine finished; {bridge.frames_forwarded} frames", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
