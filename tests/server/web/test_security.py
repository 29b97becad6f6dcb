"""Tokens, roles, Origins, limits and hostile input on both WebSocket endpoints."""

from __future__ import annotations

import math
import random
import time

import msgpack
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus

import protocol as p
from server.web.auth import RateLimiter
from server.web.ws import MAX_ERRORS_PER_10S, MAX_REFUSED_PER_10S, Guard
from tests.conftest import LiveServer
from tests.protocol.samples import samples
from tests.protocol.test_fuzz import _mutations
from tests.server.peers import Peer, frame, molecule


def closed_with(peer: Peer) -> tuple[p.Error | None, int | None]:
    """Read until the server closes; returns the last error and the close code."""
    error = None
    try:
        while True:
            msg = peer.recv(20)
            if isinstance(msg, p.Error):
                error = msg
    except ConnectionClosed as exc:
        return error, exc.rcvd.code if exc.rcvd else None


def test_no_or_wrong_token_is_unauthorized(live_server: LiveServer) -> None:
    for token in (None, "wrong"):
        peer = Peer(live_server.view_url, "steerer", token, hello=False)
        peer.send(p.Hello(role="steerer", token=token))
        error, code = closed_with(peer)
        assert error is not None and error.code == "unauthorized" and code == 1008


def test_viewer_token_cannot_steer_or_claim_steerer(live_server: LiveServer) -> None:
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token)
    for msg in (
        p.SetRenderParams(params={"sigma_A": 2.0}),
        p.SimParams(temperature_K=400.0),
        p.Control(action="pause"),
        p.Pull(atom=0, target=(0.0, 0.0, 0.0)),
    ):
        seq = viewer.send(msg)
        err = viewer.expect(p.Error)
        assert (err.code, err.ref) == ("forbidden", seq)
    viewer.send(p.Ping(client_time=1.0))
    assert viewer.expect(p.Pong).client_time == 1.0  # still connected
    claim = Peer(live_server.view_url, "steerer", live_server.viewer_token, hello=False)
    claim.send(p.Hello(role="steerer", token=live_server.viewer_token))
    error, code = closed_with(claim)
    # the right token for another role: forbidden and said so, not "wrong token"
    assert error is not None and error.code == "forbidden" and code == 1008
    assert "viewer token is read-only: role steerer needs the server token" in error.message
    assert error.path == "hello.role"


def test_roles_belong_on_their_endpoint(live_server: LiveServer) -> None:
    peer = Peer(live_server.view_url, "simulation", live_server.token, hello=False)
    peer.send(p.Hello(role="simulation", token=live_server.token))
    error, _ = closed_with(peer)
    assert error is not None and error.code == "forbidden"


def test_foreign_origin_is_refused(live_server: LiveServer) -> None:
    with pytest.raises(InvalidStatus) as info:
        Peer(live_server.view_url, "viewer", live_server.viewer_token, origin="http://evil.example")
    assert info.value.response.status_code == 403
    ok = Peer(live_server.view_url, "viewer", live_server.viewer_token, origin=live_server.url)
    assert ok.welcome is not None
    ok.close()


def test_oversized_message_is_too_large_and_closes_1009(live_server: LiveServer) -> None:
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token)
    viewer.send_raw(b"\x00" * (live_server.settings.viewer_limits.max_message_bytes + 10))
    _error, code = closed_with(viewer)  # refused by the transport from the frame's header
    assert code == 1009
    # a simulation, once its hello is accepted, may send up to its own (larger) limit
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "big")
    topo, pos = molecule(20_000)
    sim.send(topo)
    sim.send(frame(pos, 0))
    assert len(p.encode(topo)) > live_server.settings.viewer_limits.max_message_bytes
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "big")
    viewer.expect(p.State, where=lambda m: m.sim is not None and m.sim.n_atoms == 20_000)


def test_steering_flood_is_rate_limited(live_server: LiveServer) -> None:
    """A burst of valid steering over the rate is answered message by message, each refusal
    naming the limit, and the connection stays (a burst is not a run of invalid messages)."""
    steerer = Peer(live_server.view_url, "steerer", live_server.token)
    limit = live_server.settings.limits.max_steer_per_s
    seqs = {
        steerer.send(p.SetRenderParams(params={"iso_level": 0.3 + (i % 5) * 0.1}))
        for i in range(int(limit * 2) + 20)
    }
    answers = steerer.drain(3.0)
    refused = [m for m in answers if isinstance(m, p.Error)]
    assert refused and all(m.code == "rate_limited" for m in refused), refused
    assert all(f"{limit:g} a second" in m.message for m in refused), refused[0].message
    answered = {m.ref for m in answers if isinstance(m, p.State | p.Error) and m.ref is not None}
    assert answered == seqs, f"{len(seqs - answered)} messages unanswered"
    seq = steerer.send(p.Ping(client_time=0.0))
    steerer.expect(p.Pong, where=lambda m: m.ref == seq)  # still connected
    # the budget is the client's (its role and address, all its connections together): on
    # loopback a new connection is the same client, which steers again once it has refilled
    other = Peer(live_server.view_url, "steerer", live_server.token)
    deadline = time.monotonic() + 20
    while True:
        other.send(p.SetRenderParams(params={"sigma_A": 2.0}))
        refused = [m for m in other.drain(1.0) if isinstance(m, p.Error)]
        if not refused:
            break
        assert all(m.code == "rate_limited" for m in refused), refused
        assert time.monotonic() < deadline, "the client's budget never refilled"


def test_message_before_hello_and_bad_version(live_server: LiveServer) -> None:
    peer = Peer(live_server.view_url, "viewer", None, hello=False)
    peer.send(p.View())
    error, code = closed_with(peer)
    assert error is not None and error.code == "not_ready" and code == 1008
    peer = Peer(live_server.view_url, "viewer", None, hello=False)
    peer.send_raw(
        msgpack.packb({"type": "hello", "role": "viewer", "protocol_version": "9.0", "seq": 1})
    )
    error, _ = closed_with(peer)
    assert error is not None and error.code == "version_mismatch" and error.ref == 1


def test_frames_are_checked_against_the_topology(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token)
    topo, pos = molecule(10)
    seq = sim.send(frame(pos, 0))
    err = sim.expect(p.Error)
    assert (err.code, err.ref) == ("not_ready", seq)
    sim.send(topo)
    seq = sim.send(frame(np.zeros((7, 3), np.float32), 1))
    err = sim.expect(p.Error)
    assert (
        err.code == "invalid_message" and err.path == "frame.positions" and "7 atoms" in err.message
    )
    raw = p.unpack(p.encode(frame(pos, 2)))
    raw["positions"]["data"] = np.full((10, 3), np.nan, "<f4").tobytes()
    sim.send_raw(msgpack.packb(raw))
    err = sim.expect(p.Error)
    assert err.code == "invalid_message" and err.path == "frame.positions"
    sim.close()


def test_hostile_input_on_both_endpoints_leaves_other_sessions_serving(
    live_server: LiveServer,
) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "calm")
    topo, pos = molecule(16)
    sim.send(topo)
    sim.send(frame(pos, 0))
    watcher = Peer(live_server.view_url, "viewer", live_server.viewer_token, "calm")
    watcher.expect(p.Image, 60)
    rng = random.Random(5)
    corpus = [p.encode(m) for m in samples().values()]
    codes: dict[str, int] = {}
    for url, role in ((live_server.ws_url, "simulation"), (live_server.view_url, "steerer")):
        hostile = Peer(url, role, live_server.token, "stormy")  # type: ignore[arg-type]
        sent = 0
        for i in range(300):
            raw = _mutations(rng, corpus[i % len(corpus)])
            try:
                hostile.send_raw(raw)
            except ConnectionClosed:
                hostile = Peer(url, role, live_server.token, "stormy")  # type: ignore[arg-type]
                continue
            sent += 1
            if i % 40 == 0:
                for msg in hostile.drain(0.2):
                    if isinstance(msg, p.Error):
                        codes[msg.code] = codes.get(msg.code, 0) + 1
                step = 100 + i
                sim.send(frame(pos + np.float32(0.01 * (i % 9)), step))
                watcher.expect(p.Image, 60, where=lambda m, s=step: m.step == s)
            time.sleep(0.002)
        assert sent > 250
        hostile.close()
    assert codes.get("invalid_message", 0) > 0
    sim.close()
    watcher.close()


def test_foreign_host_header_is_refused(live_server: LiveServer) -> None:
    """A page reaching the loopback server through a rebound DNS name sends its own Host."""
    import httpx

    r = httpx.get(
        f"{live_server.url}/healthz", headers={"Host": f"evil.example:{live_server.port}"}
    )
    assert r.status_code == 403
    assert httpx.get(f"{live_server.url}/healthz").status_code == 200
    with pytest.raises(InvalidStatus):
        Peer(
            live_server.view_url,
            "viewer",
            live_server.viewer_token,
            origin=f"http://evil.example:{live_server.port}",
        )


def test_viewers_join_but_do_not_create_sessions(live_server: LiveServer) -> None:
    peer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "made-up", hello=False)
    peer.send(p.Hello(role="viewer", token=live_server.viewer_token, session="made-up"))
    error, _ = closed_with(peer)
    assert error is not None and error.code == "not_found"
    default = Peer(live_server.view_url, "viewer", live_server.viewer_token)  # always exists
    assert default.welcome is not None and default.welcome.session_id == "default"
    default.close()
    bad = Peer(live_server.view_url, "steerer", live_server.token, hello=False)
    bad.send_raw(
        msgpack.packb({"type": "hello", "role": "steerer", "token": "test-token", "session": ".."})
    )
    error, _ = closed_with(bad)
    assert error is not None and error.code == "invalid_message" and error.path == "hello.session"


def test_a_second_simulation_is_refused_unless_it_takes_over(live_server: LiveServer) -> None:
    old = Peer(live_server.ws_url, "simulation", live_server.token, instance="a1")
    topo, pos = molecule(10)
    old.send(topo)
    old.send(frame(pos, 0))
    steerer = Peer(live_server.view_url, "steerer", live_server.token)
    # another adapter instance: refused, and the first keeps the session
    with pytest.raises(ConnectionClosed) as refused:
        Peer(live_server.ws_url, "simulation", live_server.token, instance="b2")
    assert refused.value.rcvd is not None and refused.value.rcvd.code == 1008
    assert refused.value.rcvd.reason == "conflict"
    old.send(frame(pos, 1))
    steerer.expect(p.Image, 60, where=lambda m: m.step == 1)
    # it asks to take over: the old one is told why and closed, its pending steering failed
    seq = steerer.send(p.SimParams(temperature_K=320.0))
    old.expect(p.SimParams)  # forwarded, never acknowledged
    new = Peer(live_server.ws_url, "simulation", live_server.token, instance="b2", takeover=True)
    error, code = closed_with(old)
    assert error is not None and "replaced" in error.message and code == 1008
    ack = steerer.expect(p.ParamsAck, where=lambda m: m.ref == seq)
    assert not ack.ok and "replaced" in ack.detail
    new.send(topo)
    new.send(frame(pos, 5))
    steerer.expect(p.Image, 60, where=lambda m: m.step == 5)
    # the same instance reconnecting (its old socket not yet noticed as gone) replaces itself
    again = Peer(live_server.ws_url, "simulation", live_server.token, instance="b2")
    error, code = closed_with(new)
    assert code == 1008
    again.send(topo)
    again.send(frame(pos, 6))
    steerer.expect(p.Image, 60, where=lambda m: m.step == 6)
    again.close()
    steerer.close()


def test_an_adapter_refused_for_a_taken_session_stops_trying(live_server: LiveServer) -> None:
    from simulation_adapters.connection import ConnectionState, SimulationConnection

    first = Peer(live_server.ws_url, "simulation", live_server.token, instance="first")
    with SimulationConnection(live_server.ws_url, token=live_server.token) as second:
        assert not second.wait_connected(10)
        assert second.state is ConnectionState.FAILED
        assert second.error is not None and "conflict" in second.error
        connects = second.stats.connects
        time.sleep(1.0)
        assert second.stats.connects == connects == 0  # no flapping
    first.close()


def test_pulls_are_capped(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from tests.conftest import make_settings, start_server

    server = start_server(make_settings(tmp_path, limits=p.Limits(max_forces=2)))
    try:
        sim = Peer(server.ws_url, "simulation", server.token)
        topo, pos = molecule(10)
        sim.send(topo)
        sim.send(frame(pos, 0))
        steerer = Peer(server.view_url, "steerer", server.token)
        for atom in (0, 1):
            steerer.send(p.Pull(atom=atom, target=(0.0, 0.0, 0.0)))
        seq = steerer.send(p.Pull(atom=2, target=(0.0, 0.0, 0.0)))
        err = steerer.expect(p.Error, where=lambda m: m.ref == seq)
        assert err.code == "too_large" and err.path == "pull.atom"
        sim.close()
        steerer.close()
    finally:
        server.stop()


def test_the_steering_budget_is_the_clients_not_the_connections(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Round three: the steering rate limit started afresh on every reconnection (15,114
    actions accepted in 30 s, 4.2 times the limit, each one fsync'd to the steering log)."""
    from tests.conftest import make_settings, start_server

    rate = 1.0  # one steering message a second, bursts of one
    limits = p.Limits(max_message_bytes=256 * 1024, max_steer_per_s=rate)
    server = start_server(make_settings(tmp_path, viewer_limits=limits))
    try:
        accepted = refused = 0
        started = time.monotonic()
        for _ in range(6):  # a flood that reconnects after every refusal
            steerer = Peer(server.view_url, "steerer", server.token)
            seqs = []
            for _ in range(3):  # each a change (a change is what the log records)
                sigma = 1.0 + 0.01 * (accepted + refused + len(seqs))
                seqs.append(steerer.send(p.SetRenderParams(params={"sigma_A": sigma})))
            steerer.send(p.Ping(client_time=0.0))
            replies = []
            while not any(isinstance(m, p.Pong) for m in replies):
                replies.append(steerer.recv(10))
            errors = {m.ref: m for m in replies if isinstance(m, p.Error)}
            for seq in seqs:
                if seq in errors:
                    assert errors[seq].code == "rate_limited"
                    assert "1 a second for each client" in errors[seq].message
                    refused += 1
                else:
                    accepted += 1
            steerer.close()
        elapsed = time.monotonic() - started
        # one burst, then what refilled meanwhile: not a fresh burst per connection
        assert accepted <= 1 + math.floor(elapsed * rate), (accepted, elapsed)
        assert refused >= 18 - accepted
        # the log holds what was accepted, and only that (its writer thread may lag a little)
        deadline = time.monotonic() + 10
        while True:
            log = server.app_state.steering_log.read("default")
            logged = sum(e.get("event") == "render_params" for e in log)
            if logged >= accepted or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        assert logged == accepted
        # a viewer at the same address is another client: its own budget is whole
        viewer = Peer(server.view_url, "viewer", server.viewer_token)
        viewer.send(p.Ping(client_time=3.0))
        assert viewer.expect(p.Pong, 10).client_time == 3.0
        viewer.close()
    finally:
        server.stop()


def test_viewers_cannot_shut_the_steerers_out_of_a_session(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Round four: 64 connections with the viewer token filled the session, and the steerer
    with the server token was refused (`capacity`). Viewers now leave `steerer_places`."""
    from tests.conftest import make_settings, start_server

    server = start_server(make_settings(tmp_path, max_clients_per_session=4, steerer_places=1))
    try:
        sim = Peer(server.ws_url, "simulation", server.token)
        sim.send(molecule(6)[0])
        viewers = [Peer(server.view_url, "viewer", server.viewer_token) for _ in range(3)]
        late = Peer(server.view_url, "viewer", server.viewer_token, hello=False)
        late.send(p.Hello(role="viewer", token=server.viewer_token, client="late"))
        refused = late.expect(p.Error, timeout=20)
        assert refused.code == "capacity" and "steerer_places" in refused.message
        steerer = Peer(server.view_url, "steerer", server.token)  # the kept place
        assert steerer.welcome is not None
        full = Peer(server.view_url, "steerer", server.token, hello=False)
        full.send(p.Hello(role="steerer", token=server.token, client="fifth"))
        assert full.expect(p.Error, timeout=20).code == "capacity"
        for peer in (*viewers, late, steerer, full, sim):
            peer.close()
    finally:
        server.stop()


def test_refusals_for_rate_close_only_a_client_that_keeps_flooding() -> None:
    """Invalid messages close a connection after `MAX_ERRORS_PER_10S`; messages refused only
    for their rate after `MAX_REFUSED_PER_10S`, many times a burst of the steering rate."""
    limiter = RateLimiter(120.0, 120.0)
    guard = Guard(limiter, limiter, ("steerer", "127.0.0.1"))
    over = p.ProtocolError(p.ErrorCode.RATE_LIMITED, "too many render_params messages")
    assert all(guard.note_error(over) is None for _ in range(MAX_REFUSED_PER_10S))
    closing = guard.note_error(over)
    assert closing is not None and "over the rate limit" in closing
    bad = p.ProtocolError(p.ErrorCode.INVALID_MESSAGE, "render_params.params.sigma_A: bad")
    assert all(guard.note_error(bad) is None for _ in range(MAX_ERRORS_PER_10S))
    closing = guard.note_error(bad)
    assert closing is not None and "invalid messages" in closing
