"""A replay's speed and loop as the server keeps them: every viewer sees them as the replay
acknowledged them, also a viewer who joins later (the dashboard's Loop box had shown a replay
opened with loop on as off)."""

from __future__ import annotations

import protocol as p
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame, molecule


def engine_state(peer: Peer) -> p.EngineInfo:
    state = peer.expect(p.State, 30, where=lambda m: m.engine is not None)
    assert state.engine is not None
    return state.engine


def open_replay(server: LiveServer, session: str, engine: p.EngineInfo) -> tuple[Peer, Peer]:
    """A simulation declaring `engine` with a frame of a small molecule, and a steerer."""
    sim = Peer(server.ws_url, "simulation", server.token, session)
    sim.send(engine)
    topology, positions = molecule(12)
    sim.send(topology)
    sim.send(frame(positions, 0))
    return sim, Peer(server.view_url, "steerer", server.token, session)


def test_a_replays_speed_and_loop_reach_every_viewer(live_server: LiveServer) -> None:
    replay = p.EngineInfo(name="replay of a test", kind="replay", n_frames=10,
                          controls=["pause", "resume", "speed", "loop"],
                          playback=p.Playback(speed=1.0, loop=True))  # fmt: skip
    sim, steerer = open_replay(live_server, "playback", replay)
    try:
        assert engine_state(steerer).playback == p.Playback(speed=1.0, loop=True)
        steerer.send(p.Control(action="loop", loop=False))
        forwarded = sim.expect(p.Control)
        sim.send(p.ParamsAck(ref=forwarded.seq, step=0, applied={"action": "loop", "loop": False}))
        assert engine_state(steerer).playback == p.Playback(speed=1.0, loop=False)
        late = Peer(live_server.view_url, "viewer", live_server.viewer_token, "playback")
        try:
            assert engine_state(late).playback == p.Playback(speed=1.0, loop=False)
        finally:
            late.close()
        # an acknowledged value the playback cannot hold leaves it as it was
        steerer.send(p.Control(action="speed", speed=2.0))
        forwarded = sim.expect(p.Control)
        sim.send(p.ParamsAck(ref=forwarded.seq, step=0, applied={"action": "speed", "speed": -1}))
        steerer.expect(p.ParamsAck, 30)
        session = live_server.app_state.sessions.get("playback")
        assert session is not None and session.engine is not None
        assert session.engine.playback == p.Playback(speed=1.0, loop=False)
    finally:
        steerer.close()
        sim.close()


def engines_until_event(peer: Peer) -> list[p.EngineInfo]:
    """The engines `peer` is sent before the next event (the simulation's marker: messages
    reach a viewer in the order the session sends them)."""
    seen: list[p.EngineInfo] = []
    while not isinstance(message := peer.recv(30), p.Event):
        if isinstance(message, p.State) and message.engine is not None:
            seen.append(message.engine)
    return seen


def test_a_change_the_replay_declares_again_reaches_the_viewers_once(
    live_server: LiveServer,
) -> None:
    """A replay declares its engine again as its speed changes, then acknowledges the change:
    the viewers had been sent the new engine twice (and re-sent the same one after a
    reconnect), each time one message more to every viewer."""
    engine = p.EngineInfo(name="replay of a test", kind="replay", n_frames=10,
                          controls=["speed", "loop"], playback=p.Playback())  # fmt: skip
    sim, steerer = open_replay(live_server, "again", engine)
    try:
        engine_state(steerer)
        steerer.send(p.Control(action="speed", speed=2.0))
        forwarded = sim.expect(p.Control)
        faster = engine.model_copy(update={"playback": p.Playback(speed=2.0)})
        sim.send(faster)  # as the replay does: declared, then acknowledged
        sim.send(p.ParamsAck(ref=forwarded.seq, step=0, applied={"action": "speed", "speed": 2}))
        marker = p.Event(code="marker", message="the steps above are in")
        sim.send(marker)
        assert [e.playback for e in engines_until_event(steerer)] == [p.Playback(speed=2.0)]
        sim.send(faster)  # declared again as it is (a reconnect)
        sim.send(marker)
        assert engines_until_event(steerer) == []
    finally:
        steerer.close()
        sim.close()
