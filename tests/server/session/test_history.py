"""The frames a session keeps for temporal smoothing: while asked for, up to the window, and
started again when a replay seeks."""

from __future__ import annotations

import time

import protocol as p
from server.session.steps import StepRun, is_jump
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame, molecule


def test_steps_that_go_back_or_skip_far_ahead_are_jumps() -> None:
    assert not is_jump(100, 10, 110)
    assert not is_jump(100, 10, 140)
    assert is_jump(100, 10, 141)  # more than 4 increments: a seek ahead
    assert is_jump(100, 10, 90)  # back: a seek or a reset
    assert is_jump(5, 1, 5)
    assert not is_jump(0, 0, 500)  # the second frame sets the increment


def test_a_run_of_steps_learns_its_increment_and_starts_again_after_a_jump() -> None:
    run = StepRun()
    assert [run.advance(s) for s in (0, 10, 20, 30)] == [False] * 4
    assert run.delta == 10
    assert run.advance(500)  # a seek ahead: a jump, the increment kept
    assert run.delta == 10 and not run.advance(510)
    assert run.advance(100)  # back
    run.reset()
    assert not run.advance(5)  # a new run's first step never jumps


def wait(condition: object, what: str) -> None:
    deadline = time.monotonic() + 20
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def test_the_history_fills_to_the_window_and_restarts_on_a_seek(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "hist")
    topo, pos = molecule()
    sim.send(topo)
    steerer = Peer(live_server.view_url, "steerer", live_server.token, "hist")
    live = live_server.app_state.sessions.get("hist")
    try:
        sim.send(frame(pos, 0))
        wait(lambda: live.positions is not None, "a frame")
        assert live.snapshot().history == ()  # smoothing off: nothing kept
        steerer.send(p.SetRenderParams(params={"time_smoothing": "warped", "time_window": 4}))
        wait(lambda: live.render_params.time_smoothing == "warped", "smoothing on")
        for k in range(1, 7):
            sim.send(frame(pos + k, k * 10))
        wait(lambda: live.status.step == 60, "six frames")
        snap = live.snapshot()
        assert len(snap.history) == 4 and snap.history[-1][0] == snap.positions_id
        assert snap.live
        epoch = snap.history_epoch
        sim.send(frame(pos, 20))  # a replay seeked back
        wait(lambda: live.status.step == 20, "the seek")
        snap = live.snapshot()
        assert snap.history_epoch == epoch + 1 and len(snap.history) == 1
    finally:
        sim.close()
        steerer.close()


def test_a_new_topology_starts_the_window_again(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "retopo")
    topo, pos = molecule()
    sim.send(topo)
    steerer = Peer(live_server.view_url, "steerer", live_server.token, "retopo")
    live = live_server.app_state.sessions.get("retopo")
    try:
        steerer.send(p.SetRenderParams(params={"time_smoothing": "classical", "time_window": 4}))
        wait(lambda: live.render_params.time_smoothing == "classical", "smoothing on")
        for k in range(3):
            sim.send(frame(pos + k, k * 10))
        wait(lambda: live.snapshot() and len(live.snapshot().history) == 3, "three frames")
        small, small_pos = molecule(n=12)
        sim.send(small)
        sim.send(frame(small_pos, 40))
        wait(lambda: live.positions is not None and len(live.positions) == 12, "the new system")
        snap = live.snapshot()
        assert len(snap.history) == 1 and snap.history[0][1].shape == (12, 3)
        image = steerer.expect(p.Image, where=lambda m: m.still is not False)
        assert image.data  # the smoothed render of the new system
    finally:
        sim.close()
        steerer.close()
