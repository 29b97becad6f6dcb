"""The per-session steering log: one JSON line per accepted action, flushed and fsync'd.

It is the record of who changed what and at which simulation step, so it must survive a crash:
each line is written whole, flushed and fsync'd before the next, by one writer thread (order kept).
"""

from __future__ import annotations

import json
import os
import re
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from protocol.messages import SESSION_NAME

_SAFE = re.compile(SESSION_NAME)


class SteeringLog:
    """Appends and reads `<dir>/<session>.jsonl` files."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.directory.mkdir(parents=True, exist_ok=True)
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="steering-log")
        self._lock = threading.Lock()
        self._id_lock = threading.Lock()
        self._ids: dict[str, int] = {}
        """The last id handed out per session (read from disk on first use)."""

    def path(self, session: str) -> Path:
        if not _SAFE.match(session):
            raise ValueError(f"invalid session name {session!r}")
        return self.directory / f"{session}.jsonl"

    def append(self, session: str, entry: dict[str, Any]) -> Future[None]:
        """Queue one entry; the returned future resolves once it is on disk."""
        record = {"wall_time": time.time(), **entry}
        line = json.dumps(record, separators=(",", ":"), default=str) + "\n"
        return self._writer.submit(self._write, self.path(session), line)

    def _write(self, path: Path, line: str) -> None:
        with self._lock, open(path, "a", encoding="utf-8") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())

    def read(self, session: str) -> list[dict[str, Any]]:
        """All complete entries, oldest first (a torn last line after a crash is skipped),
        including every entry appended before this call: the read waits for the queued
        writes (blocking; call it off the event loop)."""
        path = self.path(session)
        self._writer.submit(lambda: None).result()
        if not path.exists():
            return []
        out: list[dict[str, Any]] = []
        with open(path, encoding="utf-8") as fh:
            for raw in fh:
                if raw.endswith("\n"):
                    try:
                        out.append(json.loads(raw))
                    except json.JSONDecodeError:
                        continue
        return out

    def next_id(self, session: str) -> int:
        """A new entry id for `session`: one more than any on disk or handed out in this
        process, so a `ref` names one action for the life of the log, across restarts."""
        with self._id_lock:
            last = self._ids.get(session)
            if last is None:
                last = self.last_id(session)
            self._ids[session] = last + 1
            return last + 1

    def last_id(self, session: str) -> int:
        """The largest entry id on disk (0 for a new log), so ids continue across restarts and a
        `ref` names one action for the life of the log. Reads only the file's tail."""
        path = self.path(session)
        if not path.exists():
            return 0
        with open(path, "rb") as fh:
            end = fh.seek(0, os.SEEK_END)
            chunk = 1 << 16
            while True:
                start = max(0, end - chunk)
                fh.seek(start)
                tail = fh.read(end - start)
                lines = tail.split(b"\n")
                complete = lines[1:-1] if start > 0 else lines[:-1]
                for raw in reversed(complete):
                    try:
                        found = json.loads(raw).get("id")
                    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
                        continue
                    if isinstance(found, int):
                        return found
                if start == 0:
                    return 0
                chunk *= 4

    def close(self) -> None:
        self._writer.shutdown(wait=True)
