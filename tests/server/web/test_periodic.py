"""Periodic boxes through a real server, on MDAnalysisTests' solvated adenylate kinase (GROMACS
TPR/XTC, a rhombic dodecahedron that cuts the protein): replayed by a replay child as a
dashboard sees it (the bonds the box cuts whole in every position the viewer gets, the box as a
cell, `periodic: off` shows them cut again), rendered by REST (one piece, the cell's outline)
and by a job (every frame fitted onto the first, outlined)."""

from __future__ import annotations

import io
import json
import time
import warnings
import zipfile

import httpx
import numpy as np
import pytest
from PIL import Image

import protocol as p
from server.pipeline.overlay import CELL, cell_edges
from server.render.camera import camera_frame, project
from tests.conftest import LiveServer
from tests.server.peers import Peer

mda = pytest.importorskip("MDAnalysis")
pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import TPR, XTC  # noqa: E402

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
        with open(TPR, "rb") as top, open(XTC, "rb") as traj:
            r = c.post(
                "/api/replays",
                headers=AUTH,
                files=[("topology", ("adk.tpr", top)), ("trajectory", ("adk.xtc", traj))],
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


def finished_job(live_server: LiveServer, job: str) -> dict[str, object]:
    """The job's record once it is done or failed (within three minutes)."""
    deadline = time.monotonic() + 180
    while (info := httpx.get(f"{live_server.url}/api/jobs/{job}", headers=AUTH).json())[
        "state"
    ] not in ("done", "failed"):
        assert time.monotonic() < deadline, info
        time.sleep(0.2)
    return dict(info)


def _box() -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.asarray(mda.Universe(TPR).trajectory.ts.triclinic_dimensions, dtype=np.float64)


def _camera(box: np.ndarray, distance: float) -> p.Camera:
    return p.Camera(target=tuple(box.sum(axis=0) / 2), distance=distance)


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int64)


def _pieces(png: bytes) -> int:
    """Separate drawn parts of the picture (the background left out; specks ignored)."""
    from scipy import ndimage

    img = _pixels(png)
    background = np.asarray(p.RenderParams().background) * 255
    labels, _count = ndimage.label(np.abs(img - background).max(axis=-1) > 12)
    sizes = np.bincount(labels.ravel())[1:]
    return int((sizes >= 4).sum())


def _outlined(png: bytes, camera: p.Camera, cell: p.Cell) -> int:
    """How many of the cell's edges in view have the outline's colour at their middle."""
    img = _pixels(png)
    h, w = img.shape[:2]
    view = camera_frame(camera, w, h)
    found = 0
    for a, b in cell_edges(cell):
        x, y, z = project(view, np.array([(a + b) / 2]))[0]
        if z <= 0 or not (1 <= x < w - 1 and 1 <= y < h - 1):
            continue
        near = img[int(y) - 1 : int(y) + 2, int(x) - 1 : int(x) + 2].reshape(-1, 3)
        found += int((np.abs(near - np.asarray(CELL[:3])).max(axis=1) <= 2).any())
    return found


def test_a_file_renders_whole_centred_and_with_its_cell(live_server: LiveServer) -> None:
    """REST renders of the GRO: the protein in one piece at the box's centre (drawn in two far
    apart as read), and the box's outline where the camera sees its edges."""
    box = _box()
    camera = _camera(box, 320.0)
    protein = [{"name": "protein", "selection": "protein"}]

    def render(**params: object) -> bytes:
        with open(TPR, "rb") as f:
            r = httpx.post(
                f"{live_server.url}/api/render",
                headers=AUTH,
                files={"file": ("adk.tpr", f)},
                data={"params": json.dumps({"layers": protein, **params}),
                      "camera": camera.model_dump_json(), "width": "160", "height": "120"},
                timeout=180,
            )  # fmt: skip
        assert r.status_code == 200, r.text
        return r.content

    whole = render()
    cut = render(periodic="off", center="off")
    assert _pieces(whole) == 1 and _pieces(cut) >= 2, (_pieces(whole), _pieces(cut))
    cell = p.Cell(origin=(0.0, 0.0, 0.0), vectors=tuple(tuple(v) for v in box))
    assert _outlined(render(show_cell=True), camera, cell) >= 8  # of 12 edges
    assert _outlined(whole, camera, cell) == 0  # no outline asked for
    bad = httpx.post(
        f"{live_server.url}/api/render",
        headers=AUTH,
        files={"file": ("adk.tpr", TPR_BYTES())},
        data={"params": json.dumps({"fit": "rotation", "fit_selection": "around 3 protein"})},
        timeout=60,
    )
    assert bad.status_code == 422 and "params.fit_selection" in bad.text, bad.text


def TPR_BYTES() -> bytes:  # noqa: N802
    with open(TPR, "rb") as f:
        return f.read()


def test_a_job_draws_every_frame_fitted_and_outlined(live_server: LiveServer) -> None:
    """A job fits every frame onto the file's first by the CA atoms and outlines the box as
    displayed: the first frame's box is the file's (it is the reference), and every frame has
    its outline."""
    box = _box()
    camera = _camera(box, 200.0)
    params = {
        "layers": [{"name": "protein", "selection": "protein"}],
        "fit": "rotation",
        "fit_selection": "name CA",
        "show_cell": True,
    }
    with open(TPR, "rb") as top, open(XTC, "rb") as traj:
        r = httpx.post(
            f"{live_server.url}/api/jobs",
            headers=AUTH,
            files=[("topology", ("adk.tpr", top)), ("trajectory", ("adk.xtc", traj))],
            data={"start": "0", "stop": "10", "stride": "9", "width": "160", "height": "120",
                  "output": "zip", "params": json.dumps(params),
                  "camera": camera.model_dump_json()},
            timeout=180,
        )  # fmt: skip
    assert r.status_code == 202, r.text
    job = r.json()["id"]
    info = finished_job(live_server, job)
    assert info["state"] == "done", info
    body = httpx.get(f"{live_server.url}/api/jobs/{job}/result", headers=AUTH, timeout=60)
    z = zipfile.ZipFile(io.BytesIO(body.content))
    pngs = [z.read(name) for name in sorted(z.namelist())]
    assert len(pngs) == 2  # frames 0 and 9
    cell = p.Cell(origin=(0.0, 0.0, 0.0), vectors=tuple(tuple(v) for v in box))
    assert _outlined(pngs[0], camera, cell) >= 8
    for png in pngs:
        outline = (np.abs(_pixels(png) - np.asarray(CELL[:3])).max(axis=-1) <= 2).sum()
        assert outline > 150, outline
    bad = httpx.post(
        f"{live_server.url}/api/jobs",
        headers=AUTH,
        files=[("topology", ("adk.tpr", TPR_BYTES()))],
        data={"params": json.dumps({"center": "selection", "center_selection": "around 5 x"})},
        timeout=60,
    )
    assert bad.status_code == 422 and "params.center_selection" in bad.text, bad.text
    for params, field, words in (
        ({"center": "selection", "center_selection": "resname NOPE"}, "center_selection",
         "matches no atom"),
        ({"fit": "rotation", "fit_selection": "index 0"}, "fit_selection",
         "a rotation fit needs at least 3"),
    ):  # fmt: skip
        bad = httpx.post(
            f"{live_server.url}/api/render",
            headers=AUTH,
            files=[("file", ("adk.tpr", TPR_BYTES()))],
            data={"params": json.dumps(params), "width": "32", "height": "24"},
            timeout=60,
        )
        assert bad.status_code == 422, bad.text
        assert f"params.{field}" in bad.text and words in bad.text, bad.text


def test_a_job_over_a_trajectory_damaged_at_its_end_keeps_the_frames_before(
    live_server: LiveServer, tmp_path: object
) -> None:
    """An XTC cut short: the frames before the damage are rendered, the job is done and marked
    partial, its warning names the frame (it had failed, losing every frame)."""
    with open(XTC, "rb") as fh:
        data = fh.read()
    cut = data[: int(len(data) * 0.85)]  # frames 0-7 whole, frame 8 cut
    with open(TPR, "rb") as top:
        r = httpx.post(
            f"{live_server.url}/api/jobs",
            headers=AUTH,
            files=[("topology", ("adk.tpr", top)), ("trajectory", ("cut.xtc", cut))],
            data={"width": "64", "height": "48", "output": "zip",
                  "params": json.dumps({"layers": [{"name": "p", "selection": "protein"}]})},
            timeout=180,
        )  # fmt: skip
    assert r.status_code == 202, r.text
    job = r.json()["id"]
    info = finished_job(live_server, job)
    assert info["state"] == "done" and info["partial"], info
    assert "frame 8 could not be read" in info["warning"], info
    body = httpx.get(f"{live_server.url}/api/jobs/{job}/result", headers=AUTH, timeout=60)
    assert len(zipfile.ZipFile(io.BytesIO(body.content)).namelist()) == 8
