"""Child processes that end with the server, `kill -9` of the server included.

Every long-lived process the server starts (a replay, a local Ray instance) runs under a small
supervisor, `python -m server.supervisor --lifeline FD -- COMMAND...`, started by `Supervised`.
The server holds the write end of a pipe (the lifeline) and the supervisor its read end; the
server never writes to it. When the lifeline closes (the server stopped, crashed or was killed:
the kernel closes a dead process's files) or the supervisor is sent SIGTERM, it ends the whole
tree: SIGTERM to the command, then to every process still under it, SIGKILL to what is left after
the grace period; then it removes the command's folder, when it was given one. On Linux the
supervisor is a child subreaper, so a process that leaves its parent (Ray's agents, daemons)
still counts as under it; and the command itself gets SIGTERM should the supervisor be killed.

The supervisor runs in a session of its own: a Ctrl-C meant for the server reaches the server,
which stops its children in order, and not the children themselves. When the command exits by
itself, whatever it left running is ended too, and the supervisor exits as the command did (the
same code, or killed by the same signal).
"""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parents[1]
GRACE_S = 5.0
"""How long a tree has, after SIGTERM, before what is left is killed."""


class Supervised:
    """A command running under the supervisor; it ends when this process ends, at the latest."""

    def __init__(
        self,
        command: Sequence[str],
        *,
        env: Mapping[str, str] | None = None,
        cwd: Path | str | None = None,
        output: IO[bytes] | int | None = subprocess.DEVNULL,
        grace_s: float = GRACE_S,
        remove: Path | None = None,
    ) -> None:
        """`remove`: a folder of the command's, deleted once the tree has ended."""
        read_end, self._lifeline = os.pipe()  # both ends non-inheritable: no other child holds it
        environment = dict(os.environ if env is None else env)
        path = environment.get("PYTHONPATH")
        environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), path]))
        supervisor = [sys.executable, "-m", "server.supervisor", "--lifeline", str(read_end)]
        extra = [] if remove is None else ["--remove", str(remove)]
        try:
            self.process = subprocess.Popen(
                [*supervisor, "--grace", str(grace_s), *extra, "--", *command],
                pass_fds=(read_end,),
                stdin=subprocess.DEVNULL,
                stdout=output,
                stderr=subprocess.STDOUT if output is not None else None,
                env=environment,
                cwd=cwd,
                start_new_session=True,
            )
        except BaseException:
            os.close(self._lifeline)
            raise
        finally:
            os.close(read_end)
        self.grace_s = grace_s

    @property
    def pid(self) -> int:
        return self.process.pid

    def poll(self) -> int | None:
        code = self.process.poll()
        if code is not None:
            self._release()
        return code

    def stop(self, timeout: float | None = None) -> int:
        """End the command and everything under it; returns the supervisor's exit code."""
        timeout = self.grace_s + 5.0 if timeout is None else timeout
        self._release()  # the supervisor sees the lifeline close and ends the tree
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:  # a supervisor that hangs: end its tree from here
            tree = descendants(self.process.pid)
            self.process.kill()
            for pid in tree:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
            return self.process.wait()

    def _release(self) -> None:
        if self._lifeline >= 0:
            os.close(self._lifeline)
            self._lifeline = -1

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self._release()


# ---------------------------------------------------------------------------- the supervisor


def _subreaper() -> None:
    """Become the parent of every orphan below us (Linux), so none escapes the tree."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER


def _ending_with(parent: int) -> Callable[[], None]:
    """For the command's process, before it runs (Linux): SIGTERM when the supervisor dies.
    A supervisor killed with SIGKILL (its pid is the one a notebook's client knows) had left
    the server running, orphaned, with nothing to end it."""

    def arrange() -> None:
        if not sys.platform.startswith("linux"):
            return
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)  # PDEATHSIG
        if os.getppid() != parent:  # it died before that was arranged
            os._exit(1)

    return arrange


def descendants(root: int) -> list[int]:
    """The processes under `root` (from /proc; empty where there is none), parents first."""
    children: dict[int, list[int]] = {}
    with contextlib.suppress(OSError):
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                with open(f"/proc/{entry.name}/stat", "rb") as fh:
                    stat = fh.read()
            except OSError:
                continue
            fields = stat[stat.rfind(b")") + 2 :].split()
            children.setdefault(int(fields[1]), []).append(int(entry.name))
    out: list[int] = []
    todo = list(children.get(root, []))
    while todo:
        pid = todo.pop(0)
        out.append(pid)
        todo.extend(children.get(pid, []))
    return out


class _Tree:
    """The supervised command and what it starts."""

    def __init__(self, command: list[str]) -> None:
        self.child = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, preexec_fn=_ending_with(os.getpid())
        )
        self.status: int | None = None

    def reap(self) -> None:
        """Collect every exited process under us (orphans come here too), noting the child's."""
        while True:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if pid == 0:
                return
            if pid == self.child.pid:
                self.status = status
                self.child.returncode = os.waitstatus_to_exitcode(status)

    def signal(self, pids: Sequence[int], sig: int) -> None:
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)

    def end(self, grace_s: float) -> None:
        """SIGTERM to the command (it may stop its own in order), then to all still under us,
        then SIGKILL to what is left."""
        if self.status is None:
            self.signal([self.child.pid], signal.SIGTERM)
        self._wait(lambda: self.status is not None, grace_s / 2)
        self.signal(self._left(), signal.SIGTERM)
        self._wait(lambda: not self._left(), grace_s / 2)
        self.signal(self._left(), signal.SIGKILL)
        self._wait(lambda: not self._left(), 1.0)

    def _left(self) -> list[int]:
        self.reap()
        left = descendants(os.getpid())
        if self.status is None and self.child.pid not in left:
            left.append(self.child.pid)
        return left

    def _wait(self, done: Callable[[], bool], seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while True:
            self.reap()
            if done() or time.monotonic() > deadline:
                return
            time.sleep(0.05)


def _exit_as(status: int | None) -> None:
    """Exit as the command did: its code, or killed by its signal."""
    if status is None:
        os._exit(1)
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        with contextlib.suppress(OSError, ValueError):  # SIGKILL's handler cannot be set
            signal.signal(sig, signal.SIG_DFL)
        os.kill(os.getpid(), sig)
        time.sleep(1.0)
        os._exit(128 + sig)
    os._exit(os.waitstatus_to_exitcode(status))


def main(argv: Sequence[str]) -> None:
    args = list(argv)
    if "--" not in args:
        sys.exit("usage: python -m server.supervisor --lifeline FD [--grace S] -- COMMAND...")
    split = args.index("--")
    options, command = args[:split], args[split + 1 :]
    values = dict(zip(options[::2], options[1::2], strict=False))
    lifeline = int(values["--lifeline"])
    grace_s = float(values.get("--grace", GRACE_S))
    remove = values.get("--remove")
    _subreaper()
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)

    def wake(_sig: int, _frame: Any) -> None:
        with contextlib.suppress(OSError):
            os.write(wake_w, b"x")

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, wake)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server decides when its children end
    tree = _Tree(command)
    while tree.status is None:
        ready, _, _ = select.select([lifeline, wake_r], [], [], 0.5)
        if wake_r in ready:
            break
        if lifeline in ready and not os.read(lifeline, 64):
            break  # the server is gone
        tree.reap()
    tree.end(grace_s)
    if remove is not None:
        shutil.rmtree(remove, ignore_errors=True)
    _exit_as(tree.status)


if __name__ == "__main__":
    main(sys.argv[1:])
