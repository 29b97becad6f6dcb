"""Recordings of live sessions: the frames as an XTC trajectory, the topology as a PDB beside it,
and the steering log of the span, in one folder per recording.

A recording takes every frame the session receives (or every `stride`-th) from the event loop
into a queue; a writer thread encodes them with MDAnalysis's XTC writer in chunks and appends
each chunk to `frames.xtc` with one write, flushed and fsync'd. XTC frames are self-contained,
so the file is a valid trajectory after every chunk: a crash or a kill loses at most the frames
of the chunk being gathered (`FLUSH_S`), never the file. Positions keep XTC's precision
(0.001 nm, so within 0.005 Å of what the simulation sent).

The frames waiting for the disk hold at most `queue_bytes` of positions: a frame that arrives
when they are full is skipped, and the recording says so (`skipped`, and the steps of each run
of skipped frames in `skipped_spans`), so a simulation faster than the disk costs bounded memory
and a bounded stop, and the recorded frames stay whole.

On disk, `<state_dir>/recordings/<id>/`: `recording.json` (the manifest, replaced atomically),
`topology.pdb`, `frames.xtc` (and `frames.chunk.xtc` while a chunk is encoded), and, once it
ends, `steering.jsonl` (the session's log entries between its start and stop marks) and
`marks.json` (those entries as timeline marks, `server.pipeline.marks`). A recording the server
did not end (a crash) is found `interrupted` at the next start and finished from what is on
disk; a chunk file the crash left is removed.

Kept whole: the on-disk format (manifest, XTC chunks, the span of the steering log) is written by
`Recording` and read back by `RecordingStore` after a crash, both beside the format they share.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import re
import secrets
import shutil
import threading
import time
import warnings
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.pipeline.marks import steering_marks

log = logging.getLogger(__name__)

RECORDING_ID = re.compile(r"^r[A-Za-z0-9_-]{22}$")
FLUSH_S = 0.5
"""Longest time a received frame waits before it is on disk."""
FLUSH_FRAMES = 64
FILES = ("recording.json", "topology.pdb", "frames.xtc", "steering.jsonl", "marks.json")
"""What a recording's folder may hold (and what may be downloaded of it)."""
CHUNK = "frames.chunk.xtc"
"""The chunk being encoded, beside `frames.xtc` (a crash may leave it; the next start removes
it: its frames either reached `frames.xtc` or are the chunk a crash may lose)."""
LEFTOVERS = (CHUNK, "recording.json.tmp", "topology.pdb.tmp")
MAX_SKIPPED_SPANS = 256
"""Runs of skipped frames listed one by one; later ones extend the last (its count stays true)."""


@dataclass
class Recording:
    """One recording: its manifest fields, and while it runs, its writer."""

    id: str
    session: str
    directory: Path
    n_atoms: int
    stride: int
    max_bytes: int
    render_params: dict[str, Any]
    camera: dict[str, Any] | None
    first_log_id: int
    queue_bytes: int = 128 << 20
    """Positions that may wait for the disk; frames beyond are skipped (and counted)."""
    started: float = field(default_factory=time.time)
    state: str = "recording"
    """recording, finished, capped (stopped at its size limit), interrupted (by a crash)."""
    stopped: float | None = None
    last_log_id: int | None = None
    frames: int = 0
    bytes: int = 0
    steps: list[int] = field(default_factory=list)
    error: str | None = None
    received: int = 0
    """Frames the session received while recording (every one, `stride` or not)."""
    skipped: int = 0
    """Frames not recorded because the disk fell `queue_bytes` behind."""
    deleting: bool = False
    """Its deletion is under way: no movie or replay of it may start (it would lose its
    files halfway)."""
    skipped_spans: list[list[int]] = field(default_factory=list)
    """[first step, last step, frames skipped] of each run of skipped frames."""
    queued_bytes: int = 0
    """Positions taken and not yet on disk."""
    owner: str | None = None
    """The page (`hello.instance`) whose leaving ends the recording (None: nobody's)."""
    ended_because: str | None = None
    """Why it stopped, when something other than a stop request ended it."""
    _last_kept: bool = True
    _queue_lock: threading.Lock = field(default_factory=threading.Lock)
    detach: Callable[[], tuple[int, Future[None]]] | None = None
    """Unhooks the recording from its session's frames (set by whoever hooked it)."""
    _queue: queue.Queue[tuple[int, float, Any, Any] | None] = field(default_factory=queue.Queue)
    _thread: threading.Thread | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def running(self) -> bool:
        return self.state == "recording"

    def manifest(self) -> dict[str, Any]:
        return {
            "scalesteer_recording": 1,
            "id": self.id,
            "session": self.session,
            "n_atoms": self.n_atoms,
            "stride": self.stride,
            "max_bytes": self.max_bytes,
            "render_params": self.render_params,
            "camera": self.camera,
            "first_log_id": self.first_log_id,
            "last_log_id": self.last_log_id,
            "started": self.started,
            "stopped": self.stopped,
            "state": self.state,
            "frames": self.frames,
            "bytes": self.bytes,
            "queue_bytes": self.queue_bytes,
            "received": self.received,
            "skipped": self.skipped,
            "skipped_spans": self.skipped_spans,
            "error": self.error,
            "owner": self.owner,
            "ended_because": self.ended_because,
        }

    def skip_warning(self) -> str | None:
        """What the skipped frames mean, for whoever reads the recording (None: none)."""
        if not self.skipped:
            return None
        return (
            f"{self.skipped} frame(s) not recorded: the disk fell behind the simulation by "
            f"{self.queue_bytes / (1 << 20):g} MiB of frames (recording_queue_bytes); "
            "skipped_spans lists the steps of each gap"
        )

    def describe(self) -> dict[str, Any]:
        base = f"/api/recordings/{self.id}"
        out = {k: v for k, v in self.manifest().items() if k != "scalesteer_recording"}
        out["warning"] = self.skip_warning()
        out["files"] = {n: f"{base}/files/{n}" for n in FILES if (self.directory / n).exists()}
        out["download"] = f"{base}/download"
        return out

    def steering(self) -> list[dict[str, Any]]:
        """The steering log entries of the recorded span."""
        path = self.directory / "steering.jsonl"
        if not path.exists():
            return []
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    def frame_steps(self) -> list[int]:
        """The step of every recorded frame (read from the trajectory once after a restart)."""
        if not self.steps and self.frames:
            self.steps = xtc_steps(self.directory / "frames.xtc", self.n_atoms)
        return self.steps

    def marks(self) -> list[dict[str, Any]]:
        path = self.directory / "marks.json"
        if not path.exists():
            return []
        marks: list[dict[str, Any]] = json.loads(path.read_text())
        return marks

    @classmethod
    def load(cls, directory: Path) -> Recording:
        raw = json.loads((directory / "recording.json").read_text())
        return cls(
            id=raw["id"],
            session=raw["session"],
            directory=directory,
            n_atoms=int(raw["n_atoms"]),
            stride=int(raw["stride"]),
            max_bytes=int(raw["max_bytes"]),
            render_params=raw["render_params"],
            camera=raw.get("camera"),
            first_log_id=int(raw["first_log_id"]),
            queue_bytes=int(raw.get("queue_bytes", 128 << 20)),
            received=int(raw.get("received", 0)),
            skipped=int(raw.get("skipped", 0)),
            skipped_spans=[[int(x) for x in span] for span in raw.get("skipped_spans", [])],
            started=float(raw["started"]),
            state=raw["state"],
            stopped=raw.get("stopped"),
            last_log_id=raw.get("last_log_id"),
            frames=int(raw["frames"]),
            bytes=int(raw["bytes"]),
            error=raw.get("error"),
            owner=raw.get("owner"),
            ended_because=raw.get("ended_because"),
        )


def write_topology_pdb(path: Path, topology: p.Topology, positions: npt.NDArray[Any]) -> None:
    """The session's topology as a PDB (names, residues, chains, elements, bonds as CONECT),
    with the first recorded frame's positions. MDAnalysis writes the atoms; the CONECT records
    are made here from the bond array at once, as MDAnalysis would write them (its writer walks
    every atom's bonds in Python: 32 s of 34 for 47,681 atoms, while no frame of the recording
    reached the disk). Written beside `path` and moved into place: a crash never leaves a
    partial topology."""
    import MDAnalysis as mda

    n = topology.n_atoms
    resids = np.asarray(topology.residue_ids.to_numpy(), dtype=np.int64)
    chain_ids = np.asarray(topology.chain_ids, dtype=object)
    resnames = np.asarray(topology.residue_names, dtype=object)
    new = np.ones(n, dtype=bool)  # an atom that starts a residue
    new[1:] = (
        (chain_ids[1:] != chain_ids[:-1])
        | (resids[1:] != resids[:-1])
        | (resnames[1:] != resnames[:-1])
    )
    starts = np.flatnonzero(new)
    atom_res = np.cumsum(new) - 1
    chains = sorted(set(topology.chain_ids)) or [""]
    chain_of = {c: i for i, c in enumerate(chains)}
    res_chain = [chain_of[topology.chain_ids[s]] for s in starts]
    u = mda.Universe.empty(
        n,
        n_residues=len(starts),
        n_segments=len(chains),
        atom_resindex=atom_res,
        residue_segindex=res_chain,
        trajectory=True,
    )
    u.add_TopologyAttr("names", topology.names)
    u.add_TopologyAttr("elements", [e.capitalize() for e in topology.elements])
    u.add_TopologyAttr("types", topology.elements)
    u.add_TopologyAttr("resnames", resnames[starts])
    u.add_TopologyAttr("resids", resids[starts])
    u.add_TopologyAttr("chainIDs", topology.chain_ids)
    u.add_TopologyAttr("segids", [c or "SYS" for c in chains])
    if topology.bfactors is not None:
        u.add_TopologyAttr("tempfactors", topology.bfactors.to_numpy())
    u.atoms.positions = positions
    partial = path.with_name(path.name + ".tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # missing optional PDB fields (occupancy, altLocs...)
        u.atoms.write(str(partial), file_format="PDB", bonds=None)
    conect = conect_records(topology.bonds.to_numpy(), n)
    if conect:
        with open(partial, "r+b") as fh:
            fh.seek(0, os.SEEK_END)
            end = fh.tell()
            fh.seek(max(0, end - len(_END)))
            if fh.read() == _END:  # CONECT goes before the END record
                fh.seek(max(0, end - len(_END)))
                fh.truncate()
            fh.write(conect + _END)
    os.replace(partial, path)


_END = b"END\n"
MAX_CONECT_SERIAL = 99_999
"""PDB serial numbers have five digits: past them MDAnalysis writes no CONECT record at all."""


def conect_records(bonds: npt.NDArray[Any], n_atoms: int) -> bytes:
    """The CONECT records of `bonds` (atom index pairs), byte for byte as MDAnalysis's PDB
    writer makes them: one line per bonded atom in serial order, its partners in order."""
    pairs = np.asarray(bonds, dtype=np.int64).reshape(-1, 2)
    if not len(pairs) or pairs.min() < 0 or pairs.max() >= min(n_atoms, MAX_CONECT_SERIAL):
        return b""
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)  # a bond once, whichever way it was given
    both = np.concatenate([pairs, pairs[:, ::-1]]) + 1  # (atom, partner) as serials
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    atoms, first = np.unique(both[:, 0], return_index=True)
    partners = np.char.mod("%5d", both[:, 1])
    ends = np.append(first[1:], len(both))
    lines = [
        f"CONECT{atom:5d}" + "".join(partners[a:b]) + "\n"
        for atom, a, b in zip(atoms.tolist(), first.tolist(), ends.tolist(), strict=True)
    ]
    return "".join(lines).encode("ascii")


class _XtcAppender:
    """Appends frames to one XTC file in whole chunks (see the module's docstring)."""

    def __init__(self, path: Path, n_atoms: int) -> None:
        import MDAnalysis as mda

        self.path = path
        self.n_atoms = n_atoms
        self.universe = mda.Universe.empty(n_atoms, trajectory=True)
        self.chunk = path.parent / CHUNK

    def append(self, frames: list[tuple[int, float, Any, Any]]) -> int:
        """Write `frames` (step, time_ps, positions A, box A or None); the bytes appended."""
        from MDAnalysis.coordinates.XTC import XTCWriter
        from MDAnalysis.lib.mdamath import triclinic_box

        u = self.universe
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with XTCWriter(str(self.chunk), self.n_atoms) as writer:
                for step, time_ps, positions, box in frames:
                    u.atoms.positions = positions
                    ts = u.trajectory.ts
                    ts.time = time_ps
                    ts.data["step"] = step
                    ts.dimensions = (
                        None if box is None else triclinic_box(*np.asarray(box, dtype=np.float64))
                    )
                    writer.write(u.atoms)
        data = self.chunk.read_bytes()
        with open(self.path, "ab") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        return len(data)

    def close(self) -> None:
        self.chunk.unlink(missing_ok=True)


class RecordingStore:
    """The recordings of one server: start, feed, stop, list, restore after a crash."""

    def __init__(self, directory: Path, read_log: Callable[[str], list[dict[str, Any]]]) -> None:
        self.directory = directory
        self.directory.mkdir(parents=True, exist_ok=True)
        self.read_log = read_log
        self.recordings: dict[str, Recording] = {}
        self.starting: set[str] = set()
        """Sessions whose recording is being started (the web layer claims a session here
        before its first await, so two starts cannot both pass the check)."""

    # ------------------------------------------------------------------ lifecycle

    def restore(self) -> list[Recording]:
        """Load every recording on disk; those a crash left running are finished as
        `interrupted` from the frames that reached the disk."""
        interrupted = []
        for folder in sorted(self.directory.iterdir()):
            if not RECORDING_ID.match(folder.name) or not (folder / "recording.json").is_file():
                continue
            for name in LEFTOVERS:  # what a crash left beside the recording's files
                (folder / name).unlink(missing_ok=True)
            for stray in folder.glob("tmp*.xtc"):  # the chunks' former, random names
                stray.unlink(missing_ok=True)
            try:
                rec = Recording.load(folder)
            except (OSError, ValueError, KeyError) as exc:
                log.warning("recording %s is unreadable (%s); left alone", folder.name, exc)
                continue
            self.recordings[rec.id] = rec
            if rec.running:
                rec.steps = xtc_steps(folder / "frames.xtc", rec.n_atoms)
                rec.frames = len(rec.steps)
                rec.bytes = _size(folder / "frames.xtc")
                self._end(rec, "interrupted", None)
                interrupted.append(rec)
        return interrupted

    def start(
        self,
        session: str,
        topology: p.Topology,
        render_params: p.RenderParams,
        camera: p.Camera | None,
        first_log_id: int,
        stride: int,
        max_bytes: int,
        queue_bytes: int = 128 << 20,
        owner: str | None = None,
    ) -> Recording:
        rec_id = f"r{secrets.token_urlsafe(16)}"
        folder = self.directory / rec_id
        folder.mkdir(parents=True)
        rec = Recording(
            id=rec_id,
            session=session,
            directory=folder,
            n_atoms=topology.n_atoms,
            stride=stride,
            max_bytes=max_bytes,
            render_params=render_params.model_dump(mode="json"),
            camera=camera.model_dump(mode="json") if camera is not None else None,
            first_log_id=first_log_id,
            queue_bytes=queue_bytes,
            owner=owner,
        )
        self._save(rec)
        rec._thread = threading.Thread(
            target=self._write_loop, args=(rec, topology), name=f"recording-{rec_id}", daemon=True
        )
        rec._thread.start()
        self.recordings[rec_id] = rec
        return rec

    def add(
        self,
        rec: Recording,
        step: int,
        time_ps: float,
        positions: npt.NDArray[Any],
        box: npt.NDArray[Any] | None,
    ) -> bool:
        """Take one frame of the session (called on the event loop: only queues it). False when
        the frame was due but skipped, the frames waiting for the disk being at the bound (a
        frame is always taken when none waits, so a recording never stalls)."""
        if not rec.running or positions.shape[0] != rec.n_atoms:
            return True
        rec.received += 1
        if (rec.received - 1) % rec.stride != 0:
            return True
        size = _nbytes(positions, box)
        with rec._queue_lock:
            kept = rec.queued_bytes == 0 or rec.queued_bytes + size <= rec.queue_bytes
            if kept:
                rec.queued_bytes += size
            else:
                rec.skipped += 1
                spans = rec.skipped_spans
                if spans and (not rec._last_kept or len(spans) >= MAX_SKIPPED_SPANS):
                    spans[-1][1:] = [step, spans[-1][2] + 1]  # this run goes on
                else:
                    spans.append([step, step, 1])
            rec._last_kept = kept
        if kept:
            rec._queue.put((step, time_ps, positions, box))
        return kept

    def stop(self, rec: Recording, last_log_id: int | None) -> None:
        """End a recording: the queued frames are written, then the steering span and its
        marks (blocking: call it from a worker thread)."""
        if rec._thread is not None:
            rec._queue.put(None)
            rec._thread.join()
        with rec._lock:
            if rec.running:
                self._end(rec, "finished", last_log_id)

    def delete(self, rec: Recording) -> None:
        if rec.running:
            self.stop(rec, None)
        self.recordings.pop(rec.id, None)
        shutil.rmtree(rec.directory, ignore_errors=True)

    def close(self) -> None:
        """The server stops: every running recording ends as finished."""
        for rec in list(self.recordings.values()):
            if rec.running:
                self.stop(rec, None)

    def get(self, rec_id: str) -> Recording | None:
        return self.recordings.get(rec_id) if RECORDING_ID.match(rec_id) else None

    # ------------------------------------------------------------------ internals

    def _write_loop(self, rec: Recording, topology: p.Topology) -> None:
        appender: _XtcAppender | None = None
        pending: list[tuple[int, float, Any, Any]] = []
        pending_bytes = 0
        last_flush = time.monotonic()
        try:
            while True:
                timeout = max(0.0, FLUSH_S - (time.monotonic() - last_flush))
                ending = False
                try:
                    item = rec._queue.get(timeout=timeout)
                    ending = item is None
                except queue.Empty:
                    item = None
                if item is not None:
                    if appender is None:
                        write_topology_pdb(rec.directory / "topology.pdb", topology, item[2])
                        appender = _XtcAppender(rec.directory / "frames.xtc", rec.n_atoms)
                    pending.append(item)
                    pending_bytes += _nbytes(item[2], item[3])
                # half the queue gathered: write it, so that the other half takes frames
                due = (
                    time.monotonic() - last_flush >= FLUSH_S
                    or len(pending) >= FLUSH_FRAMES
                    or pending_bytes >= rec.queue_bytes // 2
                )
                if pending and (ending or due):
                    assert appender is not None
                    written = appender.append(pending)
                    with rec._queue_lock:
                        rec.queued_bytes -= pending_bytes
                    pending_bytes = 0
                    with rec._lock:
                        rec.frames += len(pending)
                        rec.bytes += written
                        rec.steps.extend(f[0] for f in pending)
                        pending = []
                        if rec.bytes >= rec.max_bytes and rec.running:
                            self._end(rec, "capped", None)
                        else:
                            self._save(rec)
                if due or ending:
                    last_flush = time.monotonic()
                if ending or not rec.running:
                    return
        except Exception as exc:  # a full disk, say: the recording ends with the reason
            log.exception("recording %s failed", rec.id)
            with rec._lock:
                rec.error = f"{type(exc).__name__}: {exc}"
                if rec.running:
                    self._end(rec, "finished", None)
        finally:
            if appender is not None:
                appender.close()

    def _end(self, rec: Recording, state: str, last_log_id: int | None) -> None:
        """Write the steering span and its marks, then the final manifest."""
        entries = [
            e
            for e in self.read_log(rec.session)
            if isinstance(e.get("id"), int)
            and e["id"] > rec.first_log_id
            and (last_log_id is None or e["id"] < last_log_id)
        ]
        if last_log_id is None and entries:
            last_log_id = max(e["id"] for e in entries) + 1
        with open(rec.directory / "steering.jsonl", "w", encoding="utf-8") as fh:
            for e in entries:
                fh.write(json.dumps(e, separators=(",", ":")) + "\n")
        marks = steering_marks(entries, rec.steps)
        (rec.directory / "marks.json").write_text(json.dumps(marks))
        rec.state = state
        rec.stopped = time.time()
        rec.last_log_id = last_log_id
        self._save(rec)

    def _save(self, rec: Recording) -> None:
        tmp = rec.directory / "recording.json.tmp"
        tmp.write_text(json.dumps(rec.manifest(), indent=1))
        os.replace(tmp, rec.directory / "recording.json")


def _nbytes(positions: Any, box: Any) -> int:
    """Memory a queued frame holds."""
    return int(positions.nbytes) + (0 if box is None else int(np.asarray(box).nbytes))


def _size(path: Path) -> int:
    with contextlib.suppress(OSError):
        return path.stat().st_size
    return 0


def xtc_steps(path: Path, n_atoms: int) -> list[int]:
    """The steps of the frames in an XTC file (empty when there is none)."""
    if not path.exists() or path.stat().st_size == 0:
        return []
    import MDAnalysis as mda

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe.empty(n_atoms, trajectory=True)
        u.load_new(str(path))
        return [int(ts.data.get("step", ts.frame)) for ts in u.trajectory]
