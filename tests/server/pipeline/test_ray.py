"""Batch jobs on Ray, on a local Ray cluster of two CPU workers: the same output as the
in-process path (PNG frames bit for bit), a worker killed mid-job changes nothing, cancel frees
the workers, a bad input fails the job with its reason, and /healthz names the workers."""

from __future__ import annotations

import io
import json
import os
import signal
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.conftest import LiveServer, make_settings, start_server

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
                                    "time_window": 5})}  # fmt: skip
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
