"""Replays started from the dashboard, each a `scalesteer replay` child process.

The files were saved into the server's data directory and checked by the isolated reader before
a child starts; the child plays them into this server's `/ws/sim` with the server token (passed
in its environment, not on its command line). A child ends with its session's `stop` control,
`ReplayManager.stop`, or the server: it runs under the server's supervisor
(`server.supervisor`), so a server that crashes or is killed leaves no replay behind to
reconnect to the next one.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.supervisor import Supervised

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class ReplayProcess:
    session: str
    files: list[str]
    process: Supervised
    log_path: Path
    started: float = field(default_factory=time.time)
    recording: str | None = None
    """The recording this replay plays (its steering marks belong on the timeline)."""

    def describe(self) -> dict[str, Any]:
        code = self.process.poll()
        return {
            "session": self.session,
            "files": self.files,
            "running": code is None,
            "exit_code": code,
            "started": self.started,
            "dashboard": f"/?session={self.session}",
            "recording": self.recording,
        }

    stopping: bool = False
    """The server asked it to stop (its end is no failure)."""

    def last_words(self) -> str:
        """The end of the child's output (why it stopped), for the API's answer; nothing when
        all it said was the line it starts with (that says nothing of its end)."""
        try:
            last = self.log_path.read_text(errors="replace").strip().splitlines()[-1][:300]
        except (OSError, IndexError):
            return ""
        return "" if _BANNER.match(last) else last

    def why_ended(self) -> str:
        """Why an ended child ended, in words: its signal first, then its last line; else
        its last line, else its exit status."""
        code = self.process.poll()
        words = self.last_words()
        if code is not None and code < 0:
            with contextlib.suppress(ValueError):
                name = signal.Signals(-code).name
                return f"killed by {name}; it last said: {words}" if words else f"killed by {name}"
        return words or f"exit status {code}"


_BANNER = re.compile(r"scalesteer replay: \d+ atoms, \d+ frames ")
"""The line a replay prints as it starts (`simulation_adapters.replay`)."""


@dataclass
class ReplayManager:
    """The replay children of one server, by session."""

    processes: dict[str, ReplayProcess] = field(default_factory=dict)

    def start(
        self,
        session: str,
        files: list[Path],
        port: int,
        token: str | None,
        fps: float,
        loop: bool,
        log_dir: Path,
        recording: str | None = None,
    ) -> ReplayProcess:
        log_dir.mkdir(parents=True, exist_ok=True)
        log_path = log_dir / f"replay-{session}.log"
        command = [
            sys.executable,
            "-m",
            "simulation_adapters.replay",
            *[str(f) for f in files],
            "--url",
            f"ws://127.0.0.1:{port}/ws/sim",
            "--session",
            session,
            "--fps",
            str(fps),
            "--retry",
            "30",
            *(["--loop"] if loop else []),
        ]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        if token is not None:
            env["SCALESTEER_TOKEN"] = token  # not on the command line, where `ps` shows it
        with open(log_path, "wb") as out:
            process = Supervised(command, cwd=ROOT, env=env, output=out)
        replay = ReplayProcess(
            session, [f.name for f in files], process, log_path, recording=recording
        )
        self.processes[session] = replay
        return replay

    watchers: set[asyncio.Task[None]] = field(default_factory=set)

    def watch(
        self, replay: ReplayProcess, on_failure: Callable[[str], None], every_s: float = 0.5
    ) -> None:
        """Call `on_failure(why)` if the child ends with a failure, not by a stop the server
        asked for or a `stop` its session sent (status 0): a damaged file, a crash."""

        async def poll() -> None:
            while (code := replay.process.poll()) is None:
                await asyncio.sleep(every_s)
            if code != 0 and not replay.stopping:
                on_failure(replay.why_ended())

        task = asyncio.get_running_loop().create_task(poll(), name=f"watch-{replay.session}")
        self.watchers.add(task)
        task.add_done_callback(self.watchers.discard)

    def stop(self, session: str, timeout: float | None = None) -> bool:
        replay = self.processes.get(session)
        if replay is None:
            return False
        replay.stopping = True
        if replay.process.poll() is None:
            replay.process.stop(timeout)
        return True

    def close(self) -> None:
        for session in list(self.processes):
            self.stop(session)
        for task in list(self.watchers):
            task.cancel()
