"""Recording a steered OpenMM run and replaying it with its steering in sync, on a real server:
the frames the session received are the frames recorded (within XTC's precision), the replay
plays every one of them, and each steering action is a mark at the frame it took effect."""

from __future__ import annotations

import io
import os
import signal
import time
import warnings
from pathlib import Path
from typing import Any

import httpx
import MDAnalysis as mda
import numpy as np
import pytest

import protocol as p
from server.pipeline.recordings import FILES
from tests.browser.simulation import OpenMMSimulation
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame, molecule
from tests.server.processes import TOKEN, VIEWER_TOKEN, ServerProcess

AUTH = {"Authorization": "Bearer test-token"}
XTC_TOLERANCE_A = 0.0051
"""XTC stores nm on a 0.001 nm grid: a coordinate is within 0.005 A of what was sent."""


def read_xtc(folder: Path, n_atoms: int) -> tuple[list[int], np.ndarray]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(str(folder / "topology.pdb"), str(folder / "frames.xtc"))
        assert u.atoms.n_atoms == n_atoms
        steps = [int(ts.data["step"]) for ts in u.trajectory]
        return steps, np.stack([ts.positions.copy() for ts in u.trajectory])


def wait_for(condition: Any, what: str, timeout: float = 60.0) -> Any:
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)
    return value


def wait_for_movie(client: httpx.Client, job_id: str) -> list[np.ndarray]:
    import av

    done = wait_for(
        lambda: client.get(f"/api/jobs/{job_id}").json()["state"] in ("done", "failed"),
        "the movie job",
        timeout=180,
    )
    assert done
    info = client.get(f"/api/jobs/{job_id}").json()
    assert info["state"] == "done", info
    movie = client.get(f"/api/jobs/{job_id}/result")
    with av.open(io.BytesIO(movie.content)) as container:
        return [f.to_ndarray(format="rgb24").astype(np.float64) for f in container.decode(video=0)]


def test_a_steered_openmm_run_is_recorded_and_replayed_with_its_marks(
    live_server: LiveServer,
) -> None:
    sim = OpenMMSimulation(live_server.ws_url, live_server.token).start()
    client = httpx.Client(base_url=live_server.url, headers=AUTH, timeout=30)
    steerer = Peer(live_server.view_url, "steerer", live_server.token)
    try:
        live = live_server.app_state.sessions.get("default")
        seen: list[tuple[int, np.ndarray]] = []
        live.frame_sinks.append(lambda step, t, pos, box: seen.append((step, pos.copy())))
        r = client.post("/api/sessions/default/recordings", json={})
        assert r.status_code == 201, r.text
        rec_id = r.json()["id"]
        assert client.post("/api/sessions/default/recordings").status_code == 409  # one at once
        wait_for(lambda: len(seen) > 5, "frames")
        steerer.send(p.SimParams(temperature_K=360.0))
        ack = steerer.expect(p.ParamsAck)
        assert ack.ok, ack.detail
        wait_for(lambda: len(seen) > 12, "frames after the temperature change")
        steerer.send(p.Pull(atom=3, target=(5.0, 5.0, 5.0), spring_k=2.0, max_force=20.0))
        wait_for(lambda: len(seen) > 20, "frames while pulling")
        steerer.send(p.Pull(atom=3, release=True))
        wait_for(lambda: len(seen) > 26, "frames after the release")
        running = client.get(f"/api/recordings/{rec_id}").json()
        assert running["state"] == "recording" and running["bytes"] > 0  # disk use, live
        r = client.post(f"/api/recordings/{rec_id}/stop")
        assert r.status_code == 200, r.text
        rec = r.json()
    finally:
        sim.stop()
        steerer.close()
    assert rec["state"] == "finished"
    folder = live_server.settings.state_dir / "recordings" / rec_id
    n_atoms = live.topology.n_atoms
    steps, positions = read_xtc(folder, n_atoms)
    assert len(steps) == rec["frames"] >= 20
    # every frame the session received between the first and last recorded one, in order
    by_step = [(s, x) for s, x in seen if steps[0] <= s <= steps[-1]]
    assert [s for s, _ in by_step] == steps
    worst = max(float(np.abs(x - positions[i]).max()) for i, (_, x) in enumerate(by_step))
    assert worst <= XTC_TOLERANCE_A
    # the marks: the temperature change at the step it was applied, the pull and its release
    marks = rec["marks"]
    kinds = [m["kind"] for m in marks]
    assert kinds == ["sim_params", "pull", "release"], marks
    temperature = marks[0]
    assert temperature["step"] == ack.step and "temperature_K 360.0" in temperature["text"]
    for m in marks:
        assert steps[m["frame"]] >= m["step"] and (
            m["frame"] == 0 or steps[m["frame"] - 1] < m["step"]
        )
    assert marks[1]["atom"] == 3
    listed = client.get("/api/recordings").json()
    assert [x["id"] for x in listed] == [rec_id]
    assert client.get(f"/api/recordings/{rec_id}/files/steering.jsonl").status_code == 200
    assert client.get(f"/api/recordings/{rec_id}/files/../../x").status_code == 404
    viewer = httpx.get(
        f"{live_server.url}/api/recordings", headers={"Authorization": "Bearer viewer-token"}
    )
    assert viewer.status_code == 403  # scoped like jobs: the server token

    movies = {}
    for overlay in (True, False):
        r = client.post(
            f"/api/recordings/{rec_id}/movie",
            json={"width": 96, "height": 72, "fps": 10, "overlay": overlay, "caption_s": 0.1},
        )
        assert r.status_code == 202, r.text
        movies[overlay] = wait_for_movie(client, r.json()["id"])
    assert len(movies[True]) == len(movies[False]) == len(steps)  # every recorded frame
    pull_frame = marks[1]["frame"]
    drawn = np.abs(movies[True][pull_frame] - movies[False][pull_frame]).mean()
    # before the first action nothing is drawn: the movies differ by encoding noise only
    noise = np.abs(movies[True][0] - movies[False][0]).mean()
    print(f"overlay difference {drawn:.2f}, encoding noise {noise:.2f}")
    assert marks[0]["frame"] > 0 and drawn > 3 * noise + 0.3  # the pull arrow and caption
    # a recording being rendered to a movie is not deleted under it (the job failed halfway,
    # "no such file: topology.pdb"): 409 naming the job, until it ends
    r = client.post(f"/api/recordings/{rec_id}/movie", json={"width": 1280, "height": 960})
    assert r.status_code == 202, r.text
    slow = r.json()["id"]
    refused = client.delete(f"/api/recordings/{rec_id}")
    assert refused.status_code == 409 and slow in refused.json()["detail"], refused.text
    assert client.post(f"/api/jobs/{slow}/cancel").status_code == 200
    wait_for(lambda: client.get(f"/api/jobs/{slow}").json()["state"] == "cancelled", "the cancel")
    assert client.get(f"/api/recordings/{rec_id}").status_code == 200  # kept whole
    # while its deletion is under way (it awaits the recording's last writes), nothing that
    # reads its files starts: a movie asked for then had been accepted and failed halfway
    held = live_server.app_state.recordings.get(rec_id)
    held.deleting = True
    try:
        for path in (f"/api/recordings/{rec_id}/movie", f"/api/recordings/{rec_id}/replay"):
            r = client.post(path)
            assert r.status_code == 409 and "being deleted" in r.text, (path, r.text)
        assert client.delete(f"/api/recordings/{rec_id}").status_code == 409
    finally:
        held.deleting = False

    # replayed: the same number of frames, the recorded positions, the marks on the timeline
    r = client.post(f"/api/recordings/{rec_id}/replay", params={"fps": 60})
    assert r.status_code == 201, r.text
    name = r.json()["session"]
    replayed: list[np.ndarray] = []

    def hooked() -> bool:
        session = live_server.app_state.sessions.get(name)
        if session is None:
            return False
        if not session.frame_sinks:
            session.frame_sinks.append(lambda step, t, pos, box: replayed.append(pos.copy()))
        return True

    wait_for(hooked, "the replay session")
    described = client.get(f"/api/replays/{name}").json()
    assert described["recording"] == rec_id and described["marks"] == marks
    engine = wait_for(
        lambda: live_server.app_state.sessions.get(name).engine, "the replay's engine"
    )
    assert engine.kind == "replay" and engine.n_frames == len(steps)
    # from the start again (it may have played already): every recorded frame, in order
    player = Peer(live_server.view_url, "steerer", live_server.token, name)
    try:
        wait_for(lambda: len(replayed) > 0, "a replayed frame")
        player.send(p.Control(action="pause"))
        assert player.expect(p.ParamsAck).ok
        time.sleep(0.5)
        replayed.clear()
        player.send(p.Control(action="seek", frame=0))
        assert player.expect(p.ParamsAck).ok
        player.send(p.Control(action="resume"))
        assert player.expect(p.ParamsAck).ok
        wait_for(lambda: len(replayed) >= len(steps), "the replay to play", timeout=90)
        time.sleep(0.5)
        # deleting the recording stops its replay, which had played on from the deleted files
        assert client.get(f"/api/replays/{name}").json()["running"]
        r = client.delete(f"/api/recordings/{rec_id}")
        assert r.status_code == 200 and r.json()["replays_stopped"] == [name], r.text
        assert not client.get(f"/api/replays/{name}").json()["running"]
    finally:
        player.close()
        client.delete(f"/api/replays/{name}")
        client.close()
    assert len(replayed) in (len(steps), len(steps) + 1)  # the seek shows frame 0 at once
    assert np.array_equal(np.stack(replayed[-len(steps) :]), positions)


def test_a_recording_survives_a_kill_of_the_server(tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    server = ServerProcess(state_dir)
    sim = OpenMMSimulation(f"ws://127.0.0.1:{server.port}/ws/sim", TOKEN).start()
    try:
        client = httpx.Client(base_url=server.url, headers=AUTH, timeout=30)
        r = client.post("/api/sessions/default/recordings", json={"stride": 2})
        assert r.status_code == 201, r.text
        rec_id = r.json()["id"]
        wait_for(lambda: client.get(f"/api/recordings/{rec_id}").json()["frames"] >= 6, "frames")
        server.process.send_signal(signal.SIGKILL)
        server.process.wait()
        client.close()
    finally:
        sim.stop()
    folder = state_dir / "recordings" / rec_id
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(str(folder / "topology.pdb"), str(folder / "frames.xtc"))
        frames = [ts.positions.copy() for ts in u.trajectory]
    assert len(frames) >= 6 and all(np.isfinite(f).all() for f in frames)
    steps = [int(ts.data["step"]) for ts in u.trajectory]
    assert steps == sorted(steps) and len(set(np.diff(steps))) == 1  # every second frame

    def leftovers() -> list[str]:  # beside the recording's files and MDAnalysis's offset caches
        return [n for n in os.listdir(folder) if n not in FILES and "_offsets." not in n]

    assert leftovers()  # the chunk being written when the server was killed

    again = ServerProcess(state_dir, port=server.port)
    try:
        got = httpx.get(f"{again.url}/api/recordings/{rec_id}", headers=AUTH).json()
        assert got["state"] == "interrupted" and got["frames"] == len(frames)
        assert not leftovers()  # a chunk file had stayed for good
    finally:
        again.stop()


@pytest.mark.parametrize("body", [{"stride": 0}, {"strid": 2}, {"max_bytes": 10}])
def test_bad_recording_requests_are_refused_by_name(live_server: LiveServer, body: dict) -> None:
    r = httpx.post(f"{live_server.url}/api/sessions/default/recordings", json=body, headers=AUTH)
    assert r.status_code == 422
    assert next(iter(body)) in r.text


def test_a_recording_ends_when_its_session_is_reaped(tmp_path: Path) -> None:
    from tests.conftest import make_settings, start_server

    server = start_server(make_settings(tmp_path, session_idle_s=0.4))
    try:
        sim = Peer(server.ws_url, "simulation", server.token, "brief")
        topo, pos = molecule(12)
        sim.send(topo)
        sim.send(frame(pos, 0))
        client = httpx.Client(base_url=server.url, headers=AUTH, timeout=30)
        wait_for(lambda: server.app_state.sessions.get("brief").topology is not None, "topology")
        rec_id = client.post("/api/sessions/brief/recordings").json()["id"]
        for step in range(1, 4):
            sim.send(frame(pos + np.float32(0.1 * step), step))
        wait_for(lambda: client.get(f"/api/recordings/{rec_id}").json()["frames"] >= 3, "frames")
        sim.close()  # nobody left: the session is reaped
        wait_for(lambda: server.app_state.sessions.get("brief") is None, "the reaper", 20)
        got = wait_for(
            lambda: (
                (r := client.get(f"/api/recordings/{rec_id}").json())["state"] != "recording" and r
            ),
            "the recording to end",
            20,
        )
        assert got["state"] == "finished" and got["frames"] >= 3
        folder = server.settings.state_dir / "recordings" / rec_id
        steps, positions = read_xtc(folder, 12)
        assert steps[:3] == [1, 2, 3] or steps[:4] == [0, 1, 2, 3]
        assert np.isfinite(positions).all()
        client.close()
    finally:
        server.stop()


def test_a_recording_faster_than_its_disk_holds_bounded_memory_and_says_what_it_skipped(
    tmp_path: Path,
) -> None:
    """An 80k-atom simulation at full speed took the server from 809 to 3,270 MB in 12 s while
    recording (the writer kept ~160 frames/s of ~300) and stopping took 12 s to drain. The
    frames waiting for the disk are now bounded (`recording_queue_bytes`, here less than one
    frame: one frame at a time); the others are skipped, counted, listed by step and announced
    to the session, and what was recorded is whole."""
    server = ServerProcess(tmp_path / "state", "--set", "recording_queue_bytes=65536")
    n, sent = 10_000, 120  # 120 KB a frame
    sim = Peer(server.ws_url, "simulation", TOKEN, "fast")
    viewer = Peer(server.view_url, "viewer", VIEWER_TOKEN, "fast")
    client = httpx.Client(base_url=server.url, headers=AUTH, timeout=60)
    try:
        topo, _helix = molecule(n)
        pos = np.random.default_rng(1).uniform(0, 60, (n, 3)).astype(np.float32)  # PDB's range
        sim.send(topo)
        sim.send(frame(pos, 0))
        wait_for(lambda: client.get("/api/sessions/fast").json()["status"]["step"] == 0, "a frame")
        r = client.post("/api/sessions/fast/recordings", json={})
        assert r.status_code == 201, r.text
        rec_id = r.json()["id"]
        for step in range(1, sent + 1):
            sim.send(frame(pos + np.float32(0.001 * step), step))
        wait_for(
            lambda: client.get(f"/api/recordings/{rec_id}").json()["received"] == sent,
            "every frame to reach the session",
        )
        rec = client.post(f"/api/recordings/{rec_id}/stop").json()
        event = viewer.expect(p.Event, 10, where=lambda m: m.code == "recording_skipped")
    finally:
        sim.close()
        viewer.close()
        client.close()
        server.stop()
    assert rec["skipped"] > 0 and rec["frames"] > 0, rec
    assert rec["frames"] + rec["skipped"] == rec["received"] == sent  # every frame accounted for
    assert "recording_queue_bytes" in rec["warning"] and rec["queue_bytes"] == 65536
    assert event.level == "warning" and rec_id in event.message
    steps, positions = read_xtc(server.state_dir / "recordings" / rec_id, n)
    assert len(steps) == rec["frames"] and np.isfinite(positions).all()
    skipped = {s for first, last, _ in rec["skipped_spans"] for s in range(first, last + 1)}
    assert sum(count for _, _, count in rec["skipped_spans"]) == rec["skipped"]
    assert skipped == set(range(1, sent + 1)) - set(steps)  # the gaps, exactly
    assert steps == sorted(steps)


def test_concurrent_starts_of_one_session_record_once(tmp_path: Path) -> None:
    """Eight concurrent recording starts of one session all got 201 (the docs promise 409)."""
    import asyncio
    import concurrent.futures

    server = ServerProcess(tmp_path / "state")
    sim = Peer(server.ws_url, "simulation", TOKEN, "raced")
    try:
        topo, pos = molecule(12)
        sim.send(topo)
        sim.send(frame(pos, 0))
        with httpx.Client(base_url=server.url, headers=AUTH, timeout=30) as client:
            wait_for(
                lambda: client.get("/api/sessions/raced").json().get("status", {}).get("step") == 0,
                "the session's first frame",
            )

        async def race() -> list[httpx.Response]:
            async with httpx.AsyncClient(base_url=server.url, headers=AUTH, timeout=30) as c:
                url = "/api/sessions/raced/recordings"
                return await asyncio.gather(*[c.post(url, json={}) for _ in range(8)])

        # on a thread of its own: the test's thread may hold a running loop (the browser tests')
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            responses = pool.submit(asyncio.run, race()).result()
        codes = sorted(r.status_code for r in responses)
        assert codes == [201] + [409] * 7, codes
        listed = httpx.get(f"{server.url}/api/recordings", headers=AUTH).json()
        assert [r["state"] for r in listed] == ["recording"]
    finally:
        sim.close()
        server.stop()


def test_a_movie_of_a_recording_cut_short_is_marked_partial(tmp_path: Path) -> None:
    """A movie job of a truncated recording was marked done with 66 of 132 frames and no
    warning; the job now says it is partial, and why."""
    server = ServerProcess(tmp_path / "state")
    sim = Peer(server.ws_url, "simulation", TOKEN, "cut")
    client = httpx.Client(base_url=server.url, headers=AUTH, timeout=60)
    try:
        topo, pos = molecule(30)
        sim.send(topo)
        sim.send(frame(pos, 0))
        wait_for(
            lambda: client.get("/api/sessions/cut").json().get("status", {}).get("step") == 0,
            "the session's first frame",
        )
        rec_id = client.post("/api/sessions/cut/recordings", json={}).json()["id"]
        for step in range(1, 41):
            sim.send(frame(pos + np.float32(0.01 * step), step))
        wait_for(lambda: client.get(f"/api/recordings/{rec_id}").json()["received"] == 40, "frames")
        rec = client.post(f"/api/recordings/{rec_id}/stop").json()
        assert rec["frames"] == 40 and rec["skipped"] == 0
        xtc = server.state_dir / "recordings" / rec_id / "frames.xtc"
        whole = xtc.read_bytes()
        xtc.write_bytes(whole[: len(whole) // 2])  # a disk that lost the file's second half
        kept = len(read_xtc(xtc.parent, 30)[0])
        assert 0 < kept < 40
        body = {"width": 32, "height": 24, "overlay": False}
        job = client.post(f"/api/recordings/{rec_id}/movie", json=body).json()
        info = wait_for(
            lambda: (
                (j := client.get(f"/api/jobs/{job['id']}").json())["state"] in ("done", "failed")
                and j
            ),
            "the movie",
        )
    finally:
        sim.close()
        client.close()
        server.stop()
    assert info["state"] == "done" and info["progress"]["done"] == kept
    assert info["partial"] is True
    assert f"{kept} readable frame(s) of the 40" in info["warning"], info["warning"]
