"""Trajectory replay of MDAnalysisTests' files to a real /ws/sim peer, steered like a live run."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Iterator

import numpy as np
import pytest
from MDAnalysisTests.datafiles import DCD, GRO, MMCIF, PSF, XTC, PDB_multiframe

from protocol import Control, EngineInfo, Event, Playback, SimParams
from simulation_adapters import replay
from simulation_adapters.replay import TrajectoryReplay
from structures.reader import load
from tests.adapters.sim_peer import SimPeer

HANG_S = 300.0
"""Only a hung replay takes this long (the ten frames take a second)."""


@pytest.fixture
def replays() -> Iterator[list[TrajectoryReplay]]:
    made: list[TrajectoryReplay] = []
    yield made
    for r in made:
        r.close()


def play(
    made: list[TrajectoryReplay], peer: SimPeer, *files: str, **kw: object
) -> TrajectoryReplay:
    structure = load(files[0], files[1:], guess_bonds=bool(kw.pop("guess_bonds", True)))
    r = TrajectoryReplay(structure, peer.ws_url, "secret", **kw)  # type: ignore[arg-type]
    made.append(r)
    return r.start()


def test_psf_dcd_streams_all_frames_in_order(
    no_leaked_threads: None, peer: SimPeer, replays: list[TrajectoryReplay]
) -> None:
    r = play(replays, peer, PSF, DCD, fps=2000, exit_at_end=True)
    assert r.wait(60)
    frames = peer.wait_frames(98)
    assert [f.step for f in frames] == list(range(98))
    (topology,) = peer.topologies
    assert topology.n_atoms == 3341 and topology.bonds.shape[0] > 3000  # PSF bonds
    u = load(PSF, [DCD]).universe  # load() silences the DCD reader's deprecation notice
    for i in (0, 57, 97):
        np.testing.assert_allclose(frames[i].positions.to_numpy(), u.trajectory[i].positions)
        assert frames[i].time_ps == pytest.approx(u.trajectory[i].time)
    assert frames[0].box is None  # this DCD has no unit cell
    replays.clear()
    r.close()


def test_gro_xtc_streams_all_frames_in_order(
    peer: SimPeer, replays: list[TrajectoryReplay]
) -> None:
    """Every frame of the trajectory reaches the server, in order, with its positions, box and
    time exactly: the replay is lossless (a frame waits for room instead of being replaced), so
    how fast either side runs changes only when the frames arrive. It stays at the end instead
    of exiting, so no flush deadline decides what gets out; the timeout only catches a hang."""
    u = load(GRO, [XTC], guess_bonds=False).universe
    n = len(u.trajectory)
    r = play(replays, peer, GRO, XTC, fps=200, guess_bonds=False)
    assert r.connection.lossless
    frames = peer.wait_frames(n, timeout=HANG_S)
    assert [f.step for f in frames] == list(range(n))
    assert r.connection.stats.frames_dropped == 0
    assert peer.topologies[0].n_atoms == 47681
    for frame, ts in zip(frames, u.trajectory, strict=True):
        np.testing.assert_array_equal(frame.positions.to_numpy(), ts.positions)
        box = frame.box
        assert box is not None  # a triclinic (rhombic dodecahedron) cell, as rows
        np.testing.assert_array_equal(
            box.to_numpy(), np.asarray(ts.triclinic_dimensions, dtype=np.float32)
        )
        assert frame.time_ps == pytest.approx(ts.time)


def test_steering_that_arrives_right_after_a_poll_is_applied(
    peer: SimPeer, replays: list[TrajectoryReplay]
) -> None:
    """A paused replay sleeps until steering wakes it. A message that lands between its poll
    of the steering queue and its going to sleep must still wake it: here a `resume` is
    delivered just after the replay's first poll, through the connection's own path."""
    structure = load(PSF, [DCD])
    r = TrajectoryReplay(structure, peer.ws_url, "secret", fps=50, start_paused=True)
    replays.append(r)
    connection = r.connection
    delivered = False
    real_poll = connection.poll_steering

    def poll_then_deliver() -> list[object]:
        nonlocal delivered
        out = real_poll()
        # once connected nothing else wakes a paused replay: only this message can
        if not delivered and connection.connected:
            delivered = True
            connection._dispatch(Control(action="resume", seq=10_000), 0)
        return out  # type: ignore[return-value]

    connection.poll_steering = poll_then_deliver  # type: ignore[method-assign]
    r.start()
    assert connection.wait_connected(10)
    frames = peer.wait_frames(3, timeout=10)
    assert [f.step for f in frames[:3]] == [0, 1, 2]


def test_seek_step_speed_loop_and_stop(peer: SimPeer, replays: list[TrajectoryReplay]) -> None:
    r = play(replays, peer, PSF, DCD, fps=50, start_paused=True)
    assert r.connection.wait_connected(10)
    (engine,) = peer.wait_for(lambda: peer.of_type(EngineInfo))
    assert engine.playback == Playback(speed=1.0, loop=False)  # as it starts
    # a paused start says so and shows its first frame, then waits
    (paused,) = peer.wait_for(lambda: [e for e in peer.of_type(Event) if e.code == "paused"])
    assert paused.step == 0
    peer.wait_for(lambda: [f.step for f in peer.frames] == [0])
    time.sleep(0.3)
    assert [f.step for f in peer.frames] == [0]
    seq = peer.send(Control(action="seek", frame=40))
    ack = peer.wait_ack(seq)
    assert ack.ok and ack.applied == {"action": "seek", "frame": 40}
    peer.wait_for(lambda: [f.step for f in peer.frames] == [0, 40])
    seq = peer.send(Control(action="step", n_steps=2))
    peer.wait_for(lambda: [f.step for f in peer.frames] == [0, 40, 41, 42])
    assert peer.wait_ack(seq).step in (40, 41, 42)
    bad = peer.wait_ack(peer.send(Control(action="seek", frame=98)))
    assert not bad.ok and "out of range" in bad.detail
    peer.send(Control(action="loop", loop=True))
    peer.send(Control(action="speed", speed=20.0))
    peer.send(SimParams(frame_interval=5))
    peer.send(Control(action="resume"))
    # after the last frame it starts again at 0: a wrap-around shows up as a decrease
    peer.wait_for(
        lambda: any(b.step < a.step for a, b in itertools.pairwise(peer.frames)), timeout=30
    )
    steps = [f.step for f in peer.frames]
    wrap = next(i for i in range(1, len(steps)) if steps[i] < steps[i - 1])
    assert steps[wrap] == 0 and all(b - a == 5 for a, b in itertools.pairwise(steps[4:wrap]))
    refused = peer.wait_ack(peer.send(SimParams(temperature_K=300.0)))
    assert not refused.ok and "temperature_K" in refused.detail
    stop = peer.send(Control(action="stop"))
    assert r.wait(10)
    assert any(a.ref == stop for a in peer.of_type(type(refused)))


def test_the_end_without_loop_pauses_there_and_resume_plays_again(
    peer: SimPeer, replays: list[TrajectoryReplay]
) -> None:
    """A replay at its last frame is not playing: it pauses there and says so (the dashboard
    then shows it paused, not running at a rate), and resume starts it again from frame 0."""
    r = play(replays, peer, PSF, DCD, fps=2000)
    (ended,) = peer.wait_for(
        lambda: [e for e in peer.of_type(Event) if e.code == "paused"], timeout=60
    )
    assert ended.step == 97 and "last frame" in ended.message
    # the event may overtake the last frame on its way (events and frames queue apart)
    assert [f.step for f in peer.wait_frames(98)] == list(range(98))
    assert r.paused
    time.sleep(0.3)
    assert len(peer.frames) == 98  # waits at the end
    ack = peer.wait_ack(peer.send(Control(action="resume")))
    assert ack.ok
    peer.wait_for(lambda: len(peer.frames) > 98, timeout=30)
    assert peer.frames[98].step == 0


def test_a_reconnect_declares_the_playback_as_it_is_now(
    peer: SimPeer, replays: list[TrajectoryReplay]
) -> None:
    """The engine a replay declares again after a reconnect carries the speed and loop it
    plays at: it had carried those it started with, so a restarted server (and every
    dashboard) showed 1x and no loop while it played at 4x, looping."""
    r = play(replays, peer, PSF, DCD, fps=50, start_paused=True)
    assert r.connection.wait_connected(10)
    peer.wait_for(lambda: peer.of_type(EngineInfo))
    assert peer.wait_ack(peer.send(Control(action="speed", speed=4.0))).ok
    assert peer.wait_ack(peer.send(Control(action="loop", loop=True))).ok
    peer.restart()
    (engine,) = peer.wait_for(lambda: peer.of_type(EngineInfo), timeout=30)
    assert engine.playback == Playback(speed=4.0, loop=True)


def test_multimodel_pdb_and_mmcif_with_guessed_bonds(
    peer: SimPeer, replays: list[TrajectoryReplay]
) -> None:
    r = play(replays, peer, PDB_multiframe, fps=500, exit_at_end=True)
    assert r.wait(30)
    assert [f.step for f in peer.wait_frames(24)] == list(range(24))
    assert peer.topologies[0].bonds.shape[0] > 380  # CONECT records plus guessed bonds
    r2 = play(replays, peer, os.path.join(MMCIF, "1YJP.cif"), fps=10, exit_at_end=True)
    assert r2.wait(30)
    cif = peer.topologies[-1]
    assert cif.n_atoms == 66 and cif.bonds.shape[0] >= 55  # none in the file: all guessed


def test_cli_plays_to_the_end(peer: SimPeer) -> None:
    argv = [PSF, DCD, "--fps", "2000", "--exit-at-end", "--url", peer.ws_url, "--token", "secret"]
    assert replay.main([*argv, "--session", "cli"]) == 0
    assert [f.step for f in peer.wait_frames(98)] == list(range(98))
    assert peer.hellos[0].session == "cli" and peer.hellos[0].client == "scalesteer-replay"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["/no/such/file.pdb"], "no such file"),
        ([PSF, XTC], "same number of atoms"),
        ([PSF], "has no coordinates"),
        ([PSF, DCD, "--fps", "0"], "--fps must be positive"),
        ([PSF, DCD, "--url", "ftp://x"], "ws://HOST:PORT"),
        ([__file__], "unsupported structure format 'py'"),
    ],
)
def test_cli_bad_input_is_a_clear_error(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert replay.main(argv) == 2
    err = capsys.readouterr().err
    assert "scalesteer replay: error:" in err and message in err


def test_cli_bad_token_exits_with_the_servers_reason(
    peer: SimPeer, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [PDB_multiframe, "--exit-at-end", "--url", peer.ws_url, "--token", "wrong"]
    assert replay.main(argv) == 1
    assert "unauthorized" in capsys.readouterr().err


def test_cli_against_no_server_says_each_retry_and_gives_up(
    capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    import socket
    import time

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started = time.monotonic()
    code = replay.main([PDB_multiframe, "--url", f"ws://127.0.0.1:{port}/ws/sim", "--retry", "1.5"])
    assert code == 1 and time.monotonic() - started < 15
    assert "retry 1 in" in caplog.text and "giving up" in caplog.text
    assert "could not reach" in capsys.readouterr().err
    assert replay.build_parser().parse_args([PSF, "--retry", "forever"]).retry is None
