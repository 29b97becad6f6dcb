"""Batch jobs on Ray, on a local Ray cluster of two CPU workers: the same output as the
in-process path (PNG frames bit for bit), a worker killed mid-job changes nothing, cancel frees
the workers, a bad input fails the job with its reason, and /healthz names the workers."""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from server.supervisor import descendants
from tests.conftest import LiveServer, make_settings, start_server
from tests.server.processes import (
    LOOPBACK,
    ServerProcess,
    command_line,
    listening_sockets,
    running,
    wait_gone,
)

ray = pytest.importorskip("ray")
pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import DCD, PSF  # noqa: E402

AUTH = {"Authorization": "Bearer test-token"}


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[None]:
    """One local Ray instance with two CPU workers for the module's servers."""
    if not ray.is_initialized():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, namespace="scalesteer")
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def servers(
    tmp_path_factory: pytest.TempPathFactory, ray_cluster: None
) -> Iterator[tuple[LiveServer, LiveServer]]:
    """The same server twice: jobs on Ray, and jobs in its own process (one pair for the
    module: its Ray actors hold the cluster's two CPUs)."""
    tmp_path = tmp_path_factory.mktemp("ray")
    data = tmp_path / "data"
    data.mkdir()
    for src in (PSF, DCD):
        (data / Path(src).name).write_bytes(Path(src).read_bytes())
    on_ray = start_server(make_settings(tmp_path / "a", data_dir=data, batch_engine="ray"))
    local = start_server(make_settings(tmp_path / "b", data_dir=data))
    yield on_ray, local
    on_ray.stop()
    local.stop()


def submit(server: LiveServer, **fields: str) -> str:
    data = {"dataset": Path(PSF).name, "trajectory_dataset": Path(DCD).name,
            "width": "64", "height": "48", "output": "zip", **fields}  # fmt: skip
    r = httpx.post(f"{server.url}/api/jobs", headers=AUTH, data=data, timeout=30)
    assert r.status_code == 202, r.text
    return str(r.json()["id"])


def wait(server: LiveServer, job: str, until: tuple[str, ...], timeout: float = 90) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        info = httpx.get(f"{server.url}/api/jobs/{job}", headers=AUTH, timeout=10).json()
        if info["state"] in until:
            return dict(info)
        assert time.monotonic() < deadline, info
        time.sleep(0.1)


def frames(server: LiveServer, job: str) -> dict[str, bytes]:
    body = httpx.get(f"{server.url}/api/jobs/{job}/result", headers=AUTH, timeout=30).content
    z = zipfile.ZipFile(io.BytesIO(body))
    return {name: z.read(name) for name in z.namelist()}


def test_a_job_on_ray_equals_the_in_process_job_and_survives_a_killed_worker(
    servers: tuple[LiveServer, LiveServer],
) -> None:
    on_ray, local = servers
    fields = {"start": "0", "stop": "40",
              "params": json.dumps({"scale_space": "warped", "time_smoothing": "warped",
                                    "time_window": 5, "fit": "rotation",
                                    "fit_selection": "name CA"})}  # fmt: skip
    reference = submit(local, **fields)
    job = submit(on_ray, **fields)
    info = wait(on_ray, job, ("running", "done"))
    batch = on_ray.app_state.jobs.batch
    assert batch is not None
    while info["progress"]["done"] < 8 and info["state"] == "running":  # a chunk is written
        info = wait(on_ray, job, ("running", "done"))
    pids = batch.worker_pids()
    assert len(pids) == 2
    os.kill(pids[0], signal.SIGKILL)  # mid-job: its chunk is retried
    assert wait(on_ray, job, ("done", "failed"))["state"] == "done"
    assert wait(local, reference, ("done", "failed"))["state"] == "done"
    got, want = frames(on_ray, job), frames(local, reference)
    assert sorted(got) == [f"frame_{i:06d}.png" for i in range(40)]  # every frame, once
    assert got == want  # bit for bit
    health = httpx.get(f"{on_ray.url}/healthz", timeout=30).json()["batch"]
    assert health["engine"] == "ray" and len(health["workers"]) == 2
    assert sum(w.get("alive", True) for w in health["workers"]) == 2  # restarted
    metrics = httpx.get(f"{on_ray.url}/metrics", timeout=30).text
    assert "scalesteer_batch_workers 2.0" in metrics


def test_cancel_frees_the_workers_and_bad_input_fails_with_its_reason(
    servers: tuple[LiveServer, LiveServer],
) -> None:
    on_ray, _local = servers
    job = submit(on_ray, width="320", height="240")
    wait(on_ray, job, ("running",))
    deadline = time.monotonic() + 120
    while (info := httpx.get(f"{on_ray.url}/api/jobs/{job}", headers=AUTH).json())["progress"][
        "done"
    ] < 1:
        assert info["state"] == "running", info  # a failure says why at once
        assert time.monotonic() < deadline, "no frame rendered"
        time.sleep(0.1)
    t0 = time.monotonic()  # the workers are busy rendering: /healthz still answers at once
    health = httpx.get(f"{on_ray.url}/healthz", timeout=10).json()["batch"]
    assert time.monotonic() - t0 < 3.0 and len(health["workers"]) == 2
    r = httpx.delete(f"{on_ray.url}/api/jobs/{job}", headers=AUTH, timeout=30)
    assert r.status_code == 200
    assert wait(on_ray, job, ("cancelled", "failed", "done"))["state"] == "cancelled"
    quick = submit(on_ray, start="0", stop="4")  # the workers take new work at once
    assert wait(on_ray, quick, ("done", "failed"), timeout=60)["state"] == "done"
    r = httpx.post(
        f"{on_ray.url}/api/jobs",
        headers=AUTH,
        files=[("topology", ("broken.pdb", b"ATOM  garbage\n" * 3))],
        data={"output": "zip"},
        timeout=30,
    )
    if r.status_code == 202:
        failed = wait(on_ray, r.json()["id"], ("failed", "done"))
        assert failed["state"] == "failed" and "broken.pdb" in failed["error"]
    else:
        assert r.status_code == 422 and "broken.pdb" in r.text


GCS_PROBE = """
import sys
from ray._raylet import GcsClient
try:
    GcsClient(address=sys.argv[1]).internal_kv_get(b"scalesteer-probe", None, timeout=10)
    print("accepted")
except Exception as exc:
    print("refused:", type(exc).__name__, exc)
"""


def gcs_probe(address: str, token: str | None) -> str:
    """What Ray's GCS answers a client holding `token` (None: no token at all)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
    env["RAY_AUTH_MODE"] = "token" if token else "disabled"
    if token:
        env["RAY_AUTH_TOKEN"] = token
    out = subprocess.run(
        [sys.executable, "-c", GCS_PROBE, address],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return out.stdout.strip()


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["stopped", "killed"])
def test_a_ray_instance_of_the_servers_own_is_authenticated_and_ends_with_it(
    tmp_path: Path, sig: signal.Signals
) -> None:
    """The first job started a local Ray whose servers listen on every interface, with no
    authentication (whoever reached a port ran code as the server's user); two of its agents
    outlived the server, and a SIGTERM printed Ray's crash dump. Asked for without a cluster,
    Ray now runs under the server's supervisor, every server of it on loopback, with Ray's token
    authentication and no dashboard, and neither a stop nor a `kill -9` of the server leaves
    any of its processes."""
    data = tmp_path / "data"
    data.mkdir()
    for src in (PSF, DCD):
        (data / Path(src).name).write_bytes(Path(src).read_bytes())
    env = {k: v for k, v in os.environ.items() if not k.endswith("RAY_ADDRESS")}
    server = ServerProcess(
        tmp_path / "state", "--batch-engine", "ray", "--data-dir", str(data), env=env
    )
    try:
        r = httpx.post(
            f"{server.url}/api/jobs",
            headers=AUTH,
            data={"dataset": Path(PSF).name, "trajectory_dataset": Path(DCD).name,
                  "width": "32", "height": "24", "output": "zip", "stop": "4"},
            timeout=30,
        )  # fmt: skip
        assert r.status_code == 202, r.text
        stages = set()
        deadline = time.monotonic() + 120
        while (info := httpx.get(f"{server.url}/api/jobs/{r.json()['id']}", headers=AUTH).json())[
            "state"
        ] not in ("done", "failed"):
            stages.add(info["stage"])
            assert time.monotonic() < deadline, info
            time.sleep(0.1)
        assert info["state"] == "done", info
        assert "starting Ray" in stages  # what the job is waiting for, not "0/4 frames"
        health = httpx.get(f"{server.url}/healthz", timeout=30).json()["batch"]
        assert health["address"] == "local" and health["auth"] == "token"
        tree = running(descendants(server.process.pid))
        (supervisor,) = [p for p in tree if "server.supervisor" in command_line(p)]
        ray = descendants(supervisor)
        assert any("gcs_server" in command_line(p) for p in ray)
        assert any("raylet" in command_line(p) for p in ray)
        assert {int(w["pid"]) for w in health["workers"]} <= set(ray)
        sockets = listening_sockets(ray)
        assert sockets and 8265 not in {port for _, port in sockets}  # no dashboard
        # every Ray server (GCS, raylet, workers, agents, autoscaler metrics) on loopback only
        exposed = {s for s in sockets if s[0] not in LOOPBACK}
        assert not exposed, exposed
        port = re.search(r"--port=(\d+)", command_line(supervisor))
        temp_dir = re.search(r"--temp-dir=(\S+)", command_line(supervisor))
        assert port is not None and temp_dir is not None
        # Ray makes its folder writable by everyone: it sits in one only this user enters
        assert Path(temp_dir.group(1)).parent.stat().st_mode & 0o777 == 0o700
        environ = Path(f"/proc/{supervisor}/environ").read_bytes().split(b"\0")
        token = next(v[15:].decode() for v in environ if v.startswith(b"RAY_AUTH_TOKEN="))
        address = f"127.0.0.1:{port.group(1)}"
        refused = gcs_probe(address, None)
        assert refused.startswith("refused: AuthenticationError"), refused
        assert gcs_probe(address, "0" * len(token)).startswith("refused"), address
        assert gcs_probe(address, token) == "accepted"  # the control: the probe can pass
    finally:
        server.stop(sig)
    left = wait_gone(tree)
    assert not left, [command_line(p) for p in left]
    assert not Path(temp_dir.group(1)).parent.exists()  # its sockets and logs: removed too
    assert "SIGTERM received" not in server.log.read_text()  # no crash dump on a stop
