"""Periodic boxes through a real server: MDAnalysisTests' solvated adenylate kinase (GRO/XTC,
no bonds in the file: guessed across the box) replayed by a replay child, as a dashboard sees
it: the bonds the box cuts are whole in every position the viewer gets, the box comes as a
cell, and steering `periodic` to `off` shows them cut again."""

from __future__ import annotations

import time
import warnings

import httpx
import numpy as np
import pytest

import protocol as p
from tests.conftest import LiveServer
from tests.server.peers import Peer

mda = pytest.importorskip("MDAnalysis")
pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import GRO, TPR, XTC  # noqa: E402

AUTH = {"Authorization": "Bearer test-token"}


def cut_bond() -> tuple[int, int, set[int]]:
    """A protein bond the box cuts (its atoms far apart as sent), and the frames it is cut in."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(TPR, XTC)
        bonds = u.select_atoms("protein").bonds.indices
        cut = []
        for _ts in u.trajectory:
            x = u.atoms.positions
            cut.append(np.linalg.norm(x[bonds[:, 0]] - x[bonds[:, 1]], axis=1) > 40.0)
    counts = np.sum(cut, axis=0)
    best = int(np.argmax(counts))
    a, b = bonds[best]
    return int(a), int(b), {i for i, frame in enumerate(cut) if frame[best]}


def test_a_replayed_solvated_protein_is_shown_whole_with_its_cell(
    live_server: LiveServer,
) -> None:
    a, b, frames = cut_bond()
    assert frames
    with httpx.Client(base_url=live_server.url, timeout=180) as c:
        with open(GRO, "rb") as top, open(XTC, "rb") as traj:
            r = c.post(
                "/api/replays",
                headers=AUTH,
                files=[("topology", ("adk.gro", top)), ("trajectory", ("adk.xtc", traj))],
                data={"fps": "20", "loop": "true"},
            )
        assert r.status_code == 201, r.text
        name = r.json()["session"]
        deadline = time.monotonic() + 120
        while c.get(f"/api/sessions/{name}", headers=AUTH).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        viewer = Peer(live_server.view_url, "steerer", live_server.token, name)
        try:
            viewer.send(p.View(width=64, height=48, track=[a, b]))

            def distance(t: p.Tracked) -> float:
                return float(np.linalg.norm(np.subtract(t.positions[0], t.positions[1])))

            for _ in range(2):  # frames in which the box cuts the bond: whole
                tracked = viewer.expect(
                    p.Tracked, 120, where=lambda m: len(m.positions) == 2 and m.step in frames
                )
                assert distance(tracked) < 2.0, tracked
            state = viewer.expect(p.State, 60, where=lambda m: m.cell is not None)
            assert state.cell is not None
            vectors = np.asarray(state.cell.vectors)
            lengths = np.linalg.norm(vectors, axis=1)
            assert np.ptp(lengths) < 0.01 and 79.0 < lengths[0] < 81.0  # the dodecahedron's
            cosines = [vectors[i] @ vectors[j] / lengths[0] ** 2 for i, j in ((1, 2), (0, 2))]
            np.testing.assert_allclose(cosines, [0.5, 0.5], atol=1e-3)  # 60 degree angles
            seq = viewer.send(p.SetRenderParams(params={"periodic": "off", "center": "off"}))
            viewer.expect(p.State, 30, where=lambda m: m.ref == seq)
            viewer.expect(p.Tracked, 60, where=lambda m: len(m.positions) == 2)
            far = viewer.expect(
                p.Tracked, 120, where=lambda m: len(m.positions) == 2 and m.step in frames
            )
            assert distance(far) > 40.0  # as the replay sends it: cut by the box
        finally:
            viewer.close()
            c.delete(f"/api/replays/{name}", headers=AUTH)
