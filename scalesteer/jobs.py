"""Batch jobs and recordings: handles on the server's `/api/jobs` and `/api/recordings`."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from scalesteer.rest import Rest

FINAL_STATES = frozenset({"done", "failed", "cancelled", "expired"})
Progress = Callable[["Job"], None]


class JobFailedError(RuntimeError):
    """A job that ended otherwise than `done`; `job.info` holds the server's description."""

    def __init__(self, job: Job) -> None:
        self.job = job
        why = job.info.get("error") or job.info.get("warning") or ""
        super().__init__(f"job {job.id} is {job.state}" + (f": {why}" if why else ""))


class _Described:
    """Something the server describes by an id and a state (`info`: its latest answer)."""

    def __init__(self, rest: Rest, info: dict[str, Any]) -> None:
        self._rest = rest
        self.info = info

    @property
    def id(self) -> str:
        return str(self.info["id"])

    @property
    def state(self) -> str:
        return str(self.info["state"])


class Job(_Described):
    """A batch render (trajectory -> zip of PNGs or MP4) or a movie of a live session.

    `info` is the server's description as of the last call (`state`, `progress` {done,
    total}, `eta_s`, `error`, `stage`, `partial`, `warning`, `ending`): `refresh()` asks
    again, and `wait()` and `cancel()` refresh it."""

    @property
    def progress(self) -> tuple[int, int]:
        """(frames done, frames in all)."""
        p = self.info.get("progress") or {}
        return int(p.get("done", 0)), int(p.get("total", 0))

    @property
    def done(self) -> bool:
        return self.state in FINAL_STATES

    def refresh(self) -> Job:
        self.info = self._rest.json("GET", f"/api/jobs/{self.id}")
        return self

    def wait(
        self, timeout: float | None = None, progress: Progress | None = None, poll_s: float = 0.5
    ) -> Job:
        """Wait until the job ends, calling `progress(job)` whenever its progress changed;
        raises `JobFailedError` unless it ends `done`, `TimeoutError` after `timeout` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        seen: tuple[Any, ...] = ()
        while True:
            self.refresh()
            now = (self.state, self.progress, self.info.get("stage"))
            if progress is not None and now != seen:
                progress(self)
            seen = now
            if self.done:
                break
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {self.id} is still {self.state} after {timeout} s")
            time.sleep(poll_s)
        if self.state != "done":
            raise JobFailedError(self)
        return self

    def download(self, target: str | os.PathLike[str]) -> Path:
        """Save the finished job's output (a zip or an MP4) to `target`."""
        return self._rest.download(f"/api/jobs/{self.id}/result", target)

    def cancel(self) -> Job:
        """Stop a queued or running job at its next frame: it ends `cancelled`
        (`info["ending"]` says so until it has; one asked during its last frame ends `done`),
        and a live movie ends keeping what it filmed. A job that has ended is left as it is,
        its output too (`delete()` removes it)."""
        self.info = self._rest.json("POST", f"/api/jobs/{self.id}/cancel")
        return self

    def delete(self, timeout: float = 60.0) -> None:
        """Remove the job and its output from the server; one still running is cancelled
        first (a live movie's too: nothing is kept), and waited for up to `timeout` s."""
        deadline = time.monotonic() + timeout
        while not (answer := self._rest.json("DELETE", f"/api/jobs/{self.id}")).get("deleted"):
            self.info = answer  # still running: the answer describes it
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {self.id} is still {self.state} after {timeout} s")
            time.sleep(0.2)

    def __repr__(self) -> str:
        done, total = self.progress
        return f"Job({self.id[:8]}, {self.state}, {done}/{total})"


class Recording(_Described):
    """A recording of a session's run: its frames (XTC), topology (PDB) and steering."""

    @property
    def frames(self) -> int:
        return int(self.info.get("frames", 0))

    @property
    def marks(self) -> list[dict[str, Any]]:
        """The steering actions at the frames they took effect (once stopped)."""
        return list(self.info.get("marks") or [])

    def refresh(self) -> Recording:
        self.info = self._rest.json("GET", f"/api/recordings/{self.id}")
        return self

    def stop(self) -> Recording:
        """End the recording, keeping it; `marks` then lists its steering."""
        self.info = self._rest.json("POST", f"/api/recordings/{self.id}/stop")
        return self

    def download(self, target: str | os.PathLike[str], name: str | None = None) -> Path:
        """All its files as a zip, or one file (`topology.pdb`, `frames.xtc`,
        `steering.jsonl`, `marks.json`, `recording.json`)."""
        path = (
            f"/api/recordings/{self.id}/download"
            if name is None
            else f"/api/recordings/{self.id}/files/{name}"
        )
        return self._rest.download(path, target)

    def movie(self, **options: Any) -> Job:
        """Render it to an MP4 job (`width`, `height`, `fps`, `stride`, `camera`, `params`,
        `overlay`, `caption_s`)."""
        return Job(
            self._rest,
            self._rest.json("POST", f"/api/recordings/{self.id}/movie", json_body=options),
        )

    def delete(self) -> None:
        self._rest.request("DELETE", f"/api/recordings/{self.id}")

    def __repr__(self) -> str:
        return f"Recording({self.id}, {self.state}, {self.frames} frames)"
