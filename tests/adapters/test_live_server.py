"""End to end against the real render server, steered by a real steerer client on /ws/view.

These need only a `live_server` fixture (tests/conftest.py) with `.ws_url` (the /ws/sim URL or
the server's base ws:// URL) and `.token`; its `.url`, `.view_url` and `.restart()` are used when
present. Without the fixture they are skipped.
"""

from __future__ import annotations

import json
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy as np
import openmm.unit as unit
import pytest
from MDAnalysisTests.datafiles import DCD, PSF
from websockets.sync.client import ClientConnection, connect

import protocol
from protocol import Control, Hello, Message, ParamsAck, Pull, SimParams, Welcome
from simulation_adapters.connection import ConnectionState, SimulationConnection
from simulation_adapters.openmm_reporter import SteeringReporter, run_steered
from simulation_adapters.replay import TrajectoryReplay
from structures.reader import load
from tests.adapters.openmm_helpers import argon_recipe
from tests.conftest import LiveServer

M = TypeVar("M", bound=Message)


@pytest.fixture
def live(live_server: LiveServer) -> LiveServer:
    return live_server


def sim_url(live: Any) -> str:
    url = str(live.ws_url).rstrip("/")
    return url if url.endswith("/ws/sim") else f"{url}/ws/sim"


def wait_until(predicate: Callable[[], Any], timeout: float = 20.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise TimeoutError("condition not met in time")


def session_summary(live: Any, session: str) -> dict[str, Any]:
    req = urllib.request.Request(
        f"{live.url}/api/sessions/{session}", headers={"Authorization": f"Bearer {live.token}"}
    )
    with urllib.request.urlopen(req, timeout=10) as resp:
        data: dict[str, Any] = json.load(resp)
    return data


class Steerer:
    """A dashboard stand-in: a steerer on /ws/view that sends steering and collects replies."""

    def __init__(self, live: Any, session: str) -> None:
        self.ws: ClientConnection = connect(
            live.view_url, max_size=None, compression=None, legacy=True
        )
        hello = Hello(role="steerer", token=live.token, client="test-steerer", session=session)
        self.ws.send(protocol.encode(hello))
        assert isinstance(protocol.decode(self.ws.recv(timeout=10)), Welcome)
        self.received: list[Message] = []
        self._seq = 0
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, name="test-steerer")
        self._thread.start()

    def _read(self) -> None:
        try:
            for raw in self.ws:
                msg = protocol.decode(raw) if isinstance(raw, bytes) else None
                if msg is not None and msg.type != "image":
                    with self._cond:
                        self.received.append(msg)
                        self._cond.notify_all()
        except Exception:
            return

    def send(self, message: Message) -> int:
        self._seq += 1
        self.ws.send(protocol.encode(message.model_copy(update={"seq": self._seq})))
        return self._seq

    def ack(self, seq: int, timeout: float = 20.0) -> ParamsAck:
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for m in self.received:
                    if isinstance(m, ParamsAck) and m.ref == seq:
                        return m
                    if isinstance(m, protocol.Error) and m.ref == seq:
                        raise AssertionError(f"server refused: {m.message}")
                if not self._cond.wait(max(0.0, deadline - time.monotonic())):
                    raise TimeoutError(f"no ack for {seq}")

    def close(self) -> None:
        self.ws.close()
        self._thread.join(10)


@pytest.fixture
def steered_argon(live: Any) -> Iterator[tuple[Any, SteeringReporter, Steerer, threading.Thread]]:
    sim = argon_recipe(n_side=5, spacing_nm=0.6).make("CPU")
    reporter = SteeringReporter(sim_url(live), token=live.token, interval=10, session="live")
    sim.reporters.append(reporter)
    runner = threading.Thread(target=run_steered, args=(sim, 10_000_000), name="md")
    steerer = None
    try:
        assert reporter.connection.wait_connected(20), reporter.connection.error
        runner.start()
        steerer = Steerer(live, "live")
        yield sim, reporter, steerer, runner
    finally:
        reporter.stop_requested = True  # ends run_steered at its next report
        reporter.close()
        if runner.is_alive():
            runner.join(30)
        if steerer is not None:
            steerer.close()


def test_openmm_frames_reach_the_server_with_the_right_atom_count(
    no_leaked_threads: None, live: Any
) -> None:
    sim = argon_recipe(n_side=5).make("CPU")
    with SteeringReporter(sim_url(live), token=live.token, interval=5, session="frames") as rep:
        sim.reporters.append(rep)
        assert rep.connection.wait_connected(20), rep.connection.error
        assert run_steered(sim, 100) == 100
        summary = wait_until(
            lambda: (s := session_summary(live, "frames"))["status"]["step"] == 100 and s
        )
        assert summary["n_atoms"] == 125 and summary["status"]["n_atoms"] == 125
        assert summary["status"]["observables"]["temperature_K"] > 0
        assert list(rep.connection.server_errors) == []


def test_steering_through_the_server(
    steered_argon: tuple[Any, SteeringReporter, Steerer, threading.Thread], live: Any
) -> None:
    sim, reporter, steerer, runner = steered_argon
    # temperature: applied by the integrator, the ack names the step
    ack = steerer.ack(steerer.send(SimParams(temperature_K=150.0)))
    assert ack.ok and ack.step is not None and ack.step % 10 == 0
    assert sim.integrator.getTemperature().value_in_unit(unit.kelvin) == pytest.approx(150.0)
    # pause: steps stop, the server knows; resume: they go on
    assert steerer.ack(steerer.send(Control(action="pause"))).ok
    wait_until(lambda: session_summary(live, "live")["status"]["state"] == "paused")
    held = sim.currentStep
    time.sleep(0.5)
    assert sim.currentStep == held and runner.is_alive()
    assert steerer.ack(steerer.send(Control(action="resume"))).ok
    wait_until(lambda: sim.currentStep > held + 20)
    # pull atom 0 to a point 8 A away along +x: the server sends spring forces, it gets there
    state = sim.context.getState(getPositions=True)
    start = state.getPositions(asNumpy=True).value_in_unit(unit.angstrom)[0]
    target = start + np.array([8.0, 0.0, 0.0])

    def distance() -> float:
        pos = sim.context.getState(getPositions=True).getPositions(asNumpy=True)
        return float(np.linalg.norm(pos.value_in_unit(unit.angstrom)[0] - target))

    # a soft spring: the force lags the atom by a report or two, and a stiff spring on a light
    # atom would be driven unstable by that delay
    ack = steerer.ack(steerer.send(Pull(atom=0, target=tuple(target), spring_k=1.0)))
    assert ack.ok and ack.applied["atoms"] == 1
    wait_until(lambda: distance() < 3.0, timeout=60)
    assert steerer.ack(steerer.send(Pull(atom=0, release=True))).ok
    assert reporter.pull is not None
    wait_until(lambda: not reporter.pull.active)
    log = [e["event"] for e in _log(live, "live")]
    assert {"sim_params", "control", "pull", "applied"} <= set(log)


def _log(live: Any, session: str) -> list[dict[str, Any]]:
    req = urllib.request.Request(
        f"{live.url}/api/sessions/{session}/log",
        headers={"Authorization": f"Bearer {live.token}"},
    )
    with urllib.request.urlopen(req, timeout=10) as resp:
        entries: list[dict[str, Any]] = json.load(resp)
    return entries


def test_adapter_survives_a_server_restart(no_leaked_threads: None, live: Any) -> None:
    sim = argon_recipe(n_side=4).make("CPU")
    rep = SteeringReporter(sim_url(live), token=live.token, interval=5, session="restart")
    rep.connection._backoff_max = 1.0  # keep the test short
    sim.reporters.append(rep)
    restarted = None
    try:
        assert rep.connection.wait_connected(20)
        run_steered(sim, 20)
        restarted = live.restart()
        wait_until(lambda: rep.connection.stats.connects == 2, timeout=30)
        run_steered(sim, 20)
        summary = wait_until(
            lambda: (s := session_summary(restarted, "restart"))["status"]["step"] == 40 and s
        )
        assert summary["n_atoms"] == 64  # the topology was sent again
        assert rep.connection.stats.topologies_sent == 2
    finally:
        rep.close()
        if restarted is not None:
            restarted.stop()


def test_replay_streams_to_the_server(no_leaked_threads: None, live: Any) -> None:
    structure = load(PSF, [DCD])
    replay = TrajectoryReplay(
        structure, sim_url(live), live.token, "live-replay", fps=200, exit_at_end=True
    )
    replay.start()
    assert replay.wait(60)
    replay.close()
    assert replay.error is None and replay.frames_sent == 98
    assert list(replay.connection.server_errors) == []
    summary = session_summary(live, "live-replay")
    assert summary["n_atoms"] == 3341 and summary["status"]["step"] == 97


def test_a_wrong_token_is_refused(no_leaked_threads: None, live: Any) -> None:
    with SimulationConnection(sim_url(live), token=f"{live.token}-wrong") as conn:
        assert not conn.wait_connected(20)
        assert conn.state is ConnectionState.FAILED and conn.error


def _refusal(steerer: Steerer, seq: int, timeout: float = 20.0) -> protocol.Error:
    def found() -> protocol.Error | None:
        with steerer._cond:
            return next(
                (m for m in steerer.received if isinstance(m, protocol.Error) and m.ref == seq),
                None,
            )

    error: protocol.Error = wait_until(found, timeout)
    return error


def test_steering_cannot_blow_up_the_simulation(no_leaked_threads: None, live: Any) -> None:
    """Values the protocol accepts but villin cannot take are refused with the engine's limit;
    capped forces on every atom blow the run up, and the guard rolls it back, pauses it and
    tells the dashboard, while the session and the server keep running."""
    from tests.adapters.openmm_helpers import villin_recipe

    sim = villin_recipe().make("CPU")
    reporter = SteeringReporter(sim_url(live), token=live.token, interval=10, session="guarded")
    sim.reporters.append(reporter)
    runner = threading.Thread(target=run_steered, args=(sim, 10_000_000), name="md")
    steerer = None
    try:
        assert reporter.connection.wait_connected(20), reporter.connection.error
        runner.start()
        steerer = Steerer(live, "guarded")
        wait_until(lambda: session_summary(live, "guarded")["status"]["step"] > 0)
        refused = [
            (SimParams(temperature_K=10_000.0), "sim_params.temperature_K", "[1, 1000] K"),
            (SimParams(timestep_fs=20.0), "sim_params.timestep_fs", "fs"),
            (Pull(atom=0, target=(0.0, 0.0, 0.0), spring_k=100.0), "pull.spring_k", "stiffer"),
            (Control(action="seek", frame=3), "control.action", "cannot seek"),
        ]
        for message, path, says in refused:
            error = _refusal(steerer, steerer.send(message))
            assert error.code == "invalid_message" and error.path == path, error
            assert says in error.message and "OpenMM" in error.message, error.message
        n = sim.system.getNumParticles()
        vectors = np.random.default_rng(3).normal(size=(n, 3)) * 1e3
        steerer.send(
            protocol.Forces(
                indices=protocol.WireArray.from_numpy(np.arange(n, dtype=np.int32), "<i4"),
                forces=protocol.WireArray.from_numpy(vectors.astype(np.float32), "<f4"),
            )
        )

        def guard_event() -> protocol.Event | None:
            with steerer._cond:
                return next((m for m in steerer.received if isinstance(m, protocol.Event)), None)

        event = wait_until(guard_event, 60)
        assert event.code == "guard" and "rolled back" in event.message
        wait_until(lambda: session_summary(live, "guarded")["status"]["state"] == "paused")
        held = sim.currentStep
        assert steerer.ack(steerer.send(Control(action="resume"))).ok
        wait_until(lambda: sim.currentStep > held + 100, 60)
        assert reporter.guard_trips == 1 and runner.is_alive()
        assert "sim_event" in {e["event"] for e in _log(live, "guarded")}
    finally:
        reporter.stop_requested = True
        reporter.close()
        runner.join(30)
        if steerer is not None:
            steerer.close()
