"""The OpenMM plug-in: a reporter that streams frames to scalesteer and applies steering.

    simulation.reporters.append(SteeringReporter("ws://127.0.0.1:8000/ws/sim", token="..."))
    run_steered(simulation, 100_000)       # or simulation.step(...)

Following OpenMM's reporter protocol, `describeNextReport` says *when* (every `interval` steps)
and `report` does the work on the MD thread: it applies the steering that arrived since the last
report (temperature, friction, time step, pause/resume, reset, pulling), then hands the frame to
the connection's background thread, which never makes the MD wait. A pause holds the MD thread
inside `report` on a condition variable (no busy-waiting) until resume, `step N`, stop or close.

The reporter declares what it can be steered with (`EngineInfo`: temperature, time step and
friction ranges sensible for this system, the pull limits), and guards the run: positions,
energy or temperature that blow up (NaN, or a temperature past `runaway_K`) roll the context back
to the last good report, release every pull, pause, and tell everyone in the session why.

Kept whole: OpenMM's reporter protocol makes `SteeringReporter` one object whose `report` applies
every kind of steering on the MD thread, and the run's guard (roll back, release the pulls, pause)
shares that state.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
from typing import Any

import numpy as np
import openmm
import openmm.app as app
import openmm.unit as unit

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
from simulation_adapters.connection import ConnectionState, SimulationConnection
from simulation_adapters.openmm_pull import PullForce
from simulation_adapters.openmm_topology import (
    R_KJ_PER_MOL_K,
    box_angstrom,
    degrees_of_freedom,
    positions_angstrom,
    topology_message,
)
from simulation_adapters.runaway import RunawayGuard

log = logging.getLogger("scalesteer.openmm")

_THERMOSTATS = (openmm.AndersenThermostat,)
_BAROSTAT_NAMES = (
    "MonteCarloBarostat",
    "MonteCarloAnisotropicBarostat",
    "MonteCarloMembraneBarostat",
    "MonteCarloFlexibleBarostat",
)


class SteeringReporter:
    """Streams positions (angstrom), step, time, temperature and energies to a scalesteer
    server every `interval` steps, and applies the server's steering on the MD thread.

    `max_force` caps each pulled atom's force (kJ/mol/A). `lossless=True` makes the MD wait for
    the server instead of dropping frames. When the connection is lost while paused, the
    simulation resumes unless `resume_on_disconnect=False` (nobody is left to resume it).
    Positions are sent unwrapped so that an atom being pulled never jumps across the box;
    `wrap=True` sends them wrapped into the periodic box (molecules kept whole) instead.

    The guard rolls back to the last calm report (temperature within 25 % or 50 K of the
    thermostat's) when the run blows up: non-finite positions or energy, or a temperature above
    `runaway_K` (default: twice the thermostat's temperature and 300 K more, and as much above
    the run's own recent temperature, so that a hot start or a steered cooling that comes down
    to its thermostat is no blow-up; `simulation_adapters.runaway`). Calm is
    judged again at the rollback, against the thermostat of that moment: a state calm only for a
    hotter thermostat, or one that has blown up again since, is given up for the start's
    positions (with velocities drawn at today's temperature if the start's are too hot), so the
    guard never rolls back into the blow-up it caught. Steered settings (temperature, friction,
    time step) are not rolled back.
    `max_spring_k` is the stiffest pull spring accepted (kJ/mol/A^2); `max_force` also bounds
    what a pull may apply per atom.
    """

    def __init__(
        self,
        url: str,
        token: str | None = None,
        interval: int = 100,
        session: str = "default",
        *,
        lossless: bool = False,
        max_force: float = 50.0,
        max_spring_k: float = 10.0,
        runaway_K: float | None = None,
        force_group: int | None = None,
        client: str | None = None,
        title: str = "",
        resume_on_disconnect: bool = True,
        wrap: bool = False,
        takeover: bool = False,
    ) -> None:
        if int(interval) < 1:
            raise ValueError("interval must be at least 1 step")
        self.interval = int(interval)
        self.max_force = float(max_force)
        self.max_spring_k = float(max_spring_k)
        self.runaway = RunawayGuard(runaway_K)
        self.force_group = force_group
        self.title = title
        self.resume_on_disconnect = resume_on_disconnect
        self.wrap = wrap
        self.paused = False
        self.stop_requested = False
        self.frames_reported = 0
        self.pull: PullForce | None = None
        self._simulation: app.Simulation | None = None
        self._initial_state: openmm.State | None = None
        self._dof = 1
        self._periodic = False
        self._cond = threading.Condition()
        self._wakeups = 0
        self._step_until: int | None = None  # `step N` while paused: run to this step
        self._driven = False  # inside run_steered
        self._closed = False
        self._good: openmm.State | None = None  # the last calm report, to roll back to
        self._good_step = 0
        self._good_K = 0.0  # its temperature
        self._good_fresh = False  # taken since the last rollback (else it tripped the guard)
        self._initial_K = 0.0
        self.guard_trips = 0
        self.connection = SimulationConnection(
            url,
            token=token,
            session=session,
            client=client or f"openmm-{openmm.__version__}",
            lossless=lossless,
            on_steer=self._on_steer,
            on_state=self._on_state,
            takeover=takeover,
        )
        self.connection.start()

    # ------------------------------------------------------------------ OpenMM reporter protocol

    def describeNextReport(self, simulation: app.Simulation) -> dict[str, Any]:  # noqa: N802
        """When the next report is due, and what it needs from the state (OpenMM 8.2+ form)."""
        self.attach(simulation)
        return {
            "steps": self.steps_to_next_report(simulation),
            "periodic": self.wrap,
            "include": ["positions", "energy"],
        }

    def report(self, simulation: app.Simulation, state: openmm.State) -> None:
        """Check the run, apply pending steering, send this frame, hold here while paused."""
        problem = self._blown_up(simulation, state)
        if problem:
            state = self.recover(simulation, problem)
        elif self._calm(simulation, state):
            self._checkpoint(simulation)
        if self._apply(simulation, self.connection.poll_steering()):
            state = simulation.context.getState(getPositions=True, getEnergy=True)
        self._send_frame(simulation, state)
        self._hold(simulation)

    def recover(self, simulation: app.Simulation, problem: str) -> openmm.State:
        """The guard: restore the last good state (the clock keeps counting), drop every
        external force, pause, and tell the session. Returns the restored state."""
        step = int(simulation.currentStep)
        self.guard_trips += 1
        if self.pull is not None:
            self.pull.clear(simulation.context)
        where = self._roll_back(simulation)
        with self._cond:
            self.paused, self._step_until = True, None
        text = (
            f"the simulation blew up at step {step} ({problem}); {where}, pulls released, "
            "paused. Lower the temperature, time step or pull, then resume."
        )
        log.error("scalesteer: %s", text)
        self.connection.send_event(Event(level="error", code="guard", message=text, step=step))
        return simulation.context.getState(getPositions=True, getEnergy=True)

    def _roll_back(self, simulation: app.Simulation) -> str:
        """Restore a state calm for the thermostat of now: the last calm report, unless it is
        too hot for today's thermostat or has blown up again since, else the start's positions.
        Returns what was done, for the event."""
        target = self._reference_temperature(simulation)
        limit = self._calm_limit(simulation)
        good, fresh = self._good, self._good_fresh
        self._good_fresh = False
        if good is not None and fresh and self._good_K <= limit:
            self._restore(simulation, good)
            return f"rolled back to step {self._good_step}"
        if good is None:
            why = "no calm state yet"
        elif not fresh:
            why = f"the state of step {self._good_step} blew up again"
        else:
            why = (
                f"the last calm state, step {self._good_step}, is at {self._good_K:.0f} K: too "
                f"hot for the thermostat's {target:g} K"
            )
        assert self._initial_state is not None  # attach() ran: reports come after it
        self._restore(simulation, self._initial_state)
        fresh_velocities = ""
        if self._initial_K > limit:
            simulation.context.setVelocitiesToTemperature(target * unit.kelvin)
            fresh_velocities = f", velocities drawn at {target:g} K"
        return f"rolled back to the start's positions ({why}){fresh_velocities}"

    def _blown_up(self, simulation: app.Simulation, state: openmm.State) -> str:
        """Why this state cannot go on ('' if it can)."""
        pos = positions_angstrom(state)
        if not np.isfinite(pos).all():
            return "non-finite positions"
        potential = state.getPotentialEnergy().value_in_unit(unit.kilojoule_per_mole)
        if not math.isfinite(potential):
            return "non-finite energy"
        return self.runaway.check(self._temperature(state), _thermostat_kelvin(simulation))

    def _calm(self, simulation: app.Simulation, state: openmm.State) -> bool:
        """Close enough to the thermostat to roll back to: a state just under the runaway
        limit would only blow up again."""
        return self._temperature(state) <= self._calm_limit(simulation)

    def _reference_temperature(self, simulation: app.Simulation) -> float:
        """The temperature the run should be at: its thermostat's, without one the run's
        recent level (300 K before any report)."""
        return _thermostat_kelvin(simulation) or self.runaway.level or 300.0

    def _calm_limit(self, simulation: app.Simulation) -> float:
        target = self._reference_temperature(simulation)
        return max(1.25 * target, target + 50.0)

    def _temperature(self, state: openmm.State) -> float:
        kinetic = state.getKineticEnergy().value_in_unit(unit.kilojoule_per_mole)
        return float(2.0 * kinetic / (self._dof * R_KJ_PER_MOL_K))

    def _checkpoint(self, simulation: app.Simulation) -> None:
        # without the context's parameters: a rollback must not restore an old thermostat
        # setting (Andersen's temperature is one), only the molecule
        self._good = simulation.context.getState(
            getPositions=True, getVelocities=True, getEnergy=True
        )
        self._good_step = int(simulation.currentStep)
        self._good_K = self._temperature(self._good)
        self._good_fresh = True

    def engine_info(self, simulation: app.Simulation) -> EngineInfo:
        """What this simulation can be steered with, and the sensible range of each value."""
        integrator = simulation.context.getIntegrator()
        kind = type(integrator).__name__
        params: dict[str, ParamRange] = {
            # `recommended`: each value as the engine runs it now (the dashboard shows it)
            "frame_interval": ParamRange(
                min=1, max=1_000_000, unit="steps", recommended=self.interval
            ),
        }
        unavailable: dict[str, str] = {
            "seek": "a live simulation has no frames to seek",
            "speed": "a live simulation runs as fast as it can",
            "loop": "a live simulation does not loop",
        }
        temperature = _thermostat_kelvin(simulation)
        if temperature is not None:
            params["temperature_K"] = ParamRange(
                min=1.0, max=1000.0, unit="K", recommended=temperature
            )
        else:
            unavailable["temperature_K"] = f"{kind} has no thermostat"
        if hasattr(integrator, "setStepSize"):
            dt = integrator.getStepSize().value_in_unit(unit.femtoseconds)
            params["timestep_fs"] = ParamRange(
                min=0.1, max=max(dt, _max_timestep_fs(simulation.system)), unit="fs", recommended=dt
            )
        else:
            unavailable["timestep_fs"] = f"{kind} has no fixed time step"
        if hasattr(integrator, "setFriction") or hasattr(integrator, "setCollisionFrequency"):
            get = getattr(integrator, "getFriction", None) or integrator.getCollisionFrequency
            friction = get().value_in_unit(unit.picosecond**-1)
            params["friction_per_ps"] = ParamRange(
                min=0.01, max=max(100.0, friction), unit="1/ps", recommended=friction
            )
        else:
            unavailable["friction_per_ps"] = f"{kind} has no friction"
        return EngineInfo(
            name=f"OpenMM {openmm.__version__} ({kind})",
            kind="md",
            controls=["pause", "resume", "step", "reset", "stop"],
            params=params,
            unavailable=unavailable,
            pull=PullLimits(max_force=self.max_force, max_spring_k=self.max_spring_k),
            guard="on NaN or a temperature runaway: roll back to the last good frame, release "
            "the pulls, pause",
        )

    # ------------------------------------------------------------------ public helpers

    def attach(self, simulation: app.Simulation) -> None:
        """Install the pull force, remember the initial state and send the topology.

        Called by the first `describeNextReport`; call it yourself to do this before the run.
        """
        if self._simulation is simulation:
            return
        if self._simulation is not None:
            raise ValueError("a SteeringReporter serves one simulation")
        self._simulation = simulation
        self.pull = PullForce(simulation, self.max_force, self.force_group)
        self._dof = degrees_of_freedom(simulation.system)
        self._periodic = bool(simulation.system.usesPeriodicBoundaryConditions())
        self._initial_state = simulation.context.getState(
            getPositions=True, getVelocities=True, getEnergy=True
        )
        self._initial_K = self._temperature(self._initial_state)
        self.runaway.check(self._initial_K)  # where the run starts: its first level
        self.connection.send_topology(
            topology_message(simulation.topology, simulation.system, self.title)
        )
        self.connection.send_engine(self.engine_info(simulation))
        self._checkpoint(simulation)

    def steps_to_next_report(self, simulation: app.Simulation) -> int:
        """Steps to the next report: the frame interval, and while paused no further than
        where `step N` ends (frames keep coming while it runs)."""
        step = int(simulation.currentStep)
        regular = self.interval - step % self.interval
        with self._cond:
            if self.paused and self._step_until is not None and self._step_until > step:
                return min(regular, self._step_until - step)
        return regular

    def service(self, simulation: app.Simulation) -> None:
        """Apply pending steering now and hold while paused (between `step` calls)."""
        self.attach(simulation)
        if self._apply(simulation, self.connection.poll_steering()):
            state = simulation.context.getState(getPositions=True, getEnergy=True)
            self._send_frame(simulation, state)
        self._hold(simulation)

    def resume(self) -> None:
        """Resume a paused simulation from Python (any thread)."""
        with self._cond:
            self.paused = False
            self._wakeups += 1
            self._cond.notify_all()

    def close(self, timeout: float = 5.0) -> None:
        """Disconnect (releasing a paused MD thread) and join the connection thread."""
        with self._cond:
            self._closed = True
            self.paused = False
            self._cond.notify_all()
        self.connection.close(timeout)

    def __enter__(self) -> SteeringReporter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ frames

    def _send_frame(self, simulation: app.Simulation, state: openmm.State) -> None:
        pos = positions_angstrom(state)
        if not np.isfinite(pos).all():  # nothing good to roll back to: say so, send nothing
            text = f"OpenMM produced non-finite positions at step {simulation.currentStep}"
            self.connection.send_error(ErrorCode.INVALID_MESSAGE, text, "frame.positions")
            return
        observables = self._observables(simulation, state)
        box = box_angstrom(state) if self._periodic else None
        frame = Frame(
            step=max(0, simulation.currentStep),
            time_ps=state.getTime().value_in_unit(unit.picosecond),
            positions=WireArray.from_numpy(pos, "<f4"),
            box=WireArray.from_numpy(box, "<f4") if box is not None else None,
            observables=observables,
        )
        self.connection.send_frame(frame)
        self.frames_reported += 1

    def _observables(self, simulation: app.Simulation, state: openmm.State) -> dict[str, float]:
        kinetic = state.getKineticEnergy().value_in_unit(unit.kilojoule_per_mole)
        if self.pull is not None and self.pull.active:
            # the pull's linear potential is not physics: report the energy without it
            groups = simulation.context.getIntegrator().getIntegrationForceGroups()
            mask = self.pull.energy_groups(groups)
            state = simulation.context.getState(getEnergy=True, groups=mask)
        potential = state.getPotentialEnergy().value_in_unit(unit.kilojoule_per_mole)
        values = {
            "temperature_K": 2.0 * kinetic / (self._dof * R_KJ_PER_MOL_K),
            "potential_kJmol": potential,
            "kinetic_kJmol": kinetic,
        }
        return {k: float(v) for k, v in values.items() if math.isfinite(v)}

    # ------------------------------------------------------------------ steering

    def _on_steer(self, _msg: Message) -> None:  # I/O thread
        with self._cond:
            self._wakeups += 1
            self._cond.notify_all()

    def _on_state(self, state: ConnectionState) -> None:  # I/O thread
        lost = state in (ConnectionState.BACKOFF, ConnectionState.FAILED, ConnectionState.CLOSED)
        with self._cond:
            if lost and self.paused and self.resume_on_disconnect:
                log.warning("scalesteer: connection lost while paused; resuming the simulation")
                self.paused = False
            self._wakeups += 1
            self._cond.notify_all()

    def _woken(self, seen: int) -> bool:
        return self._wakeups != seen or self._closed

    def _hold(self, simulation: app.Simulation) -> None:
        """Block while paused, applying steering as it arrives; no busy-waiting."""
        while True:
            with self._cond:
                seen = self._wakeups
                stepping = self._step_until is not None and self._step_until > int(
                    simulation.currentStep
                )
                if (
                    not self.paused
                    or stepping
                    or self._closed
                    or (self.stop_requested and self._driven)
                ):
                    return
            messages = self.connection.poll_steering()
            if messages:
                if self._apply(simulation, messages):
                    state = simulation.context.getState(getPositions=True, getEnergy=True)
                    self._send_frame(simulation, state)
                continue
            with self._cond:
                self._cond.wait_for(functools.partial(self._woken, seen))

    def _apply(self, simulation: app.Simulation, messages: list[Message]) -> bool:
        """Apply steering messages in order and ack each; True if positions changed."""
        moved = False
        for msg in messages:
            step = simulation.currentStep
            time_ps = simulation.context.getTime().value_in_unit(unit.picosecond)
            try:
                if isinstance(msg, SimParams):
                    ok, applied, detail = self._apply_params(simulation, msg)
                elif isinstance(msg, Control):
                    ok, applied, detail = self._apply_control(simulation, msg)
                    moved = moved or (ok and msg.action == "reset")
                elif isinstance(msg, Forces):
                    ok, applied, detail = self._apply_forces(simulation, msg)
                else:
                    continue
            except (openmm.OpenMMException, ValueError) as exc:
                ok, applied, detail = False, {}, str(exc)
            if isinstance(msg, Control):
                applied = {"action": msg.action, **applied}  # the server tracks pause by it
            log.debug("scalesteer: %s at step %d: ok=%s %s", msg.type, step, ok, detail)
            self.connection.ack(msg.seq, step, time_ps, ok=ok, applied=applied, detail=detail)
        return moved

    def _apply_params(
        self, simulation: app.Simulation, msg: SimParams
    ) -> tuple[bool, dict[str, Any], str]:
        integrator = simulation.context.getIntegrator()
        context = simulation.context
        applied: dict[str, Any] = {}
        problems: list[str] = []
        kind = type(integrator).__name__
        if msg.temperature_K is not None:
            t = msg.temperature_K
            done = False
            if hasattr(integrator, "setTemperature"):
                integrator.setTemperature(t * unit.kelvin)
                done = True
            for force in simulation.system.getForces():
                if type(force).__name__ in _BAROSTAT_NAMES or isinstance(force, _THERMOSTATS):
                    force.setDefaultTemperature(t * unit.kelvin)
                    context.setParameter(type(force).Temperature(), t)
                    done = True
            if done:
                applied["temperature_K"] = t
            else:
                problems.append(f"{kind} has no temperature (and there is no thermostat)")
        if msg.friction_per_ps is not None:
            g = msg.friction_per_ps
            if hasattr(integrator, "setFriction"):
                integrator.setFriction(g / unit.picosecond)
                applied["friction_per_ps"] = g
            elif hasattr(integrator, "setCollisionFrequency"):
                integrator.setCollisionFrequency(g / unit.picosecond)
                applied["friction_per_ps"] = g
            else:
                problems.append(f"{kind} has no friction")
        if msg.timestep_fs is not None:
            if hasattr(integrator, "setStepSize"):
                integrator.setStepSize(msg.timestep_fs * unit.femtoseconds)
                applied["timestep_fs"] = msg.timestep_fs
            else:
                problems.append(f"{kind} has no fixed time step")
        if msg.frame_interval is not None:
            self.interval = int(msg.frame_interval)
            applied["frame_interval"] = self.interval
        if msg.engine:
            problems.append(f"engine parameters not supported: {', '.join(sorted(msg.engine))}")
        return not problems, applied, "; ".join(problems)

    def _apply_control(
        self, simulation: app.Simulation, msg: Control
    ) -> tuple[bool, dict[str, Any], str]:
        action = msg.action
        with self._cond:
            if action == "pause":
                self.paused, self._step_until = True, None
                return True, {"paused": True}, ""
            if action == "resume":
                self.paused, self._step_until = False, None
                return True, {"paused": False}, ""
            if action == "step":
                if not self.paused:
                    return False, {}, "step applies only while paused"
                start = max(self._step_until or 0, int(simulation.currentStep))
                self._step_until = start + msg.n_steps
                return True, {"steps": msg.n_steps, "until_step": self._step_until}, ""
            if action == "stop":
                if not self._driven:
                    return False, {}, "stop needs the run to be driven by run_steered()"
                self.stop_requested, self.paused = True, False
                return True, {"stopped": True}, ""
        if action == "reset":
            self._reset(simulation)
            return True, {"reset": True}, "positions and velocities restored; clock kept"
        return False, {}, f"{action!r} applies to trajectory replay, not to OpenMM"

    def _reset(self, simulation: app.Simulation) -> None:
        assert self._initial_state is not None
        self._restore(simulation, self._initial_state)

    @staticmethod
    def _restore(simulation: app.Simulation, state: openmm.State) -> None:
        context = simulation.context
        t, step = context.getTime(), context.getStepCount()
        context.setState(state)
        context.setTime(t)  # step and time stay monotonic for the session log
        context.setStepCount(step)

    def _apply_forces(
        self, simulation: app.Simulation, msg: Forces
    ) -> tuple[bool, dict[str, Any], str]:
        assert self.pull is not None
        result = self.pull.apply(simulation.context, msg.indices.to_numpy(), msg.forces.to_numpy())
        detail = ""
        if result.capped:
            detail = f"{result.capped} force(s) capped at {self.max_force} kJ/mol/A"
        return True, {"atoms": result.atoms, "capped": result.capped}, detail


def _thermostat_kelvin(simulation: app.Simulation) -> float | None:
    """The temperature the run is held at (integrator or thermostat), None without one."""
    integrator = simulation.context.getIntegrator()
    if hasattr(integrator, "getTemperature"):
        return float(integrator.getTemperature().value_in_unit(unit.kelvin))
    for force in simulation.system.getForces():
        if isinstance(force, _THERMOSTATS) or type(force).__name__ in _BAROSTAT_NAMES:
            return float(force.getDefaultTemperature().value_in_unit(unit.kelvin))
    return None


def _max_timestep_fs(system: openmm.System) -> float:
    """A time step Langevin dynamics stays stable at: 1 fs with flexible bonds to hydrogen,
    2.5 fs with them constrained, 4 fs with constraints and heavy hydrogens (repartitioned)."""
    if system.getNumConstraints() == 0:
        return 1.0
    hydrogen_masses = [
        system.getParticleMass(i).value_in_unit(unit.dalton)
        for i in range(system.getNumParticles())
        if 0.5 < system.getParticleMass(i).value_in_unit(unit.dalton) < 5.0
    ]
    heavy_hydrogens = bool(hydrogen_masses) and min(hydrogen_masses) >= 2.5
    return 4.0 if heavy_hydrogens else 2.5


def run_steered(
    simulation: app.Simulation, steps: int, reporter: SteeringReporter | None = None
) -> int:
    """Advance `steps` MD steps, honouring pause (waiting without spinning), `step N` while
    paused, and stop; returns the steps actually taken (fewer only after a stop)."""
    if reporter is None:
        reporter = next((r for r in simulation.reporters if isinstance(r, SteeringReporter)), None)
    if reporter is None:
        simulation.step(steps)
        return steps
    if reporter not in simulation.reporters:
        raise ValueError("add the reporter to simulation.reporters first")
    done = 0
    reporter._driven = True
    try:
        if reporter.stop_requested:
            return 0
        reporter.service(simulation)
        while done < steps and not reporter.stop_requested:
            chunk = min(steps - done, reporter.steps_to_next_report(simulation))
            before = int(simulation.currentStep)
            try:
                simulation.step(chunk)
            except openmm.OpenMMException as exc:  # "Particle coordinate is NaN" and alike
                if "nan" not in str(exc).lower():
                    raise
                done += max(0, int(simulation.currentStep) - before)
                reporter.recover(simulation, str(exc).strip().splitlines()[0][:120])
                reporter.service(simulation)  # paused: wait here for the dashboard
                continue
            done += chunk
    finally:
        reporter._driven = False
    return done
