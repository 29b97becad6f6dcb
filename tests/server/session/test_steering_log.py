"""The steering log reads back what was appended before the read, even while the entries are
still being written (each is fsynced on a writer thread of its own)."""

from __future__ import annotations

from pathlib import Path

from server.session.steering_log import SteeringLog


def test_a_read_sees_every_entry_appended_before_it(tmp_path: Path) -> None:
    log = SteeringLog(tmp_path)
    try:
        for i in range(40):
            log.append("s", {"id": i + 1, "event": "render_params"})
        entries = log.read("s")  # at once, without waiting for the appends' futures
        assert [e["id"] for e in entries] == list(range(1, 41))
    finally:
        log.close()
