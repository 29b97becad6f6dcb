"""Untrusted structure files, read in a child process with bounded memory, time and size.

The native readers underneath MDAnalysis (XDR, DCD, ...) trust their input: a damaged XTC can
raise SIGFPE or SIGSEGV inside them. Files that arrive over the network are therefore opened in a
child process: a crash, a runaway allocation or a reader that never returns ends that process
only, and the caller gets a `StructureError` naming the file. Compressed files are inflated by
the child with a size cap, and text formats have their atoms counted before they are parsed, so a
small gzip bomb costs neither memory nor minutes.
"""

from __future__ import annotations

import atexit
import bz2
import contextlib
import gzip
import multiprocessing.connection
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Topology
from structures.errors import StructureError
from structures.interpreters import child_environment
from structures.reader import load

_SPARE: tuple[subprocess.Popen[bytes], multiprocessing.connection.Connection] | None = None
_SPARE_LOCK = threading.Lock()


@dataclass(frozen=True)
class ReadLimits:
    """What one untrusted read may cost."""

    max_atoms: int
    max_file_bytes: int = 2 << 30
    """Largest size of any one file once decompressed."""
    memory_bytes: int = 6 << 30
    """Address space of the reader process (MDAnalysis and numpy alone map about 1 GiB)."""
    open_s: float = 120.0
    """Wall time to open the files and build the topology."""
    frame_s: float = 30.0
    """Wall time to read one frame."""
    scratch_dir: str | None = None
    """Where compressed files are inflated (a folder per read, removed when the read ends,
    even by a kill); None: the system's temporary directory."""


def _start_child() -> tuple[subprocess.Popen[bytes], multiprocessing.connection.Connection]:
    """A fresh interpreter (never a fork of the server, whose GPU context and threads must not
    be copied) that imports the readers and waits for its files."""
    ours, theirs = socket.socketpair()
    code = "import structures.isolated as m; m._main()"
    process = subprocess.Popen(
        [sys.executable, "-c", code, str(theirs.fileno())],
        env=child_environment(),
        pass_fds=(theirs.fileno(),),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    theirs.close()
    return process, multiprocessing.connection.Connection(ours.detach())


def _discard_spare() -> None:
    """At exit: end the spare child (it would see its socket close and exit anyway)."""
    global _SPARE
    with _SPARE_LOCK:
        spare, _SPARE = _SPARE, None
    if spare is not None:
        spare[1].close()
        spare[0].kill()
        spare[0].wait()


atexit.register(_discard_spare)


def _take_child() -> tuple[subprocess.Popen[bytes], multiprocessing.connection.Connection]:
    """The spare child if one is ready (its imports done), else a new one; a new spare is
    started either way, so the next untrusted read does not wait for imports."""
    global _SPARE
    with _SPARE_LOCK:
        taken, _SPARE = _SPARE, None
        if taken is None or taken[0].poll() is not None:
            taken = _start_child()
        _SPARE = _start_child()
        return taken


class IsolatedStructure:
    """A structure opened by `structures.reader.load` in a child process.

    `topology` and `n_frames` are known once it is open; `positions(i)` asks the child for one
    frame. Not thread-safe: one caller at a time (each job or request owns its own)."""

    def __init__(
        self, topology: str, trajectories: Sequence[str], limits: ReadLimits, *, label: str = ""
    ) -> None:
        self.limits = limits
        self.label = label or ", ".join(os.path.basename(f) for f in (topology, *trajectories))
        self._scratch = tempfile.mkdtemp(prefix="read-", dir=limits.scratch_dir)
        try:
            self._process, self._conn = _take_child()
        except BaseException:
            shutil.rmtree(self._scratch, ignore_errors=True)
            raise
        try:
            self._conn.send(("open", (topology, list(trajectories), limits, self._scratch)))
            self.topology: Topology
            self.n_frames: int
            self.notes: tuple[str, ...]
            self.topology, self.n_frames, self.notes = self._answer(limits.open_s, "open")
        except BaseException:
            self.close()
            raise

    def positions(self, index: int) -> npt.NDArray[np.float32]:
        """Positions (angstrom) of frame `index`, read by the child."""
        if not 0 <= index < self.n_frames:
            raise StructureError(f"frame {index} out of range: {self.label} has {self.n_frames}")
        try:
            self._conn.send(("positions", index))
        except OSError:
            raise self._crashed() from None
        positions: npt.NDArray[np.float32] = self._answer(self.limits.frame_s, f"frame {index}")
        return positions

    def frame(self, index: int) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32] | None]:
        """Positions (angstrom) of frame `index` and its periodic box (None without one), read
        by the child."""
        if not 0 <= index < self.n_frames:
            raise StructureError(f"frame {index} out of range: {self.label} has {self.n_frames}")
        try:
            self._conn.send(("frame", index))
        except OSError:
            raise self._crashed() from None
        found: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32] | None] = self._answer(
            self.limits.frame_s, f"frame {index}"
        )
        return found

    def _answer(self, timeout: float, what: str) -> Any:
        try:
            ready = self._conn.poll(timeout)
        except (EOFError, OSError):
            raise self._crashed() from None
        if not ready:
            self._kill()
            raise StructureError(
                f"reading {self.label} ({what}) took longer than {timeout:g} s; stopped"
            )
        try:
            kind, value = self._conn.recv()
        except (EOFError, OSError):
            raise self._crashed() from None
        if kind == "error":
            raise StructureError(str(value))
        return value

    def _crashed(self) -> StructureError:
        try:
            code = self._process.wait(2.0)
        except subprocess.TimeoutExpired:
            code = None
        if code is not None and code < 0:
            try:
                why = signal.Signals(-code).name
            except ValueError:
                why = f"signal {-code}"
        elif code is None:
            self._kill()
            why = "no answer"
        else:
            # an error the reader did not turn into a message of its own, or out of memory
            why = f"exit status {code}"
        return StructureError(
            f"cannot read {self.label}: the reader crashed on it ({why}); the file is damaged "
            "or not in the format its name says"
        )

    def _kill(self) -> None:
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait()

    def close(self) -> None:
        """End the child (politely, then by force) and remove what it inflated."""
        with contextlib.suppress(OSError):
            self._conn.send(("close", None))
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._process.wait(1.0)
        self._kill()
        self._conn.close()
        shutil.rmtree(self._scratch, ignore_errors=True)

    def __enter__(self) -> IsolatedStructure:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _main() -> None:
    """The child: import the readers, wait for the files, open them under resource limits,
    then answer frame requests until told to close."""
    import MDAnalysis  # noqa: F401  (imported before the request: a spare child is ready)

    conn = multiprocessing.connection.Connection(int(sys.argv[1]))
    try:
        kind, value = conn.recv()
    except (EOFError, OSError):
        return
    if kind == "open":
        topology, trajectories, limits, scratch = value
        _limit_resources(limits)
        _serve(conn, topology, trajectories, limits, scratch)


def _serve(
    conn: multiprocessing.connection.Connection,
    topology: str,
    trajectories: list[str],
    limits: ReadLimits,
    scratch: str,
) -> None:
    try:
        top = _prepare(topology, scratch, limits)
        trajs = [_prepare(t, scratch, limits) for t in trajectories]
        structure = load(top, trajs, max_atoms=limits.max_atoms)
        conn.send(("ok", (structure.topology, structure.n_frames, structure.notes)))
    except StructureError as exc:
        conn.send(("error", str(exc)))
        return
    except MemoryError:
        conn.send(("error", f"{os.path.basename(topology)}: too large to read here"))
        return
    while True:
        try:
            kind, value = conn.recv()
        except (EOFError, OSError):
            return
        if kind not in ("positions", "frame"):
            return
        try:
            if kind == "frame":
                conn.send(("ok", structure.frame(int(value))))
            else:
                conn.send(("ok", structure.positions(int(value))))
        except MemoryError:
            conn.send(("error", f"frame {value}: too large to read here"))
        except Exception as exc:  # a reader's own error for one frame, sent as text
            conn.send(("error", f"cannot read frame {value}: {str(exc)[:300]}"))


def _limit_resources(limits: ReadLimits) -> None:
    import resource

    for which, value in (
        (resource.RLIMIT_AS, limits.memory_bytes),
        (resource.RLIMIT_FSIZE, limits.max_file_bytes),
        (resource.RLIMIT_CORE, 0),
    ):
        try:
            _soft, hard = resource.getrlimit(which)
            cap = value if hard == resource.RLIM_INFINITY else min(value, hard)
            resource.setrlimit(which, (cap, hard))
        except (ValueError, OSError):
            continue
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the cap fails, no signal


_OPENERS: dict[str, Callable[..., Any]] = {".gz": gzip.open, ".bz2": bz2.open}
_PACKED_MAGIC = (b"\x1f\x8b", b"BZh", b"\xfd7zXZ\x00", b"\x28\xb5\x2f\xfd", b"PK\x03\x04")
"""gzip, bzip2, xz, zstd and zip: content that is itself compressed."""
_PACKED_SUFFIXES = (".gz", ".bz2", ".xz", ".lzma", ".zst", ".zip")


def _prepare(path: str, scratch: str, limits: ReadLimits) -> str:
    """The path to read: `path` itself, or its decompressed copy in `scratch` (refused past
    `max_file_bytes`); text formats get their atoms counted first."""
    name = os.path.basename(path)
    if not os.path.isfile(path):
        raise StructureError(f"no such file: {name}")
    suffix = os.path.splitext(name)[1].lower()
    opener = _OPENERS.get(suffix)
    if opener is not None:
        inner_name = name[: -len(suffix)] or "file"
        # the cap holds for one layer: a compressed file inside one (x.pdb.gz.gz) would be
        # inflated again by the reader itself, past it
        nested = f"{name} holds a compressed file; compress the structure once"
        if inner_name.lower().endswith(_PACKED_SUFFIXES):
            raise StructureError(nested)
        inner = os.path.join(scratch, inner_name)
        written = 0
        try:
            with opener(path, "rb") as src, open(inner, "wb") as dst:
                while block := src.read(1 << 20):
                    if written == 0 and block.startswith(_PACKED_MAGIC):
                        raise StructureError(nested)
                    written += len(block)
                    if written > limits.max_file_bytes:
                        raise StructureError(
                            f"{name} decompresses to more than {limits.max_file_bytes} bytes"
                        )
                    dst.write(block)
        except (OSError, EOFError, ValueError) as exc:
            raise StructureError(f"{name}: cannot decompress ({exc})") from None
        path = inner
    _count_atoms(path, name, limits.max_atoms)
    return path


XTC_MAGIC = 1995


def _count_atoms(path: str, name: str, max_atoms: int) -> None:
    """Refuse a PDB, GRO, XYZ or XTC file with more than `max_atoms` atoms before parsing it."""
    fmt = os.path.basename(path).rsplit(".", 1)[-1].lower()
    if fmt in ("pdb", "ent", "pqr"):
        atoms = 0
        with open(path, "rb") as fh:
            for line in fh:
                if line.startswith((b"ATOM", b"HETATM")):
                    atoms += 1
                    if atoms > max_atoms:
                        raise StructureError(
                            f"{name} has more than {max_atoms} atoms in its first model, the limit"
                        )
                elif line.startswith(b"ENDMDL"):
                    return
    elif fmt in ("gro", "xyz"):
        with open(path, "rb") as fh:
            head = [fh.readline() for _ in range(2)]
        count_line = head[1] if fmt == "gro" else head[0]
        where = "line 2" if fmt == "gro" else "line 1"
        try:
            declared = int(count_line.split()[0])
        except (ValueError, IndexError):
            start = count_line[:40]
            text = all(32 <= b < 127 or b in b"\t\r\n" for b in start)
            found = repr(start.decode().strip()) if text else "binary data, not text"
            raise StructureError(
                f"{name}: {where} should be the number of atoms, found {found}"
            ) from None
        if declared < 1:
            raise StructureError(f"{name}: {where} declares {declared} atoms, not at least 1")
        if declared > max_atoms:
            raise StructureError(f"{name} declares {declared} atoms, the limit is {max_atoms}")
    elif fmt == "xtc":  # each frame's header: magic 1995, then the atom count (big-endian)
        with open(path, "rb") as fh:
            header = fh.read(8)
        if len(header) == 8 and int.from_bytes(header[:4], "big") == XTC_MAGIC:
            declared = int.from_bytes(header[4:], "big", signed=True)
            if not 0 < declared <= max_atoms:
                raise StructureError(
                    f"{name} declares {declared} atoms a frame, the limit is {max_atoms}"
                )
