"""The supervisor: a command's whole tree ends with its owner (`kill -9` of the owner included),
with `stop`, or with the command itself; a process that left its parent is ended too."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from server.supervisor import ROOT, Supervised
from tests.server.processes import command_line, running, wait_gone

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")

# a shell that starts a daemon (its own session, reparented once the shell's subshell exits)
# and a plain background child, writes their pids and its own, then waits
TREE = (
    "(setsid sleep 301 & echo $! >> {pids}); sleep 302 & echo $! >> {pids}; "
    "echo $$ >> {pids}; {end}"
)


def pids_of(path: Path, count: int = 3) -> list[int]:
    deadline = time.monotonic() + 10
    while True:
        text = path.read_text() if path.exists() else ""
        if len(text.split()) >= count:
            return [int(x) for x in text.split()]
        assert time.monotonic() < deadline, text
        time.sleep(0.02)


def test_the_tree_ends_when_its_owner_is_killed(tmp_path: Path) -> None:
    pids, folder = tmp_path / "pids", tmp_path / "scratch"
    folder.mkdir()
    owner = subprocess.Popen(
        [sys.executable, "-c", (
            "import sys, time; from pathlib import Path; from server.supervisor import Supervised; "
            f"s = Supervised(['sh', '-c', {TREE.format(pids=pids, end='sleep 303')!r}], "
            f"grace_s=1.0, remove=Path({str(folder)!r})); print(s.pid, flush=True); time.sleep(300)"
        )],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert owner.stdout is not None
        supervisor = int(owner.stdout.readline())
        tree = [supervisor, *pids_of(pids)]
        assert running(tree) == tree
    finally:
        owner.send_signal(signal.SIGKILL)
        owner.communicate()
    left = wait_gone(tree, 10)
    assert not left, [command_line(p) for p in left]
    deadline = time.monotonic() + 5
    while folder.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not folder.exists()


def test_stop_ends_the_tree_and_a_command_that_exits_leaves_nothing(tmp_path: Path) -> None:
    first = tmp_path / "first"
    s = Supervised(["sh", "-c", TREE.format(pids=first, end="sleep 303")], grace_s=1.0)
    tree = pids_of(first)
    assert s.poll() is None
    assert s.stop() == -signal.SIGTERM  # the command's own end, passed on
    assert not wait_gone(tree, 5)
    second = tmp_path / "second"
    s = Supervised(["sh", "-c", TREE.format(pids=second, end="exit 3")], grace_s=1.0)
    tree = pids_of(second)
    assert s.process.wait(10) == 3 and s.poll() == 3
    assert not wait_gone(tree, 5)  # its background children did not outlive it


def test_the_command_ends_when_its_supervisor_is_killed(tmp_path: Path) -> None:
    """A notebook's client knows the supervisor's pid: killing that one had left the server
    running, orphaned. The command now gets SIGTERM when its supervisor dies."""
    pids = tmp_path / "pids"
    supervised = Supervised(["sh", "-c", f"echo $$ >> {pids}; sleep 300"], grace_s=1.0)
    try:
        (command,) = pids_of(pids, 1)
        assert running([command]) == [command]
        supervised.process.send_signal(signal.SIGKILL)
        supervised.process.wait(10)
        left = wait_gone([command], 10)
        assert not left, [command_line(p) for p in left]
    finally:
        supervised.stop()
