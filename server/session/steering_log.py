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
        """All complete entries, oldest first (a torn last line after a crash is skipped)."""
        path = self.path(session)
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

    def close(self) -> None:
        self._writer.shutdown(wait=True)
