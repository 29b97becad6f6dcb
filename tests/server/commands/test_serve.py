"""`scalesteer serve` options: tokens that survive restarts, limits set from the command line."""

from __future__ import annotations

import stat
import threading
import time
from pathlib import Path

import pytest

from server.commands import serve
from server.commands.serve import build_parser, settings_from
from server.settings import ServerSettings


def settings(*argv: str):  # type: ignore[no-untyped-def]
    return settings_from(build_parser().parse_args(list(argv)))


def test_generated_tokens_are_kept_so_copied_links_survive_a_restart(tmp_path: Path) -> None:
    state = str(tmp_path / "state")
    first = settings("--state-dir", state)
    again = settings("--state-dir", state)
    assert first.token and first.viewer_token and first.token != first.viewer_token
    assert (again.token, again.viewer_token) == (first.token, first.viewer_token)
    mode = stat.S_IMODE((tmp_path / "state" / "tokens.json").stat().st_mode)
    assert mode == 0o600
    renewed = settings("--state-dir", state, "--new-tokens")
    assert renewed.token != first.token
    assert settings("--state-dir", state, "--token", "mine").token == "mine"


def test_limits_are_set_by_name_and_bad_ones_are_named(tmp_path: Path) -> None:
    state = str(tmp_path / "state")
    s = settings("--state-dir", state, "--set", "max_connections=5", "--set", "frame_budget_ms=40")
    assert s.max_connections == 5 and s.frame_budget_ms == 40.0
    with pytest.raises(ValueError, match="bogus"):
        settings("--state-dir", state, "--set", "bogus=1")
    with pytest.raises(ValueError, match="not an integer"):
        settings("--state-dir", state, "--set", "max_connections=lots")
    with pytest.raises(ValueError, match="max_connections: must be positive, got 0"):
        settings("--state-dir", state, "--set", "max_connections=0")
    cold = settings(
        "--state-dir", state, "--set", "warm_up_render=0", "--set", "selection_prestart=0"
    )
    assert (cold.warm_up_render, cold.selection_prestart) == (0, 0)
    with pytest.raises(ValueError, match="selection_prestart: must be 0 or more, got -1"):
        settings("--state-dir", state, "--set", "selection_prestart=-1")
    assert settings("--state-dir", state, "--set", "close_wait_s=2.5").close_wait_s == 2.5
    with pytest.raises(ValueError, match="close_wait_s must be a finite number of seconds"):
        settings("--state-dir", state, "--set", "close_wait_s=inf")


def test_video_codecs_are_chosen_by_name_or_turned_off(tmp_path: Path) -> None:
    state = str(tmp_path / "state")
    assert settings("--state-dir", state).video_codecs == ("h264", "av1", "vp9", "h264-baseline")
    assert settings("--state-dir", state, "--video-codecs", "vp9, h264").video_codecs == (
        "vp9",
        "h264",
    )
    assert settings("--state-dir", state, "--video-codecs", "none").video_codecs == ()
    with pytest.raises(ValueError, match="unknown hevc"):
        settings("--state-dir", state, "--video-codecs", "h264,hevc")


def test_device_atoms_go_with_the_devices_and_a_bad_count_is_named(tmp_path: Path) -> None:
    state = str(tmp_path / "state")
    s = settings("--state-dir", state, "--gpus", "cpu,cpu", "--device-atoms", "150")
    assert (s.gpus, s.device_atoms) == ("cpu,cpu", 150)
    assert settings("--state-dir", state).device_atoms is None  # the message limit then
    with pytest.raises(ValueError, match="--device-atoms must be at least 1"):
        settings("--state-dir", state, "--device-atoms", "0")


def test_devices_that_do_not_exist_are_named_before_the_server_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    started: list[object] = []
    monkeypatch.setattr(serve, "run", lambda *a, **k: started.append(a))
    argv = ["--state-dir", str(tmp_path / "state"), "--port", "0"]
    assert serve.main([*argv, "--gpus", "cuda:7"]) == 2
    err = capsys.readouterr().err
    assert "--gpus cuda:7" in err and "cuda:7" in err.split("--gpus cuda:7", 1)[1]
    assert started == []
    assert serve.main([*argv, "--gpus", " , "]) == 2
    assert "name at least one device" in capsys.readouterr().err
    assert serve.main([*argv, "--gpus", "cpu,cpu"]) == 0 and len(started) == 1
    # --device too: gpu7 had served, and failed every render
    assert serve.main([*argv, "--device", "gpu7"]) == 2
    assert "--device gpu7: unknown device 'gpu7'" in capsys.readouterr().err
    assert len(started) == 1


def test_ctrl_c_stops_the_server_without_a_traceback(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys

    cmd = [sys.executable, "-c", "from server.commands.cli import main; raise SystemExit(main())"]
    argv = ["serve", "--port", "0", "--state-dir", str(tmp_path / "state"), "--token", "t"]
    proc = subprocess.Popen(
        [*cmd, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # the dashboard link is printed once settings are made
            if "scalesteer dashboard" in line:
                break
        time.sleep(3.0)  # uvicorn starts after the link
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err, err[-2000:]


def test_a_server_interrupted_while_it_starts_is_stopped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while `ServerThread` waits for its server (the demo's start-up): the interrupt
    reaches the caller and the half-started server stops instead of running on in the
    background."""

    class InterruptedWait:
        monotonic = staticmethod(time.monotonic)

        @staticmethod
        def sleep(seconds: float) -> None:
            raise KeyboardInterrupt

    monkeypatch.setattr(serve, "time", InterruptedWait)
    before = {t for t in threading.enumerate() if t.name == "uvicorn"}
    with pytest.raises(KeyboardInterrupt):
        serve.ServerThread(ServerSettings(port=0, state_dir=tmp_path, token="t" * 24))
    left = [t for t in threading.enumerate() if t.name == "uvicorn" and t not in before]
    assert not any(t.is_alive() for t in left)


def test_a_stopped_server_exits_without_waiting_for_a_render_of_minutes(tmp_path: Path) -> None:
    """SIGTERM while a REST render holds the device for minutes (the geodesic density of
    adenylate kinase in volume at 1920x1080 on the CPU device): the app closes (recordings,
    jobs, sessions), waits `close_wait_s` for the device, then the process ends, saying so."""
    import signal

    import httpx
    from MDAnalysisTests.datafiles import PDB

    from tests.server.processes import TOKEN, ServerProcess

    wait_s = 3.0
    server = ServerProcess(tmp_path / "state", "--set", f"close_wait_s={wait_s}")
    answers: list[int] = []
    details: list[str] = []

    def render() -> None:
        with open(PDB, "rb") as f, httpx.Client(timeout=600) as c:
            params = '{"mode": "volume", "sigma_A": 3.3, "scale_space": "geodesic"}'
            try:
                r = c.post(
                    f"{server.url}/api/render",
                    headers={"Authorization": f"Bearer {TOKEN}"},
                    files={"file": ("adk.pdb", f)},
                    data={"width": "1920", "height": "1080", "params": params},
                )
                answers.append(r.status_code)
                details.append(r.json()["detail"])
            except httpx.HTTPError:
                answers.append(-1)  # the connection closed with the server

    asker = threading.Thread(target=render, daemon=True)
    try:
        asker.start()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until the render holds the device
            health = httpx.get(f"{server.url}/healthz", timeout=5).json()
            if any(r["busy_s"] > 1.0 for r in health["render"]):
                break
            time.sleep(0.2)
        else:
            pytest.fail(f"the render did not start: {health}")
        # the render runs for minutes: a server that waited for it would time out here
        code = server.stop(signal.SIGTERM, timeout=5 + wait_s + 30)
    finally:
        if server.alive():
            server.stop(signal.SIGKILL)
    log = server.log.read_text()
    assert code in (0, -signal.SIGTERM), log[-3000:]
    assert "stopping with work still running: cpu for" in log
    asker.join(10)
    assert answers == [503], answers  # answered, as JSON, before the process ended
    assert "the server is stopping" in details[0]
    assert "Exception in ASGI application" not in log
