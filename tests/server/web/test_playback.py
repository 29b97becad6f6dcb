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


def test_a_replays_speed_and_loop_reach_every_viewer(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "playback")
    replay = p.EngineInfo(name="replay of a test", kind="replay", n_frames=10,
                          controls=["pause", "resume", "speed", "loop"],
                          playback=p.Playback(speed=1.0, loop=True))  # fmt: skip
    sim.send(replay)
    topology, positions = molecule(12)
    sim.send(topology)
    sim.send(frame(positions, 0))
    steerer = Peer(live_server.view_url, "steerer", live_server.token, "playback")
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
