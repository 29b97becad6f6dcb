"""Selections evaluated in worker processes that can be killed.

A selection is priced before it runs (`structures.selection_cost`), but an estimate can be
wrong, and MDAnalysis gives no way to stop an evaluation once started. So selections never run
in the server's process: a few worker processes (fresh interpreters, never forks of the server)
hold the universes of the topologies they are given and evaluate there, each under an address
space limit, each request under a wall-time limit. A worker that runs past its time is killed;
one that runs out of memory dies or answers so; either way the caller gets a SelectionError
naming the limit, a fresh worker starts, and the server's memory and event loop never see the
cost.

One thread per worker talks to it (so a slow evaluation holds no thread of anyone else), and
callers get futures: the event loop awaits them, threads wait on them. A topology stays with
the worker it was first given to, which keeps its universe warm (a selection typed on a 40,000
atom session answers in a few milliseconds) and reloads it after a restart.

Workers end with the server: each exits when its pipe to the server closes, and the kernel
kills it when the server's process dies (`PR_SET_PDEATHSIG`), even mid-evaluation.

Kept whole: the server's side of each worker's pipe and the worker's own loop (`_main`) speak one
private message format, kept in one file so the two cannot drift apart.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing.connection
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Hashable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Topology
from structures.interpreters import child_environment
from structures.selection import SelectionError, Selector
from structures.selection_cost import SelectionLimits

log = logging.getLogger("scalesteer.selections")

START_TIMEOUT_S = 60.0
"""A worker must be ready (its imports done) within this; about 1 s on an idle machine."""
LOAD_S_PER_ATOM = 2e-5
"""Time allowed to send and build a topology's universe, beyond the request's own (about
1 s per million atoms measured, so 20 s per million allowed)."""

Result = npt.NDArray[np.int32] | int | SelectionError
"""One selection's answer: its atoms, their number (when only counts were asked), or why not."""


class SelectionBusyError(SelectionError):
    """Not evaluated for now (the workers are busy, or the server is stopping): nothing is
    wrong with the selection, and asking again later may answer."""


@dataclass(frozen=True)
class PoolLimits:
    """What the worker processes may use, besides what each selection may cost."""

    selection: SelectionLimits = field(default_factory=SelectionLimits)
    workers: int = 2
    """Worker processes (each holds the universes of the topologies given to it)."""
    timeout_s: float = 10.0
    """Wall time of one request (a selection, or the layers of one render together)."""
    memory_bytes: int = 4 << 30
    """Address space of one worker process."""
    max_atoms: int = 4_000_000
    """Atoms of the topologies one worker keeps at once (least recently used go first)."""
    max_waiting: int = 64
    """Requests queued for one worker; more are refused at once rather than kept waiting."""
    owner_seconds_per_min: float = 30.0
    """Worker time one owner (a client: its role and address) may use in any minute; past it
    its requests are refused until the time is earned back, so that one client's costly (but
    allowed) selections cannot hold the workers every session shares."""


class Held:
    """One topology in the pool: its selections are evaluated by the worker that holds it.
    Thread-safe; `release` when done (a new topology, a finished request)."""

    def __init__(self, pool: SelectionPool, key: int, topology: Topology, worker: _Worker):
        self.pool = pool
        self.key = key
        self.topology = topology
        self.n_atoms = topology.n_atoms
        self._worker = worker
        self.released = False

    def submit(
        self,
        texts: Sequence[str],
        positions: npt.NDArray[np.float32] | None = None,
        box: npt.NDArray[np.float32] | None = None,
        *,
        positions_key: Hashable | None = None,
        counts: bool = False,
        strict: bool = False,
        owner: Hashable | None = None,
    ) -> Future[list[Result]]:
        """Evaluate `texts` (one budget for them all; `strict`: none if any is refused) at
        `positions`; `positions_key` names these positions, so a worker that has them is
        not sent them again. The time it takes is charged to `owner` (None: to no one)."""
        task = _Task("select", self, (list(texts), positions, box, counts, strict), positions_key)
        task.owner = owner
        return self._worker.submit(task)

    def submit_secondary(
        self, positions: npt.NDArray[np.float32], positions_key: Hashable | None = None
    ) -> Future[npt.NDArray[np.uint8]]:
        """Each atom's secondary structure (structures.selection.Selector.secondary)."""
        return self._worker.submit(_Task("secondary", self, (positions,), positions_key))

    def evaluate(
        self,
        texts: Sequence[str],
        positions: npt.NDArray[np.float32] | None = None,
        box: npt.NDArray[np.float32] | None = None,
        positions_key: Hashable | None = None,
    ) -> list[Result]:
        """`submit`, waited for (the worker's own time limit bounds the wait)."""
        return self.submit(texts, positions, box, positions_key=positions_key).result()

    def prepare(self) -> None:
        """Build the universe now (before the first selection needs it)."""
        self._worker.submit(_Task("load", self, (), None))

    def release(self) -> None:
        if not self.released:
            self.released = True
            self._worker.forget(self)


@dataclass
class _Task:
    kind: str
    held: Held
    args: tuple[Any, ...]
    positions_key: Hashable | None
    future: Future[Any] = field(default_factory=Future)
    owner: Hashable | None = None
    """Whose worker time it uses (`PoolLimits.owner_seconds_per_min`)."""


class FairQueue:
    """A worker's waiting requests, served one owner after another (round robin) rather than in
    arrival order: one client's requests queued together wait behind each other, not in front
    of everyone else's. Requests of no owner (layers of a session, jobs) are one owner of their
    own; `None` (stop) goes to the front."""

    def __init__(self) -> None:
        self._lanes: OrderedDict[Hashable, deque[_Task]] = OrderedDict()
        self._stop = False
        self._size = 0
        self._ready = threading.Condition()

    def qsize(self) -> int:
        return self._size

    def put(self, task: _Task | None) -> None:
        with self._ready:
            if task is None:
                self._stop = True
            else:
                self._lanes.setdefault(task.owner, deque()).append(task)
                self._size += 1
            self._ready.notify()

    def get(self) -> _Task | None:
        with self._ready:
            while not self._stop and not self._size:
                self._ready.wait()
            return self._next()

    def get_nowait(self) -> _Task | None:
        """The next request; raises queue.Empty when none waits."""
        with self._ready:
            if not self._size:
                raise queue.Empty
            return self._next()

    def _next(self) -> _Task | None:
        if self._stop:
            self._stop = False
            return None
        owner, lane = next(iter(self._lanes.items()))
        task = lane.popleft()
        del self._lanes[owner]
        if lane:  # its next request goes behind every other owner's
            self._lanes[owner] = lane
        self._size -= 1
        return task


class SelectionPool:
    """Worker processes that evaluate selections under `limits`."""

    def __init__(self, limits: PoolLimits | None = None) -> None:
        self.limits = limits or PoolLimits()
        self._keys = itertools.count(1)
        self._lock = threading.Lock()
        self._workers = [_Worker(self, i) for i in range(max(1, self.limits.workers))]
        self.closed = False
        self.kills = 0
        """Workers killed or lost so far (a request past a limit)."""
        self._spent: dict[Hashable, deque[tuple[float, float]]] = {}
        """owner -> (when, seconds) of its requests that ended in the last minute."""

    def used_s(self, owner: Hashable, now: float | None = None) -> float:
        """Worker seconds `owner`'s requests took in the last minute."""
        now = time.monotonic() if now is None else now
        with self._lock:
            spent = self._spent.get(owner)
            if spent is None:
                return 0.0
            while spent and now - spent[0][0] > 60.0:
                spent.popleft()
            if not spent:
                del self._spent[owner]
                return 0.0
            return sum(seconds for _, seconds in spent)

    def charge(self, owner: Hashable, seconds: float) -> None:
        with self._lock:
            spent = self._spent.setdefault(owner, deque(maxlen=4096))
            spent.append((time.monotonic(), seconds))

    def hold(self, topology: Topology) -> Held:
        """Give `topology` to the worker with the fewest atoms held."""
        with self._lock:
            worker = min(self._workers, key=lambda w: w.assigned)
            held = Held(self, next(self._keys), topology, worker)
            worker.assigned += held.n_atoms
        return held

    def start(self, workers: int) -> None:
        """Start the first `workers` worker processes now, each from its own thread, rather
        than at their first request: a fresh interpreter importing MDAnalysis takes about a
        second, which a new session's first picture would otherwise wait for."""
        for worker in self._workers[: max(0, workers)]:
            worker.prestart()

    def pids(self) -> list[int]:
        """The worker processes running now."""
        return [pid for w in self._workers if (pid := w.pid) is not None]

    def close(self) -> None:
        """End every worker (its child killed if it is still evaluating)."""
        self.closed = True
        for worker in self._workers:
            worker.stop()
        for worker in self._workers:
            worker.join()


class _Worker:
    """One worker process and the thread that starts it, feeds it and kills it. The child is
    started from this thread, which lives as long as the pool: the kernel's parent-death
    signal follows the thread that started a process."""

    def __init__(self, pool: SelectionPool, index: int) -> None:
        self.pool = pool
        self.index = index
        self.limits = pool.limits
        self.assigned = 0
        """Atoms of the live topologies given to this worker."""
        self._queue = FairQueue()
        self._process: subprocess.Popen[bytes] | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._loaded: OrderedDict[int, int] = OrderedDict()
        """Topologies the child holds (key -> atoms), least recently used first."""
        self._positions: dict[int, Hashable] = {}
        """The positions each topology's universe was last sent."""
        self._thread: threading.Thread | None = None
        self._thread_lock = threading.Lock()
        self._restart = False
        self._prestart = False

    @property
    def pid(self) -> int | None:
        process = self._process
        return process.pid if process is not None and process.poll() is None else None

    def submit(self, task: _Task) -> Future[Any]:
        if self.pool.closed or task.held.released:
            why = "the server is stopping" if self.pool.closed else "the system changed meanwhile"
            task.future.set_exception(SelectionBusyError(None, f"{why}; not evaluated", 0))
            return task.future
        if task.owner is not None:
            used, allowed = self.pool.used_s(task.owner), self.limits.owner_seconds_per_min
            if used >= allowed:
                task.future.set_exception(
                    SelectionBusyError(
                        None,
                        f"your selections took {used:.0f} s of the server's selection workers in "
                        f"the last minute (selection_seconds_per_min: {allowed:g}); wait a "
                        "little, or select fewer atoms",
                        0,
                    )
                )
                return task.future
        if self._queue.qsize() >= self.limits.max_waiting:
            task.future.set_exception(
                SelectionBusyError(
                    None,
                    f"the server's selection workers are busy ({self.limits.max_waiting} "
                    "requests waiting); try again shortly",
                    0,
                )
            )
            return task.future
        self._ensure_thread()
        self._queue.put(task)
        return task.future

    def forget(self, held: Held) -> None:
        with self.pool._lock:
            self.assigned -= held.n_atoms
        if not self.pool.closed:
            self._ensure_thread()
            self._queue.put(_Task("drop", held, (), None))

    def prestart(self) -> None:
        """Start the child before any request asks for it (a request that comes meanwhile
        waits for it as it would have anyway)."""
        self._prestart = True
        self._ensure_thread()

    def _ensure_thread(self) -> None:
        with self._thread_lock:
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name=f"selections-{self.index}", daemon=True
                )
                self._thread.start()

    def stop(self) -> None:
        self._queue.put(None)
        process = self._process
        if process is not None and process.poll() is None:
            with contextlib.suppress(OSError):
                process.kill()  # an evaluation in progress ends now; its caller is told

    def join(self) -> None:
        thread = self._thread
        if thread is not None:
            thread.join(10.0)

    # ---------------------------------------------------------------- the worker's thread

    def _run(self) -> None:
        try:
            if self._prestart and not self.pool.closed:
                with contextlib.suppress(SelectionError):  # its first request tries again
                    self._ensure_child()
            while True:
                task = self._queue.get()
                if task is None or self.pool.closed:
                    break
                if task.kind == "drop":
                    self._drop(task.held.key)
                    continue
                if not task.future.set_running_or_notify_cancel():
                    continue
                started = time.monotonic()
                try:
                    task.future.set_result(self._serve(task))
                except SelectionError as exc:
                    task.future.set_exception(exc)
                except Exception as exc:  # a fault of ours: reported, never a hung caller
                    log.exception("selection worker %d failed a request", self.index)
                    task.future.set_exception(
                        SelectionError(None, f"the selection worker failed ({exc!r})", 0)
                    )
                finally:
                    if task.owner is not None:
                        self.pool.charge(task.owner, time.monotonic() - started)
                if self._process is None and self._restart and not self.pool.closed:
                    self._restart = False  # killed: a fresh worker is ready for what follows
                    with contextlib.suppress(SelectionError):
                        self._start()
        finally:
            self._end_child()
            while True:  # whoever still waits is told
                try:
                    left = self._queue.get_nowait()
                except queue.Empty:
                    break
                if left is not None and left.future.set_running_or_notify_cancel():
                    left.future.set_exception(
                        SelectionBusyError(None, "the server is stopping; selections are closed", 0)
                    )

    def _serve(self, task: _Task) -> Any:
        held = task.held
        if held.released:
            raise SelectionBusyError(None, "the system changed meanwhile; not evaluated", 0)
        self._ensure_child()
        if held.key not in self._loaded:
            self._evict_for(held.n_atoms)
            timeout = self.limits.timeout_s + LOAD_S_PER_ATOM * held.n_atoms
            self._call(("load", held.key, held.topology), timeout)
            self._loaded[held.key] = held.n_atoms
            self._positions.pop(held.key, None)
        self._loaded.move_to_end(held.key)
        if task.kind == "load":
            return None
        limits = self.limits.selection
        if task.kind == "select":
            texts, positions, box, counts, strict = task.args
            send = positions
            if (
                positions is not None
                and task.positions_key is not None
                and self._positions.get(held.key) == task.positions_key
            ):
                send = None  # the child has these positions already
            reply = self._call(
                ("select", held.key, texts, send, box, limits, counts, strict),
                self.limits.timeout_s,
                texts[0] if len(texts) == 1 else None,
            )
        else:
            (positions,) = task.args
            send = positions
            if task.positions_key is not None and task.positions_key == self._positions.get(
                held.key
            ):
                send = None
            reply = self._call(("secondary", held.key, send, limits), self.limits.timeout_s)
        if send is not None:
            self._positions[held.key] = task.positions_key
        return reply

    def _drop(self, key: int) -> None:
        self._positions.pop(key, None)
        if self._loaded.pop(key, None) is not None and self._alive():
            with contextlib.suppress(OSError, ValueError):
                assert self._conn is not None
                self._conn.send(("drop", key))

    def _evict_for(self, atoms: int) -> None:
        """Drop the least recently used topologies until `atoms` more fit."""
        while self._loaded and sum(self._loaded.values()) + atoms > self.limits.max_atoms:
            key = next(iter(self._loaded))
            self._drop(key)

    def _alive(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def _ensure_child(self) -> None:
        if self._alive():
            return
        if self._process is not None:  # died while idle (killed from outside)
            self._end_child()
        self._start()

    def _start(self) -> None:
        ours, theirs = socket.socketpair()
        code = "import structures.selection_pool as m; m._main()"
        env = child_environment(
            OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", MALLOC_ARENA_MAX="2"
        )
        process = subprocess.Popen(
            [
                sys.executable, "-c", code, str(theirs.fileno()), str(os.getpid()),
                str(self.limits.memory_bytes),
            ],
            pass_fds=(theirs.fileno(),),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )  # fmt: skip
        theirs.close()
        conn = multiprocessing.connection.Connection(ours.detach())
        self._process, self._conn = process, conn
        self._loaded.clear()
        self._positions.clear()
        try:
            ready = conn.poll(START_TIMEOUT_S) and conn.recv()[0] == "ready"
        except (OSError, EOFError):
            ready = False
        if not ready:
            status = process.poll()
            self._end_child()
            raise SelectionError(
                None, f"the selection worker did not start (exit status {status})", 0
            )

    def _call(self, message: Any, timeout: float, text: str | None = None) -> Any:
        """Send `message` and wait at most `timeout` s for the answer; a child past it is
        killed, one that died is reported. `text`: the selection asked about, if one."""
        conn = self._conn
        assert conn is not None
        try:
            conn.send(message)
        except (OSError, ValueError):
            raise self._lost(text) from None
        try:
            ready = conn.poll(timeout)
        except (OSError, EOFError):
            raise self._lost(text) from None
        if not ready:
            self._kill(f"{message[0]} ran past {timeout:g} s")
            raise SelectionError(
                text,
                f"evaluating it took longer than {timeout:g} s, the limit "
                "(selection_timeout_s); stopped",
                0,
                "selection_timeout_s",
                int(timeout),
            )
        try:
            kind, value = conn.recv()
        except (OSError, EOFError):
            raise self._lost(text) from None
        if kind == "memory":
            self._kill(f"{message[0]} ran out of memory")
            raise self._memory_error(text)
        if kind == "error":
            raise value
        return value

    def _memory_error(self, text: str | None, why: str = "") -> SelectionError:
        return SelectionError(
            text,
            f"evaluating it needed more memory than the limit of "
            f"{_bytes(self.limits.memory_bytes)} "
            f"(selection_memory_bytes){why}; stopped",
            0,
            "selection_memory_bytes",
            self.limits.memory_bytes,
        )

    def _lost(self, text: str | None) -> SelectionError:
        """The child ended while working: past its memory (an allocation that failed in
        native code aborts it) or killed from outside."""
        process = self._process
        code = None
        if process is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                code = process.wait(2.0)
        if code is not None and code < 0:
            try:
                why = signal.Signals(-code).name
            except ValueError:
                why = f"signal {-code}"
        else:
            why = f"exit status {code}"
        self._kill(f"the worker ended ({why})")
        return self._memory_error(text, f"; the worker ended with {why}")

    def _kill(self, why: str) -> None:
        """Kill the child, whatever it is doing; a fresh one starts once its caller has been
        answered."""
        self.pool.kills += 1
        log.warning("selection worker %d killed: %s", self.index, why)
        self._end_child()
        self._restart = True

    def _end_child(self) -> None:
        process, conn = self._process, self._conn
        self._process, self._conn = None, None
        self._loaded.clear()
        self._positions.clear()
        if conn is not None:
            conn.close()  # a child waiting for work sees its pipe close and exits
        if process is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(0.5)
            if process.poll() is None:
                process.kill()
            process.wait()


def _bytes(n: int) -> str:
    return f"{n / 2**30:g} GiB" if n >= 2**30 else f"{n / 2**20:g} MiB"


class InProcess:
    """The interface of `Held`, evaluated in this process and without limits: for a user's
    own files on their own machine (`scalesteer render`)."""

    def __init__(self, topology: Topology) -> None:
        self.selector = Selector(topology)

    def submit(
        self,
        texts: Sequence[str],
        positions: npt.NDArray[np.float32] | None = None,
        box: npt.NDArray[np.float32] | None = None,
        *,
        positions_key: Hashable | None = None,
        counts: bool = False,
        strict: bool = False,
        owner: Hashable | None = None,
    ) -> Future[list[Result]]:
        """As `Held.submit` (nobody's time is counted here)."""
        done: Future[list[Result]] = Future()
        found = self.selector.evaluate(list(texts), positions, box, strict=strict)
        out: list[Result] = [
            len(r) if counts and not isinstance(r, SelectionError) else r for r in found
        ]
        done.set_result(out)
        return done

    def submit_secondary(
        self, positions: npt.NDArray[np.float32], positions_key: Hashable | None = None
    ) -> Future[npt.NDArray[np.uint8]]:
        done: Future[npt.NDArray[np.uint8]] = Future()
        try:
            done.set_result(self.selector.secondary(positions))
        except SelectionError as exc:
            done.set_exception(exc)
        return done

    def release(self) -> None:
        """Nothing is held elsewhere."""


# -------------------------------------------------------------------- the worker process


def _die_with_parent(parent: int) -> None:
    """Have the kernel kill this process when the server's dies (Linux), and exit now if it
    is already gone."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(0)


def _limit_memory(memory_bytes: int) -> None:
    import resource

    for which, value in ((resource.RLIMIT_AS, memory_bytes), (resource.RLIMIT_CORE, 0)):
        try:
            _soft, hard = resource.getrlimit(which)
            cap = value if hard == resource.RLIM_INFINITY else min(value, hard)
            resource.setrlimit(which, (cap, hard))
        except (ValueError, OSError):
            continue


def _main() -> None:
    """The worker: hold universes, answer selections, until the server's pipe closes."""
    fd, parent, memory = (int(a) for a in sys.argv[1:4])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is for the server
    _die_with_parent(parent)
    _limit_memory(memory)
    import MDAnalysis.core.selection  # noqa: F401  (imported before the greeting)

    conn = multiprocessing.connection.Connection(fd)
    conn.send(("ready", os.getpid()))
    held: dict[int, Selector] = {}
    positions: dict[int, npt.NDArray[np.float32]] = {}
    received = itertools.count(1)
    versions: dict[int, int] = {}
    """Which positions each topology was sent last (its universe keeps them placed)."""
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        kind, key = message[0], message[1]
        try:
            if kind == "load":
                selector = held[key] = Selector(message[2])
                selector.universe  # noqa: B018 (built now, timed as the load)
                reply: tuple[str, Any] = ("ok", None)
            elif kind == "drop":
                held.pop(key, None)
                positions.pop(key, None)
                versions.pop(key, None)
                continue
            elif kind == "select":
                _, _, texts, sent, box, limits, counts, strict = message
                if sent is not None:
                    positions[key], versions[key] = sent, next(received)
                found = held[key].evaluate(
                    texts, positions.get(key), box, limits, versions.get(key), strict
                )
                answer: list[Result] = [
                    len(r) if counts and not isinstance(r, SelectionError) else r for r in found
                ]
                reply = ("ok", answer)
            elif kind == "secondary":
                _, _, sent, limits = message
                if sent is not None:
                    positions[key], versions[key] = sent, next(received)
                reply = ("ok", held[key].secondary(positions[key], limits))
            else:
                return
        except MemoryError:
            reply = ("memory", None)
        except SelectionError as exc:
            reply = ("error", exc)
        except Exception as exc:  # sent as text: the server logs nothing it cannot read
            reply = ("error", SelectionError(None, f"{type(exc).__name__}: {str(exc)[:300]}", 0))
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return
        if reply[0] == "memory":
            return  # a fresh process follows; this heap may be left in pieces
        del reply
        time.sleep(0)
