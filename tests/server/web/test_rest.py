"""REST: one-off renders, batch jobs over a real trajectory, sessions, health, metrics, the log."""

from __future__ import annotations

import io
import json
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

import protocol as p
from tests.conftest import LiveServer, make_settings, start_server
from tests.server.peers import Peer, frame, molecule

pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import DCD, GRO, PSF, PDB_small

AUTH = {"Authorization": "Bearer test-token"}


def client(server: LiveServer) -> httpx.Client:
    return httpx.Client(base_url=server.url, timeout=120)


def test_render_uploaded_structure_as_png(live_server: LiveServer) -> None:
    with client(live_server) as c, open(PDB_small, "rb") as fh:
        r = c.post(
            "/api/render",
            headers=AUTH,
            files={"file": ("adk.pdb", fh)},
            data={"width": "96", "height": "72", "params": json.dumps({"sigma_A": 2.0})},
        )
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    img = Image.open(io.BytesIO(r.content))
    assert img.format == "PNG" and img.size == (96, 72)
    assert max(img.convert("L").getextrema()) > 60


def test_render_rejects_bad_input_with_a_reason(live_server: LiveServer) -> None:
    with client(live_server) as c:
        r = c.post(
            "/api/render", headers=AUTH, files={"file": ("junk.pdb", b"\x00\x01garbage" * 10)}
        )
        assert r.status_code == 422 and "junk.pdb" in r.json()["detail"]
        r = c.post("/api/render", headers=AUTH, files={"file": ("model.exe", b"MZ....")})
        assert r.status_code == 422 and "unsupported structure format" in r.json()["detail"]
        r = c.post("/api/render", headers=AUTH, data={"dataset": "../../etc/passwd"})
        assert r.status_code == 404
        with open(PDB_small, "rb") as fh:
            r = c.post(
                "/api/render",
                headers=AUTH,
                files={"file": ("a.pdb", fh)},
                data={"params": '{"sigma_A": -1}'},
            )
        assert r.status_code == 422 and "params.sigma_A" in r.json()["detail"]
        r = c.post("/api/render", files={"file": ("a.pdb", b"x")})
        assert r.status_code == 401
        r = c.post("/api/render", headers=AUTH, files={"file": ("..", b"ATOM")})
        assert r.status_code == 422 and "file name" in r.json()["detail"]


def test_upload_size_limit(tmp_path: Path) -> None:
    server = start_server(make_settings(tmp_path, max_upload_bytes=10_000))
    try:
        with client(server) as c:
            r = c.post("/api/render", headers=AUTH, files={"file": ("big.pdb", b"ATOM" * 20_000)})
            assert r.status_code == 413 and "big.pdb: upload exceeds" in r.json()["detail"]
            # a body past the files' limit and the form's allowance: refused from its length,
            # in JSON as every refusal of the API, naming both
            big = {"file": ("big.pdb", b"ATOM" * 300_000)}
            r = c.post("/api/render", headers=AUTH, files=big)
        assert r.status_code == 413
        detail = r.json()["detail"]
        assert "(0.00953674 MiB of files, max_upload_bytes, and 1 MiB for the form's" in detail
    finally:
        server.stop()


def adk_job(c: httpx.Client, **data: str) -> str:
    """Submit a job of adenylate kinase's 98-frame DCD with the form fields `data`; its id."""
    with open(PSF, "rb") as top, open(DCD, "rb") as traj:
        r = c.post(
            "/api/jobs",
            headers=AUTH,
            files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
            data=data,
        )
    assert r.status_code == 202, r.text
    return str(r.json()["id"])


def wait_job(c: httpx.Client, job_id: str, timeout: float = 240) -> tuple[dict, list[int]]:
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = c.get(f"/api/jobs/{job_id}", headers=AUTH).json()
        seen.append(info["progress"]["done"])
        if info["state"] in ("done", "failed", "cancelled", "expired"):
            return info, seen
        time.sleep(0.2)
    raise TimeoutError(job_id)


def test_trajectory_job_to_zip_and_mp4(live_server: LiveServer) -> None:
    with client(live_server) as c:
        with open(PSF, "rb") as top, open(DCD, "rb") as traj:
            r = c.post(
                "/api/jobs",
                headers=AUTH,
                files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                data={"width": "48", "height": "36", "output": "zip"},
            )
        assert r.status_code == 202, r.text
        info, seen = wait_job(c, r.json()["id"])
        assert info["state"] == "done", info
        assert info["progress"] == {"done": 98, "total": 98}
        assert seen == sorted(seen) and seen[-1] == 98
        z = zipfile.ZipFile(io.BytesIO(c.get(info["result"], headers=AUTH).content))
        names = z.namelist()
        assert len(names) == 98 and names[0] == "frame_000000.png"
        assert Image.open(io.BytesIO(z.read(names[-1]))).size == (48, 36)

        with open(PSF, "rb") as top, open(DCD, "rb") as traj:
            r = c.post(
                "/api/jobs",
                headers=AUTH,
                files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                data={
                    "width": "48",
                    "height": "36",
                    "output": "mp4",
                    "start": "10",
                    "stop": "40",
                    "stride": "3",
                },
            )
        info, _ = wait_job(c, r.json()["id"])
        assert info["state"] == "done", info
        movie = c.get(info["result"], headers=AUTH)
        assert movie.headers["content-type"] == "video/mp4"
    import av

    with av.open(io.BytesIO(movie.content)) as container:
        frames = sum(1 for _ in container.decode(video=0))
    assert frames == 10


def test_a_job_takes_a_trajectory_in_several_files(live_server: LiveServer) -> None:
    """`trajectory` given once per file (as the API and the Python client take a list): the
    files are read one after another. The form check had refused the field's second use."""
    dcd = Path(DCD).read_bytes()
    with client(live_server) as c:
        r = c.post(
            "/api/jobs",
            headers=AUTH,
            files=[
                ("topology", ("adk.psf", Path(PSF).read_bytes())),
                ("trajectory", ("part1.dcd", dcd)),
                ("trajectory", ("part2.dcd", dcd)),
            ],
            data={"width": "32", "height": "24", "output": "zip", "stride": "49"},
        )
        assert r.status_code == 202, r.text
        info, _ = wait_job(c, r.json()["id"])
        assert info["state"] == "done", info
        assert info["progress"] == {"done": 4, "total": 4}  # 196 frames, every 49th
        r = c.post(
            "/api/jobs",
            headers=AUTH,
            files=[("topology", ("adk.psf", Path(PSF).read_bytes()))],
            data={"width": "32", "height": ["24", "30"]},
        )
        assert r.status_code == 422 and "'height': form field given more than once" in r.text


def test_cancelling_a_job_never_deletes_what_it_made(live_server: LiveServer) -> None:
    """`POST /api/jobs/{id}/cancel` stops a job still running (its `ending` says so until it
    ends) and leaves one that has ended as it is: DELETE there deletes the output, so a stop
    that raced the job's last frame had lost the finished result."""
    with client(live_server) as c:
        finished = adk_job(c, width="32", height="24", output="zip", stride="49")
        info, _ = wait_job(c, finished)
        assert info["state"] == "done" and info["ending"] is None
        for _ in range(2):  # and again: still nothing deleted
            r = c.post(f"/api/jobs/{finished}/cancel", headers=AUTH)
            assert r.status_code == 200 and r.json()["state"] == "done", r.text
        assert c.get(f"/api/jobs/{finished}/result", headers=AUTH).status_code == 200

        running = adk_job(c, width="160", height="24", output="zip")  # 98 frames: still running
        r = c.post(f"/api/jobs/{running}/cancel", headers=AUTH)
        assert r.status_code == 200, r.text
        assert r.json()["state"] == "cancelled" or r.json()["ending"] == "cancelling", r.json()
        info, _ = wait_job(c, running)
        assert info["state"] == "cancelled" and info["ending"] is None
        assert c.post("/api/jobs/nope/cancel", headers=AUTH).status_code == 404


def test_a_job_over_a_trajectory_cut_short_says_so(live_server: LiveServer) -> None:
    """A DCD cut inside its second frame rendered as a 1-frame job, done and whole."""
    with client(live_server) as c:
        r = c.post(
            "/api/jobs",
            headers=AUTH,
            files=[
                ("topology", ("adk.psf", Path(PSF).read_bytes())),
                ("trajectory", ("adk.dcd", Path(DCD).read_bytes()[:50_000])),
            ],
            data={"width": "32", "height": "24", "output": "zip"},
        )
        assert r.status_code == 202, r.text
        info, _ = wait_job(c, r.json()["id"])
        assert info["state"] == "done" and info["progress"]["total"] == 1, info
        assert info["partial"] is True and "adk.dcd ends inside a frame" in info["warning"]


def test_a_queued_job_cancelled_takes_its_uploads_with_it(tmp_path: Path) -> None:
    """A job cancelled before it started kept its upload folder (gigabytes, for a long
    trajectory) until the server restarted."""
    server = start_server(make_settings(tmp_path, max_running_jobs=1))
    try:
        uploads = server.settings.state_dir / "uploads"
        with httpx.Client(base_url=server.url, timeout=120) as c:
            # the first runs, the second waits
            ids = [adk_job(c, width="160", height="120") for _ in range(2)]
            assert c.get(f"/api/jobs/{ids[1]}", headers=AUTH).json()["state"] == "queued"
            assert len(list(uploads.iterdir())) == 2
            r = c.post(f"/api/jobs/{ids[1]}/cancel", headers=AUTH)
            assert r.json()["state"] == "cancelled", r.text
            assert len(list(uploads.iterdir())) == 1  # the running job's alone
            c.post(f"/api/jobs/{ids[0]}/cancel", headers=AUTH)
    finally:
        server.stop()


def test_job_cancel_and_bad_job_input(live_server: LiveServer) -> None:
    with client(live_server) as c:
        with open(PSF, "rb") as top, open(DCD, "rb") as traj:
            r = c.post(
                "/api/jobs",
                headers=AUTH,
                files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                data={"width": "160", "height": "120"},
            )
        job_id = r.json()["id"]
        assert c.delete(f"/api/jobs/{job_id}", headers=AUTH).status_code == 200
        info, _ = wait_job(c, job_id)
        assert info["state"] == "cancelled" and info["progress"]["done"] < 98
        assert c.get(f"/api/jobs/{job_id}/result", headers=AUTH).status_code == 409
        with open(GRO, "rb") as top, open(DCD, "rb") as traj:
            r = c.post(
                "/api/jobs",
                headers=AUTH,
                files=[("topology", ("big.gro", top)), ("trajectory", ("adk.dcd", traj))],
                data={"width": "32", "height": "24"},
            )
        assert r.status_code == 422, r.text
        assert "atoms" in r.json()["detail"], r.json()
        r = c.post("/api/jobs", headers=AUTH, files=[("topology", ("t.pdb", b"junk\n" * 5))])
        assert r.status_code == 422 and "t.pdb" in r.json()["detail"]
        # frame ranges that hold no frame are refused at once, not as a job that fails later
        for data, said in (
            ({"start": "50", "stop": "10"}, "stop 10 must be after start 50"),
            ({"start": "98"}, "the trajectory has 98"),
        ):
            with open(PSF, "rb") as top, open(DCD, "rb") as traj:
                r = c.post(
                    "/api/jobs",
                    headers=AUTH,
                    files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                    data={"width": "32", "height": "24", **data},
                )
            assert r.status_code == 422 and said in r.json()["detail"], r.text
        r = c.post(
            "/api/jobs", headers={"Authorization": "Bearer viewer-token"}, data={"dataset": "x"}
        )
        assert r.status_code == 403
        assert c.get("/api/jobs/nope", headers=AUTH).status_code == 404


def test_sessions_health_metrics_and_log_survive_restart(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "logged")
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 0))
    steerer = Peer(live_server.view_url, "steerer", live_server.token, "logged")
    steerer.send(p.SetRenderParams(params={"sigma_A": 2.5}))
    steerer.send(p.Control(action="pause"))
    fwd = sim.expect(p.Control)
    sim.send(p.ParamsAck(ref=fwd.seq, step=40, applied={"action": "pause"}))
    steerer.expect(p.ParamsAck)
    steerer.expect(p.Image, 60)
    with client(live_server) as c:
        assert c.get("/healthz").json()["status"] == "ok"
        listed = {s["id"]: s for s in c.get("/api/sessions", headers=AUTH).json()}
        assert listed["logged"]["n_atoms"] == 12
        assert c.get("/api/sessions/logged", headers=AUTH).json()["status"]["state"] == "paused"
        assert c.get("/api/sessions/missing", headers=AUTH).status_code == 404
        metrics = c.get("/metrics").text
        assert (
            "scalesteer_frames_rendered_total" in metrics
            and "scalesteer_render_ms_bucket" in metrics
        )
        before = c.get("/api/sessions/logged/log", headers=AUTH).json()
    assert [e["event"] for e in before] == ["render_params", "control", "applied"]
    sim.close()
    steerer.close()
    restarted = live_server.restart()
    try:
        with client(restarted) as c:
            after = c.get("/api/sessions/logged/log", headers=AUTH).json()
        assert after == before
        # ids go on where the last run stopped: a `ref` names one action for the log's life
        sim = Peer(restarted.ws_url, "simulation", restarted.token, "logged")
        sim.send(topo)
        sim.send(frame(pos, 0))
        steerer = Peer(restarted.view_url, "steerer", restarted.token, "logged")
        steerer.send(p.SetRenderParams(params={"sigma_A": 3.0}))
        steerer.expect(p.Image, 60)
        with client(restarted) as c:
            again = c.get("/api/sessions/logged/log", headers=AUTH).json()
        ids = [e["id"] for e in again]
        assert len(again) == len(before) + 1 and ids == sorted(set(ids))
        sim.close()
        steerer.close()
    finally:
        restarted.stop()


def test_finished_job_outputs_are_reaped_by_age_and_disk_cap(tmp_path: Path) -> None:
    """Outputs of finished jobs do not accumulate: past the disk cap the oldest go first, and
    none outlives the retention time; a reaped job says why its result is gone."""
    server = start_server(make_settings(tmp_path, job_max_bytes=50_000, job_retention_s=3600))
    jobs_dir = tmp_path / "state" / "jobs"
    try:
        with client(server) as c:
            ids = []
            for _ in range(3):
                with open(PSF, "rb") as top, open(DCD, "rb") as traj:
                    r = c.post(
                        "/api/jobs",
                        headers=AUTH,
                        files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                        data={"width": "40", "height": "30", "stop": "12", "output": "zip"},
                    )
                assert r.status_code == 202, r.text
                info, _ = wait_job(c, r.json()["id"])
                assert info["state"] == "done", info
                ids.append(info["id"])
            sizes = sorted(f.stat().st_size for f in jobs_dir.glob("*.zip"))
            assert sum(sizes) <= 50_000 and len(sizes) == 2
            first = c.get(f"/api/jobs/{ids[0]}", headers=AUTH).json()
            assert first["state"] == "expired" and "exceeded" in first["error"]
            assert c.get(f"/api/jobs/{ids[0]}/result", headers=AUTH).status_code == 409
            assert c.get(f"/api/jobs/{ids[-1]}/result", headers=AUTH).status_code == 200
        jobs = server.app_state.jobs
        jobs.reap(now=time.time() + 7200)  # two hours later: past the retention time
        assert list(jobs_dir.glob("*.zip")) == []
        assert all(j.state.value == "expired" for j in jobs.jobs.values())
    finally:
        server.stop()


def test_a_trajectory_job_smooths_over_time(live_server: LiveServer) -> None:
    """The temporal settings reach batch jobs: a warped-smoothed movie of adk differs from the
    raw one frame by frame, and a window the protocol does not allow is refused by name."""
    frames = {}
    with client(live_server) as c:
        for name, params in (
            ("raw", {}),
            ("smooth", {"time_smoothing": "warped", "tau_frames": 2.0, "time_window": 9}),
            ("bad", {"time_smoothing": "warped", "time_window": 65}),
        ):
            with open(PSF, "rb") as top, open(DCD, "rb") as traj:
                r = c.post(
                    "/api/jobs",
                    headers=AUTH,
                    files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                    data={
                        "width": "48",
                        "height": "36",
                        "output": "zip",
                        "start": "20",
                        "stop": "26",
                        "params": json.dumps(params),
                    },
                )
            if name == "bad":
                assert r.status_code == 422 and "time_window" in r.text
                continue
            assert r.status_code == 202, r.text
            info, _ = wait_job(c, r.json()["id"])
            assert info["state"] == "done", info
            z = zipfile.ZipFile(io.BytesIO(c.get(info["result"], headers=AUTH).content))
            frames[name] = [
                np.asarray(Image.open(io.BytesIO(z.read(n))), dtype=np.int32)
                for n in sorted(z.namelist())
            ]
    assert len(frames["raw"]) == len(frames["smooth"]) == 6
    for raw, smooth in zip(frames["raw"], frames["smooth"], strict=True):
        assert np.abs(raw - smooth).mean() > 0.2
