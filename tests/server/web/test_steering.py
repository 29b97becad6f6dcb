"""Steering through a real server: patches merge deeply, refused simulation parameters are
rolled back, forces from scripts and pulls reach the engine as one set, and a fast simulation
is never throttled."""

from __future__ import annotations

import time

import msgpack
import numpy as np

import protocol as p
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame, molecule


def connect(live: LiveServer, session: str) -> tuple[Peer, Peer, np.ndarray]:
    sim = Peer(live.ws_url, "simulation", live.token, session)
    topo, pos = molecule()
    sim.send(topo)
    sim.send(frame(pos, 0))
    steerer = Peer(live.view_url, "steerer", live.token, session)
    steerer.expect(p.State, where=lambda m: m.sim is not None and m.sim.n_atoms == 24)
    return sim, steerer, pos


def test_a_partial_lighting_patch_keeps_the_other_fields(live_server: LiveServer) -> None:
    sim, steerer, _ = connect(live_server, "lighting")
    steerer.send(p.SetRenderParams(params={"lighting": {"specular": 0.9}}))
    steerer.expect(
        p.State, where=lambda m: m.render_params and m.render_params.lighting.specular == 0.9
    )
    steerer.send(p.SetRenderParams(params={"lighting": {"ambient": 0.5}}))
    state = steerer.expect(
        p.State, where=lambda m: m.render_params and m.render_params.lighting.ambient == 0.5
    )
    assert state.render_params is not None
    assert state.render_params.lighting.specular == 0.9, "the earlier change was reset"
    log = [
        e
        for e in live_server.app_state.steering_log.read("lighting")
        if e["event"] == "render_params"
    ]
    deadline = time.monotonic() + 10
    while len(log) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
        log = [
            e
            for e in live_server.app_state.steering_log.read("lighting")
            if e["event"] == "render_params"
        ]
    assert [e["changes"] for e in log] == [
        {"lighting.specular": 0.9},
        {"lighting.ambient": 0.5},
    ]
    sim.close()
    steerer.close()


def test_every_render_params_message_is_answered_by_a_state_naming_it(
    live_server: LiveServer,
) -> None:
    """A change reaches everyone in a state naming the message and its sender; a patch of the
    values already in effect is answered to its sender alone, with no parameters."""
    sim, steerer, _ = connect(live_server, "answered")
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "answered")
    viewer.expect(p.State, where=lambda m: m.render_params is not None)
    assert steerer.welcome is not None
    me = steerer.welcome.client_id
    seq = steerer.send(p.SetRenderParams(params={"sigma_A": 2.5}))
    for peer in (steerer, viewer):
        state = peer.expect(p.State, where=lambda m: m.ref == seq)
        assert state.by == me
        assert state.render_params is not None and state.render_params.sigma_A == 2.5
    again = steerer.send(p.SetRenderParams(params={"sigma_A": 2.5}))
    state = steerer.expect(p.State, where=lambda m: m.ref == again)
    assert state.by == me and state.render_params is None
    # only the sender hears of it: the viewer's next answer is to the next change
    later = steerer.send(p.SetRenderParams(params={"sigma_A": 3.0}))
    state = viewer.expect(p.State, where=lambda m: m.ref is not None)
    assert state.ref == later and state.render_params is not None
    # an unnumbered patch has nothing to be answered by
    steerer.send_raw(p.encode(p.SetRenderParams(params={"sigma_A": 3.5})))
    state = viewer.expect(
        p.State, where=lambda m: m.render_params is not None and m.render_params.sigma_A == 3.5
    )
    assert state.ref is None and state.by == me
    sim.close()
    steerer.close()
    viewer.close()


def test_a_patch_with_an_unknown_key_is_refused_by_name_and_changes_nothing(
    live_server: LiveServer,
) -> None:
    """A misspelt key in a steerer's patch is named in an error echoing the patch, and none of
    the patch applies (not its valid keys either); the next patch applies as usual."""
    sim, steerer, _ = connect(live_server, "typo")
    raw = {"type": "render_params", "seq": 90, "params": {"sigma_A": 2.5, "iso_levle": 0.4}}
    steerer.send_raw(msgpack.packb(raw))
    err = steerer.expect(p.Error, where=lambda m: m.ref == 90)
    assert err.code == p.ErrorCode.INVALID_MESSAGE
    assert err.path == "render_params.params.iso_levle"
    assert "iso_levle: unknown field" in err.message
    seq = steerer.send(p.SetRenderParams(params={"iso_level": 0.4}))
    state = steerer.expect(p.State, where=lambda m: m.ref == seq)
    assert state.render_params is not None and state.render_params.iso_level == 0.4
    assert state.render_params.sigma_A != 2.5, "the refused patch's valid key applied"
    changes = [
        e["changes"]
        for e in live_server.app_state.steering_log.read("typo")
        if e["event"] == "render_params"
    ]
    assert changes == [{"iso_level": 0.4}]
    # a simulation parameter likewise: refused by name, never forwarded to the simulation
    steerer.send_raw(msgpack.packb({"type": "sim_params", "seq": 91, "temperatur_K": 280.0}))
    err = steerer.expect(p.Error, where=lambda m: m.ref == 91)
    assert err.path == "sim_params.temperatur_K" and "unknown field" in err.message
    seq = steerer.send(p.Ping(client_time=0.0))
    steerer.expect(p.Pong, where=lambda m: m.ref == seq)  # the server read past it
    forwarded = [m for m in sim.drain(0.5) if isinstance(m, p.SimParams)]
    assert not forwarded, "a refused change reached the simulation"
    sim.close()
    steerer.close()


def test_refused_sim_params_are_rolled_back(live_server: LiveServer) -> None:
    sim, steerer, _ = connect(live_server, "refuse")
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "refuse")
    viewer.expect(p.State, where=lambda m: m.sim_params is not None)
    seq = steerer.send(p.SimParams(temperature_K=450.0))
    forwarded = sim.expect(p.SimParams)
    assert forwarded.temperature_K == 450.0
    sim.send(p.ParamsAck(ref=forwarded.seq, ok=False, detail="the engine refuses"))
    ack = steerer.expect(p.ParamsAck, where=lambda m: m.ref == seq)
    assert not ack.ok and "refuses" in ack.detail
    state = viewer.expect(p.State, where=lambda m: m.sim_params is not None)
    assert state.sim_params is not None and state.sim_params.temperature_K is None
    session = live_server.app_state.sessions.get("refuse")
    assert session.sim_params.temperature_K is None
    # an accepted change shows once the engine has acknowledged it, not before
    seq = steerer.send(p.SimParams(temperature_K=350.0))
    forwarded = sim.expect(p.SimParams)
    assert session.sim_params.temperature_K is None
    sim.send(p.ParamsAck(ref=forwarded.seq, ok=True, step=5, applied={"temperature_K": 350.0}))
    assert steerer.expect(p.ParamsAck, where=lambda m: m.ref == seq).ok
    state = viewer.expect(p.State, where=lambda m: m.sim_params is not None)
    assert state.sim_params is not None and state.sim_params.temperature_K == 350.0
    for peer in (sim, steerer, viewer):
        peer.close()


def forces_of(message: p.Forces) -> dict[int, tuple[float, ...]]:
    idx = message.indices.to_numpy().tolist()
    vec = message.forces.to_numpy().tolist()
    return {int(i): tuple(round(v, 3) for v in f) for i, f in zip(idx, vec, strict=True)}


def test_script_forces_and_pulls_reach_the_engine_as_one_set(live_server: LiveServer) -> None:
    sim, script, pos = connect(live_server, "forces")
    user = Peer(live_server.view_url, "steerer", live_server.token, "forces")
    script.send(
        p.Forces(
            indices=p.WireArray.from_numpy(np.array([3], np.int32), "<i4"),
            forces=p.WireArray.from_numpy(np.array([[5.0, 0.0, 0.0]], np.float32), "<f4"),
        )
    )
    assert forces_of(sim.expect(p.Forces)) == {3: (5.0, 0.0, 0.0)}
    user.send(p.Pull(atom=7, force=(0.0, 0.0, 10.0)))
    assert forces_of(sim.expect(p.Forces)) == {3: (5.0, 0.0, 0.0), 7: (0.0, 0.0, 10.0)}
    user.send(p.Pull(atom=9, target=tuple(float(v) + 2.0 for v in pos[9])))  # type: ignore[arg-type]
    merged = forces_of(sim.expect(p.Forces))
    assert set(merged) == {3, 7, 9} and merged[3] == (5.0, 0.0, 0.0)
    # springs follow every frame; the script's force stays in every update
    sim.send(frame(pos, 1))
    assert set(forces_of(sim.expect(p.Forces))) == {3, 7, 9}
    user.close()  # its pulls go with it; the script's force stays
    assert forces_of(sim.expect(p.Forces)) == {3: (5.0, 0.0, 0.0)}
    script.send(
        p.Forces(
            indices=p.WireArray.from_numpy(np.zeros(0, np.int32), "<i4"),
            forces=p.WireArray.from_numpy(np.zeros((0, 3), np.float32), "<f4"),
        )
    )
    assert forces_of(sim.expect(p.Forces)) == {}
    sim.close()
    script.close()


def test_a_spring_follows_every_frame_not_only_the_displayed_ones(live_server: LiveServer) -> None:
    """Round three: a pull's spring was recomputed only from the frames the server displayed
    (132 updates for 7,896 frames of a fast OpenMM run): the force lagged its atom by hundreds
    of steps, pointed away from the target, flung the atom and blew the run up. Every frame
    that comes now sends the spring's force computed from that frame, in the displayed frame
    (a periodic box, molecules put in the box: the default display)."""
    sim, steerer, pos = connect(live_server, "spring")
    box = p.WireArray.from_numpy(np.diag([30.0, 30.0, 30.0]).astype(np.float32), "<f4")
    steerer.send(p.Pull(atom=0, target=(5.0, 5.0, 5.0), spring_k=1.0, max_force=1000.0))
    sim.expect(p.Forces)
    n = 60
    for step in range(1, n + 1):  # a burst, faster than the display takes frames
        moved = pos.copy()
        moved[0] = (float(step) * 0.1, 5.0, 5.0)
        message = frame(moved, step)
        sim.send(message.model_copy(update={"box": box}))
    got = [forces_of(sim.expect(p.Forces, 30))[0] for _ in range(n)]
    # one per frame, each from its own frame: the spring's x falls as the atom nears x = 5
    expected = [round(5.0 - 0.1 * step, 4) for step in range(1, n + 1)]
    assert [round(f[0], 4) for f in got] == expected
    sim.close()
    steerer.close()


def test_a_fast_small_simulation_is_never_throttled(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "fast")
    topo, pos = molecule(4)
    sim.send(topo)
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "fast")
    n = 8000  # well over a second's worth of any per-connection message allowance
    for step in range(n):
        sim.send(frame(pos, step))
    sim.send(p.Ping(client_time=1.0))
    replies = []
    while True:
        message = sim.recv(60)
        replies.append(message)
        if isinstance(message, p.Pong):
            break
    errors = [m for m in replies if isinstance(m, p.Error)]
    assert errors == [], errors[:3]
    session = live_server.app_state.sessions.get("fast")
    assert session.sim is not None and session.status.step == n - 1
    sim.close()
    viewer.close()
