"""The OpenMM plug-in on real OpenMM (CPU platform, one thread) against a real /ws/sim peer."""

from __future__ import annotations

import resource
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import openmm
import openmm.app as app
import openmm.unit as unit
import pytest

from protocol import Control, EngineInfo, Event, Forces, Frame, ParamsAck, SimParams, WireArray
from simulation_adapters.openmm_reporter import SteeringReporter, run_steered
from tests.adapters.openmm_helpers import SystemRecipe, argon_recipe, villin_recipe
from tests.adapters.sim_peer import SimPeer


@pytest.fixture(scope="module")
def villin() -> SystemRecipe:
    return villin_recipe()


@pytest.fixture
def steered(
    villin: SystemRecipe, peer: SimPeer
) -> Iterator[tuple[app.Simulation, SteeringReporter]]:
    sim = villin.make()
    reporter = SteeringReporter(peer.ws_url, token="secret", interval=5, session="villin")
    sim.reporters.append(reporter)
    assert reporter.connection.wait_connected(5)
    reporter.attach(sim)
    yield sim, reporter
    reporter.close()


def wait_until(predicate: Callable[[], Any], timeout: float = 10.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.01)
    raise TimeoutError("condition not met in time")


def send_and_wait_arrival(peer: SimPeer, reporter: SteeringReporter, msg: Any) -> int:
    """Send a steering message and wait until the adapter holds it (not yet applied)."""
    assert reporter.connection.wait_connected(10)
    before = reporter.connection.stats.steering_received
    seq = peer.send(msg)
    wait_until(lambda: reporter.connection.stats.steering_received > before)
    return seq


def positions_nm(sim: app.Simulation) -> np.ndarray:
    state = sim.context.getState(getPositions=True)
    return np.asarray(state.getPositions(asNumpy=True).value_in_unit(unit.nanometer))


def forces_pull(peer: SimPeer, reporter: SteeringReporter, atoms: list[int], vecs: Any) -> int:
    idx = WireArray.from_numpy(np.asarray(atoms, dtype=np.int32).reshape(-1), "<i4")
    vec = WireArray.from_numpy(np.asarray(vecs, dtype=np.float32).reshape(-1, 3), "<f4")
    return send_and_wait_arrival(peer, reporter, Forces(indices=idx, forces=vec))


def test_frames_arrive_with_atom_count_units_and_observables(
    no_leaked_threads: None, steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    sim, _ = steered
    sim.step(20)
    frames = peer.wait_for(lambda: [f for f in peer.frames if f.step == 20])
    (topology,) = peer.topologies
    assert topology.n_atoms == sim.topology.getNumAtoms() == 582
    assert topology.elements[:2] == ["N", "H"] and topology.residue_names[0] == "LEU"
    assert topology.bonds.shape[0] == sim.topology.getNumBonds()
    frame: Frame = frames[-1]
    assert frame.positions.shape == (582, 3)
    # angstrom: ten times OpenMM's nanometres
    np.testing.assert_allclose(frame.positions.to_numpy(), positions_nm(sim) * 10.0, atol=1e-3)
    assert frame.time_ps == pytest.approx(20 * 0.002)
    state = sim.context.getState(getEnergy=True)
    assert frame.observables["potential_kJmol"] == pytest.approx(
        state.getPotentialEnergy().value_in_unit(unit.kilojoule_per_mole), rel=1e-4
    )
    kinetic = state.getKineticEnergy().value_in_unit(unit.kilojoule_per_mole)
    assert frame.observables["kinetic_kJmol"] == pytest.approx(kinetic, rel=1e-4)
    assert 50 < frame.observables["temperature_K"] < 600
    steps = [f.step for f in peer.frames]
    assert steps == sorted(steps) and all(s % 5 == 0 for s in steps)


def test_temperature_friction_timestep_applied_and_acked_with_step(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    sim, reporter = steered
    sim.step(5)
    seq = send_and_wait_arrival(
        peer, reporter, SimParams(temperature_K=350.0, friction_per_ps=5.0, timestep_fs=1.0)
    )
    sim.step(5)
    ack = peer.wait_ack(seq)
    assert ack.ok, ack.detail
    assert ack.step == 10 and ack.time_ps == pytest.approx(10 * 0.002)
    assert ack.applied == {"temperature_K": 350.0, "friction_per_ps": 5.0, "timestep_fs": 1.0}
    integrator = sim.integrator
    assert integrator.getTemperature().value_in_unit(unit.kelvin) == pytest.approx(350.0)
    assert integrator.getFriction().value_in_unit(unit.picosecond**-1) == pytest.approx(5.0)
    assert integrator.getStepSize().value_in_unit(unit.femtosecond) == pytest.approx(1.0)
    seq = send_and_wait_arrival(peer, reporter, SimParams(engine={"barostat": True}))
    sim.step(5)
    bad = peer.wait_ack(seq)
    assert not bad.ok and "barostat" in bad.detail and bad.step == 15


def test_barostat_temperature_follows(peer: SimPeer) -> None:
    sim = argon_recipe(n_side=4).make("Reference")
    barostat = openmm.MonteCarloBarostat(1.0 * unit.bar, 120 * unit.kelvin, 5)
    sim.system.addForce(barostat)
    sim.context.reinitialize(preserveState=True)
    with SteeringReporter(peer.ws_url, token="secret", interval=2) as reporter:
        sim.reporters.append(reporter)
        reporter.attach(sim)
        seq = send_and_wait_arrival(peer, reporter, SimParams(temperature_K=150.0))
        sim.step(2)
        assert peer.wait_ack(seq).ok
    assert barostat.getDefaultTemperature().value_in_unit(unit.kelvin) == pytest.approx(150.0)
    assert sim.context.getParameter(openmm.MonteCarloBarostat.Temperature()) == pytest.approx(150)


def _displacement_along(
    recipe: SystemRecipe,
    peer: SimPeer,
    atom: int,
    direction: np.ndarray,
    magnitude: float,
    steps: int,
    platform: str = "CPU",
) -> tuple[float, app.Simulation, SteeringReporter]:
    """Run `steps` with a constant pull (kJ/mol/A) on `atom`; its displacement along
    `direction` in angstrom. Same recipe and seed: a zero pull is the control run."""
    sim = recipe.make(platform)
    reporter = SteeringReporter(peer.ws_url, token="secret", interval=steps)
    sim.reporters.append(reporter)
    reporter.attach(sim)
    start = positions_nm(sim)[atom].copy()
    sim.step(1)  # before the first report: the pull is applied by service() below
    if magnitude:
        forces_pull(peer, reporter, [atom], direction * magnitude)
        reporter.service(sim)
    sim.step(steps - 1)
    moved = float(np.dot(positions_nm(sim)[atom] - start, direction) * 10.0)
    return moved, sim, reporter


def test_pull_moves_atom_and_release_stops_the_force(villin: SystemRecipe, peer: SimPeer) -> None:
    atom = 0  # the N-terminal nitrogen
    x = np.array([1.0, 0.0, 0.0])
    pull = 45.0 * x  # kJ/mol/A, under the reporter's default cap of 50
    control, _, control_reporter = _displacement_along(villin, peer, atom, x, 0.0, 200)
    control_reporter.close()
    moved, sim, reporter = _displacement_along(villin, peer, atom, x, 45.0, 200)
    try:
        assert reporter.pull is not None
        assert moved - control > 1.0, (moved, control)  # angstrom, along the pull
        assert reporter.pull.updates == 1
        group = reporter.pull.group
        f = sim.context.getState(getForces=True, groups={group}).getForces(asNumpy=True)
        applied = f.value_in_unit(unit.kilojoule_per_mole / unit.nanometer)
        np.testing.assert_allclose(applied[atom], pull * 10.0, rtol=1e-5)  # kJ/mol/nm
        assert np.count_nonzero(applied) == 1
        # the same forces again: no context update
        forces_pull(peer, reporter, [atom], pull)
        reporter.service(sim)
        assert reporter.pull.updates == 1
        # release: an empty forces message
        seq = forces_pull(peer, reporter, [], np.zeros((0, 3)))
        reporter.service(sim)
        ack = peer.wait_ack(seq)
        assert ack.ok and ack.applied["atoms"] == 0 and ack.step == sim.currentStep
        f = sim.context.getState(getForces=True, getEnergy=True, groups={group})
        assert not np.any(f.getForces(asNumpy=True).value_in_unit(f.getForces().unit))
        assert f.getPotentialEnergy().value_in_unit(unit.kilojoule_per_mole) == 0.0
        assert reporter.pull.updates == 2
    finally:
        reporter.close()


def test_pull_is_capped(steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer) -> None:
    sim, reporter = steered
    seq = forces_pull(peer, reporter, [3, 7], [[0.0, 1e5, 0.0], [3.0, 4.0, 0.0]])
    reporter.service(sim)
    ack = peer.wait_ack(seq)
    assert ack.ok and ack.applied == {"atoms": 2, "capped": 1} and "capped" in ack.detail
    assert reporter.pull is not None
    assert reporter.pull.active[3] == pytest.approx((0.0, reporter.max_force * 10.0, 0.0))
    assert reporter.pull.active[7] == pytest.approx((30.0, 40.0, 0.0))
    seq = forces_pull(peer, reporter, [100_000], [[1.0, 0.0, 0.0]])
    reporter.service(sim)
    bad = peer.wait_ack(seq)
    assert not bad.ok and "out of range" in bad.detail


def test_pause_holds_without_spinning_step_and_resume(
    no_leaked_threads: None, steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    sim, reporter = steered
    seq = send_and_wait_arrival(peer, reporter, Control(action="pause"))
    done: list[int] = []
    runner = threading.Thread(target=lambda: done.append(run_steered(sim, 60)))
    runner.start()
    try:
        ack = peer.wait_ack(seq)
        assert ack.ok and ack.applied == {"action": "pause", "paused": True} and ack.step == 0
        paused_at = sim.currentStep
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        time.sleep(0.6)
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        assert sim.currentStep == paused_at and runner.is_alive()
        assert (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime) < 0.3
        # single steps while paused, each reported
        seq = peer.send(Control(action="step", n_steps=3))
        assert peer.wait_ack(seq).ok
        peer.wait_for(lambda: any(f.step == paused_at + 3 for f in peer.frames))
        assert sim.currentStep == paused_at + 3
        seq = peer.send(Control(action="resume"))
        runner.join(60)
        assert not runner.is_alive() and done == [60]
        assert peer.wait_ack(seq).ok
    finally:
        reporter.resume()
        runner.join(60)


def test_pause_also_holds_a_plain_step_call(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    sim, reporter = steered
    send_and_wait_arrival(peer, reporter, Control(action="pause"))
    runner = threading.Thread(target=sim.step, args=(20,))
    runner.start()
    try:
        wait_until(lambda: reporter.paused and sim.currentStep == 5)
        time.sleep(0.3)
        assert sim.currentStep == 5 and runner.is_alive()
        peer.send(Control(action="resume"))
        runner.join(60)
        assert sim.currentStep == 20
    finally:
        reporter.resume()
        runner.join(60)


def test_stop_ends_run_steered_early(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    sim, reporter = steered
    seq = send_and_wait_arrival(peer, reporter, Control(action="stop"))
    sim.step(5)  # not driven by run_steered: refused
    refused = peer.wait_ack(seq)
    assert not refused.ok and "run_steered" in refused.detail
    taken: list[int] = []
    runner = threading.Thread(target=lambda: taken.append(run_steered(sim, 100_000)))
    runner.start()
    wait_until(lambda: sim.currentStep >= 15)
    seq = peer.send(Control(action="stop"))
    runner.join(60)
    assert not runner.is_alive() and peer.wait_ack(seq).ok
    assert 10 <= taken[0] < 100_000 and taken[0] % 5 == 0 and reporter.stop_requested
    assert run_steered(sim, 100) == 0  # stays stopped


def test_reset_restores_initial_positions(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    sim, reporter = steered
    initial = positions_nm(sim)
    sim.step(30)
    assert np.abs(positions_nm(sim) - initial).max() > 0.01
    seq = send_and_wait_arrival(peer, reporter, Control(action="reset"))
    sim.step(5)
    ack = peer.wait_ack(seq)
    assert ack.ok and ack.step == 35
    np.testing.assert_array_equal(positions_nm(sim), initial)
    assert sim.currentStep == 35  # the clock keeps running
    reset_frame = peer.wait_for(lambda: [f for f in peer.frames if f.step == 35][-1:])[0]
    np.testing.assert_allclose(reset_frame.positions.to_numpy(), initial * 10.0, atol=1e-3)


def test_replay_only_actions_are_refused(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    sim, reporter = steered
    seq = send_and_wait_arrival(peer, reporter, Control(action="seek", frame=3))
    sim.step(5)
    ack = peer.wait_ack(seq)
    assert not ack.ok and "replay" in ack.detail


def test_survives_server_restart_and_resumes_a_pause_when_the_server_goes(
    no_leaked_threads: None, villin: SystemRecipe, peer: SimPeer
) -> None:
    sim = villin.make()
    with SteeringReporter(peer.ws_url, token="secret", interval=5) as reporter:
        sim.reporters.append(reporter)
        sim.step(10)
        peer.wait_frames(2)
        send_and_wait_arrival(peer, reporter, Control(action="pause"))
        runner = threading.Thread(target=run_steered, args=(sim, 20))
        runner.start()
        wait_until(lambda: reporter.paused)
        peer.restart(downtime=0.3)  # nobody is left to resume: the pause is released
        runner.join(60)
        assert not runner.is_alive() and sim.currentStep == 30
        assert reporter.connection.wait_connected(10)
        sim.step(10)
        peer.wait_for(lambda: any(f.step == 40 for f in peer.frames))
        assert peer.topologies and peer.received[0].type == "topology"  # re-sent


def test_reference_platform_frames_and_pull(peer: SimPeer) -> None:
    recipe = argon_recipe(n_side=4, spacing_nm=0.6)  # a dilute gas: nothing cages the atom
    z = np.array([0.0, 0.0, 1.0])
    control, _, control_reporter = _displacement_along(recipe, peer, 0, z, 0.0, 80, "Reference")
    control_reporter.close()
    moved, sim, reporter = _displacement_along(recipe, peer, 0, z, 20.0, 80, "Reference")
    try:
        assert sim.context.getPlatform().getName() == "Reference"
        assert moved - control > 2.0, (moved, control)  # free flight: about 3.6 A
        frame = peer.wait_for(lambda: [f for f in peer.frames if f.step == 80][-1:])[0]
        assert frame.box is not None
        np.testing.assert_allclose(np.diag(frame.box.to_numpy()), [24.0] * 3, rtol=1e-5)
    finally:
        reporter.close()


def test_acks_carry_refs(steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer) -> None:
    sim, reporter = steered
    seqs = [send_and_wait_arrival(peer, reporter, SimParams(frame_interval=n)) for n in (7, 10)]
    sim.step(5)
    acks = [peer.wait_ack(s) for s in seqs]
    assert all(isinstance(a, ParamsAck) and a.ok for a in acks)
    assert reporter.interval == 10


def test_a_long_step_while_paused_sends_frames_as_it_runs(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    """`step N` while paused reports every `interval` steps on its way, not only at its end."""
    sim, reporter = steered
    send_and_wait_arrival(peer, reporter, Control(action="pause"))
    runner = threading.Thread(target=run_steered, args=(sim, 100_000))
    runner.start()
    try:
        wait_until(lambda: reporter.paused)
        paused_at = sim.currentStep
        seq = peer.send(Control(action="step", n_steps=40))
        ack = peer.wait_ack(seq)
        assert ack.ok and ack.applied["until_step"] == paused_at + 40
        peer.wait_for(lambda: any(f.step == paused_at + 40 for f in peer.frames))
        steps = sorted({f.step for f in peer.frames if paused_at < f.step <= paused_at + 40})
        assert steps == list(range(paused_at + 5, paused_at + 41, 5))
        time.sleep(0.3)
        assert sim.currentStep == paused_at + 40 and reporter.paused
    finally:
        reporter.stop_requested = True
        reporter.resume()
        runner.join(60)


def test_the_guard_rolls_back_a_blown_up_run_releases_the_pulls_and_pauses(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    """Capped forces on every atom in random directions heat villin without bound; the guard
    catches the runaway, restores the last good state and tells the session."""
    sim, reporter = steered
    n = sim.system.getNumParticles()
    vectors = np.random.default_rng(3).normal(size=(n, 3)) * 1e3  # capped at max_force each
    forces_pull(peer, reporter, list(range(n)), vectors)
    runner = threading.Thread(target=run_steered, args=(sim, 100_000))
    runner.start()
    try:
        events = peer.wait_for(lambda: [e for e in peer.of_type(Event) if e.code == "guard"], 60)
        event = events[0]
        assert event.level == "error" and "rolled back to step" in event.message
        assert reporter.paused and reporter.guard_trips == 1
        assert reporter.pull is not None and not reporter.pull.active
        held = sim.currentStep
        # the frame after the event shows the restored state (the MD thread owns the context)
        after = peer.wait_for(lambda: [f for f in peer.frames if f.step >= (event.step or 0)])
        restored = after[-1]
        assert np.isfinite(restored.positions.to_numpy()).all()
        assert restored.observables["temperature_K"] < 600.0
        time.sleep(0.3)
        assert sim.currentStep == held  # paused until someone resumes
        peer.send(Control(action="resume"))
        wait_until(lambda: sim.currentStep > held + 200, 60)
        assert reporter.guard_trips == 1  # without the forces, the run goes on calmly
    finally:
        reporter.stop_requested = True
        reporter.resume()
        runner.join(60)


def _running(sim: app.Simulation, reporter: SteeringReporter, steps: int) -> threading.Thread:
    runner = threading.Thread(target=run_steered, args=(sim, steps, reporter))
    runner.start()
    return runner


def _stop(reporter: SteeringReporter, runner: threading.Thread) -> None:
    reporter.stop_requested = True
    reporter.resume()
    runner.join(60)


def _guard_events(peer: SimPeer) -> list[Event]:
    return [e for e in peer.of_type(Event) if e.code == "guard"]


def _heat_to_1000(sim: app.Simulation, reporter: SteeringReporter, peer: SimPeer) -> None:
    """Steer the thermostat to 1000 K and start the run there (a report calm for it)."""
    send_and_wait_arrival(peer, reporter, SimParams(temperature_K=1000.0))
    sim.step(5)  # applied at this report
    # the heating, at once (constraints and the potential energy take a third of it back)
    sim.context.setVelocitiesToTemperature(1500 * unit.kelvin)
    sim.step(5)  # a report calm for a 1000 K thermostat (under 1250 K): a rollback point
    hot = peer.wait_for(lambda: [f for f in peer.frames if f.step == sim.currentStep])[-1]
    assert 700.0 < hot.observables["temperature_K"] < 1250.0  # a runaway at 300 K (600 K)


def test_a_steered_cooling_is_no_blow_up(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    """A run held at 1000 K, steered back to 300 K, cools through the 600 K that is a runaway
    for a 300 K thermostat; the guard judged it against the new thermostat alone and took the
    cooling for a blow-up (rolled back, paused)."""
    sim, reporter = steered
    _heat_to_1000(sim, reporter, peer)
    held = _running(sim, reporter, 300)  # the run's level follows it to 1000 K
    held.join(120)
    assert not held.is_alive() and not _guard_events(peer)
    send_and_wait_arrival(peer, reporter, SimParams(temperature_K=300.0))
    runner = _running(sim, reporter, 1500)
    try:
        runner.join(120)
        assert not runner.is_alive() and not _guard_events(peer), [
            e.message for e in _guard_events(peer)
        ]
        temps = [f.observables["temperature_K"] for f in peer.frames if f.step > 310]
        assert max(temps) > 650.0 and temps[-1] < 450.0  # through 600 K, down to 300 K
        assert reporter.guard_trips == 0 and not reporter.paused
    finally:
        _stop(reporter, runner)


@pytest.mark.parametrize(
    ("integrator", "start_K"),
    [("langevin", 0.0), ("langevin", 1200.0), ("verlet", 900.0)],
    ids=["cold-thermostat", "hot-thermostat", "hot-no-thermostat"],
)
def test_a_run_that_starts_cold_or_hot_is_no_blow_up(
    peer: SimPeer, integrator: str, start_K: float
) -> None:
    """Argon started at 0 K or far above its 120 K thermostat, or hot without a thermostat
    (the guard had assumed 300 K for one and tripped at 600 K): the guard judges it against
    where it started and where it goes, and lets it run."""
    recipe = argon_recipe()
    if integrator == "verlet":
        verlet = openmm.VerletIntegrator(0.002)
        recipe.integrator_xml = openmm.XmlSerializer.serialize(verlet)
    sim = recipe.make("CPU")
    if start_K:
        sim.context.setVelocitiesToTemperature(start_K * unit.kelvin, 11)
    else:
        sim.context.setVelocities(
            np.zeros((sim.system.getNumParticles(), 3)) * unit.nanometer / unit.picosecond
        )
    reporter = SteeringReporter(peer.ws_url, token="secret", interval=10, session="argon")
    sim.reporters.append(reporter)
    runner = _running(sim, reporter, 1000)
    try:
        runner.join(120)
        assert not runner.is_alive() and not _guard_events(peer), [
            e.message for e in _guard_events(peer)
        ]
        temps = [f.observables["temperature_K"] for f in peer.frames]
        assert len(temps) >= 90
        if start_K == 0.0:
            assert temps[0] < 60.0 and temps[-1] > 80.0  # heated by its thermostat
        else:
            assert temps[0] > 600.0  # what the guard took for a runaway
        assert reporter.guard_trips == 0
    finally:
        _stop(reporter, runner)
        reporter.close()


def test_the_guard_never_rolls_back_into_a_state_hot_for_the_thermostat_of_now(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    """A run held at 1000 K reports states calm for that thermostat, and the guard took one as
    its rollback point; with the thermostat back at 300 K that state is a runaway, so a guard
    that caught a blow-up soon after rolled back into it after every resume (only reset
    recovered). Now the rollback point must be calm for the thermostat of the moment."""
    sim, reporter = steered
    _heat_to_1000(sim, reporter, peer)
    send_and_wait_arrival(peer, reporter, SimParams(temperature_K=300.0))
    n = sim.system.getNumParticles()
    vectors = np.random.default_rng(5).normal(size=(n, 3)) * 1e3  # capped at max_force each
    forces_pull(peer, reporter, list(range(n)), vectors)  # a real blow-up, while still hot
    runner = _running(sim, reporter, 100_000)
    try:
        (event,) = peer.wait_for(lambda: _guard_events(peer), 60)
        assert "the start's positions" in event.message and "too hot" in event.message
        for _ in range(3):  # every resume goes on calmly, none trips the guard again
            wait_until(lambda: reporter.paused or reporter.guard_trips > 1, 30)
            held = sim.currentStep
            peer.send(Control(action="resume"))
            wait_until(lambda h=held: sim.currentStep > h + 100 or reporter.guard_trips > 1, 60)
            assert reporter.guard_trips == 1, [e.message for e in peer.of_type(Event)]
            peer.send(Control(action="pause"))
        calm = peer.wait_for(lambda: [f for f in peer.frames if f.step > held])[-1]
        assert calm.observables["temperature_K"] < 450.0
    finally:
        _stop(reporter, runner)


def test_the_engine_declares_what_it_can_be_steered_with(
    steered: tuple[app.Simulation, SteeringReporter], peer: SimPeer
) -> None:
    _sim, reporter = steered
    info = peer.wait_for(lambda: peer.of_type(EngineInfo))[-1]
    assert info.name.startswith("OpenMM") and "LangevinMiddleIntegrator" in info.name
    assert set(info.controls) == {"pause", "resume", "step", "reset", "stop"}
    assert info.params["temperature_K"].max == 1000.0
    assert info.params["temperature_K"].recommended == pytest.approx(300.0)
    # each value as the engine runs it now: the dashboard shows them before anyone steers
    assert info.params["friction_per_ps"].recommended == pytest.approx(
        _sim.integrator.getFriction().value_in_unit(unit.picosecond**-1)
    )
    assert info.params["frame_interval"].recommended == reporter.interval
    # villin constrains its bonds to hydrogen (and its hydrogens are light): 2.5 fs at most
    assert info.params["timestep_fs"].max == 2.5
    assert info.pull is not None and info.pull.max_force == reporter.max_force
    assert "seek" in info.unavailable
