"""The recording store without a server: what it writes, its stride, its size cap."""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import MDAnalysis as mda
import numpy as np

import protocol as p
from server.pipeline.recordings import RecordingStore, write_topology_pdb
from tests.server.peers import molecule


def store(tmp_path: Path, log: list[dict] | None = None) -> RecordingStore:
    return RecordingStore(tmp_path / "recordings", lambda session: list(log or []))


def test_frames_topology_and_steering_span_are_written(tmp_path: Path) -> None:
    topo, pos = molecule(24)
    log = [
        {"id": 1, "event": "recording_started", "sim_step": 0},
        {"id": 2, "event": "sim_params", "sim_step": 25, "changes": {"temperature_K": 350.0}},
        {"id": 3, "event": "applied", "ref": 2, "step": 30},
        {"id": 4, "event": "recording_stopped", "sim_step": 60},
        {"id": 5, "event": "sim_params", "sim_step": 70, "changes": {"temperature_K": 300.0}},
    ]
    s = store(tmp_path, log)
    rec = s.start("demo", topo, p.RenderParams(), None, 1, stride=2, max_bytes=1 << 30)
    sent = []
    for i in range(10):
        x = (pos + i).astype(np.float32)
        s.add(rec, i * 10, i * 0.02, x, None)
        sent.append(x)
    s.stop(rec, last_log_id=4)
    assert rec.state == "finished" and rec.frames == 5  # every second frame
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(str(rec.directory / "topology.pdb"), str(rec.directory / "frames.xtc"))
    assert list(u.atoms.names) == topo.names
    assert list(u.atoms.resnames) == topo.residue_names
    assert len(u.bonds) == topo.bonds.shape[0]
    assert [int(ts.data["step"]) for ts in u.trajectory] == [0, 20, 40, 60, 80]
    for ts, x in zip(u.trajectory, sent[::2], strict=True):
        assert np.abs(ts.positions - x).max() <= 0.0051
    steering = rec.steering()
    assert [e["id"] for e in steering] == [2, 3]  # between the start and stop marks
    assert rec.marks() == [
        {"id": 2, "step": 30, "frame": 2, "kind": "sim_params", "text": "temperature_K 350.0"}
    ]
    manifest = json.loads((rec.directory / "recording.json").read_text())
    assert manifest["frames"] == 5 and manifest["state"] == "finished"


def test_a_recording_stops_at_its_size_cap(tmp_path: Path) -> None:
    topo, pos = molecule(24)
    s = store(tmp_path)
    rec = s.start("demo", topo, p.RenderParams(), None, 0, stride=1, max_bytes=1)
    s.add(rec, 0, 0.0, pos.astype(np.float32), None)
    deadline = time.monotonic() + 10
    while rec.state == "recording" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert rec.state == "capped" and rec.frames == 1
    s.add(rec, 10, 0.02, pos.astype(np.float32), None)  # ignored from now on
    s.stop(rec, None)
    assert rec.state == "capped" and rec.frames == 1


def test_frames_of_another_size_are_not_recorded(tmp_path: Path) -> None:
    topo, pos = molecule(24)
    s = store(tmp_path)
    rec = s.start("demo", topo, p.RenderParams(), None, 0, stride=1, max_bytes=1 << 20)
    s.add(rec, 0, 0.0, np.zeros((5, 3), np.float32), None)  # a new topology's frame
    s.add(rec, 1, 0.0, pos.astype(np.float32), None)
    s.stop(rec, None)
    assert rec.frames == 1
    assert s.restore() == []  # ended cleanly: nothing to finish at the next start


def test_the_topology_is_written_as_mdanalysis_writes_it(tmp_path: Path) -> None:
    """The CONECT records are made from the bond array (MDAnalysis's writer took 32 s for the
    bonds of 47,681 atoms): they are MDAnalysis's own, byte for byte, and no partial file is
    left beside the topology."""
    topo, pos = molecule(40)
    bonds = topo.bonds.to_numpy()
    extra = np.array([[5, 2], [2, 5], [0, 39], [39, 0], [7, 30]])  # reversed and repeated
    topo = topo.model_copy(
        update={"bonds": p.WireArray.from_numpy(np.concatenate([bonds, extra]), "<i4")}
    )
    write_topology_pdb(tmp_path / "topology.pdb", topo, pos)
    ours = (tmp_path / "topology.pdb").read_bytes()
    assert sorted(x.name for x in tmp_path.iterdir()) == ["topology.pdb"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(str(tmp_path / "topology.pdb"))
        u.atoms.write(str(tmp_path / "theirs.pdb"), bonds="conect")
    theirs = (tmp_path / "theirs.pdb").read_bytes()
    conect = [line for line in ours.splitlines() if line.startswith(b"CONECT")]
    assert conect and conect == [x for x in theirs.splitlines() if x.startswith(b"CONECT")]
    assert ours.splitlines()[-1] == b"END" and ours.index(conect[-1]) > ours.rindex(b"ATOM")
    assert len(u.bonds) == len({tuple(sorted(b)) for b in np.concatenate([bonds, extra])})
