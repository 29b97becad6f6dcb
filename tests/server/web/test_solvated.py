"""One rule for a solvated system in every entry point: parameters that name no layers get the
default ones (water and ions hidden), so the REST render of a file, a job, a render of a live
session, a movie of it and a movie of a recording all show the protein of MDAnalysisTests'
GRO/XTC (47,681 atoms, 93 % water and ions), and the legend lists what is shown.

Seen from a camera that frames the protein, a picture of the protein alone is mostly
background; the water around it fills the picture."""

from __future__ import annotations

import io
import json
import time
import warnings
import zipfile
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

import protocol as p
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame

pytest.importorskip("MDAnalysisTests")
av = pytest.importorskip("av")
from MDAnalysisTests.datafiles import GRO, XTC  # noqa: E402

AUTH = {"Authorization": "Bearer test-token"}
BACKGROUND = np.asarray(p.RenderParams().background) * 255
SIZE = {"width": "160", "height": "120"}
PROTEIN = 0.75
"""Background share above which an image shows the protein alone (the water box: below 0.4)."""


def background_share(rgb: np.ndarray) -> float:
    return float((np.abs(rgb.astype(np.float64) - BACKGROUND).max(axis=-1) < 16).mean())


def image_share(data: bytes) -> float:
    return background_share(np.asarray(Image.open(io.BytesIO(data)).convert("RGB")))


def first_movie_frame_share(data: bytes) -> float:
    with av.open(io.BytesIO(data)) as container:
        first = next(container.decode(video=0))
        return background_share(first.to_ndarray(format="rgb24"))


def finished(c: httpx.Client, job: str) -> dict[str, Any]:
    deadline = time.monotonic() + 120
    while (info := c.get(f"/api/jobs/{job}", headers=AUTH).json())["state"] in (
        "queued",
        "running",
    ):
        assert time.monotonic() < deadline, info
        time.sleep(0.2)
    assert info["state"] == "done", info
    return info  # type: ignore[no-any-return]


_SYSTEM: list[Any] = []


def solvated() -> tuple[p.Topology, np.ndarray, p.Camera]:
    """The GRO's topology, its positions and a camera that frames its protein (read once)."""
    if not _SYSTEM:
        from server.render.camera import fit_camera
        from structures.reader import load

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            system = load(GRO)
            positions = system.positions(0)
        protein = np.flatnonzero(~np.isin(system.topology.residue_names, ["SOL", "NA+"]))
        camera = fit_camera(positions[protein], 160, 120)
        _SYSTEM.append((system.topology, positions, camera))
    return _SYSTEM[0]  # type: ignore[no-any-return]


def test_a_file_and_a_job_whose_params_name_no_layers_show_the_protein(
    live_server: LiveServer,
) -> None:
    """The docs' first example (`{"sigma_A": 2}`) had turned the solvent hiding off."""
    _, _, camera = solvated()
    with httpx.Client(base_url=live_server.url, timeout=180) as c:

        def render(params: dict[str, Any]) -> float:
            with open(GRO, "rb") as top:
                r = c.post(
                    "/api/render",
                    headers=AUTH,
                    files={"file": ("solvated.gro", top)},
                    data={
                        **SIZE,
                        "params": json.dumps(params),
                        "camera": camera.model_dump_json(),
                        "format": "png",
                    },
                )
            assert r.status_code == 200, r.text
            return image_share(r.content)

        assert render({"sigma_A": 2}) > PROTEIN
        with open(GRO, "rb") as top, open(XTC, "rb") as traj:
            r = c.post(
                "/api/jobs",
                headers=AUTH,
                files=[("topology", ("solvated.gro", top)), ("trajectory", ("solvated.xtc", traj))],
                data={
                    **SIZE,
                    "params": json.dumps({"sigma_A": 2}),
                    "camera": camera.model_dump_json(),
                    "stop": "1",
                },
            )
        assert r.status_code == 202, r.text
        finished(c, r.json()["id"])
        result = c.get(f"/api/jobs/{r.json()['id']}/result", headers=AUTH)
        with zipfile.ZipFile(io.BytesIO(result.content)) as z:
            assert image_share(z.read("frame_000000.png")) > PROTEIN


def test_a_live_solvated_session_renders_films_and_records_its_protein(
    live_server: LiveServer,
) -> None:
    from server.render.layerplan import subset_topology

    whole, everything, _ = solvated()
    # the protein, the ions and the first 2,000 waters (with TIP4P's dummy sites): light enough
    # to film on the CPU, water enough to fill a picture of the protein
    names = np.asarray(whole.residue_names)
    keep = np.flatnonzero(names != "SOL")
    keep = np.union1d(keep, np.flatnonzero(names == "SOL")[: 2000 * 4]).astype(np.int32)
    topology, positions = subset_topology(whole, keep), everything[keep]
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "solv")
    sim.send(topology)
    sim.send(frame(positions, 0))
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "solv")
    shown = viewer.expect(
        p.State, 60, where=lambda m: m.legend is not None and "Na" not in _labels(m.legend)
    )
    assert shown.legend is not None and _labels(shown.legend) == {"C", "H", "N", "O", "S"}
    viewer.expect(p.Image, 120)
    with httpx.Client(base_url=live_server.url, timeout=180) as c:

        def render(params: dict[str, Any]) -> float:
            data = {**SIZE, "session": "solv", "params": json.dumps(params), "format": "png"}
            r = c.post("/api/render", headers=AUTH, data=data)
            assert r.status_code == 200, r.text
            return image_share(r.content)

        assert render({"sigma_A": 2}) > PROTEIN  # the session's layers
        assert render({"sigma_A": 2, "layers": []}) < 0.4  # named: every atom, water too
        rec = c.post("/api/sessions/solv/recordings", headers=AUTH, json={}).json()["id"]
        movie = c.post("/api/sessions/solv/movies", headers=AUTH, data=SIZE).json()["id"]
        sim.send(frame(positions + np.float32(0.01), 10))
        deadline = time.monotonic() + 60
        while c.get(f"/api/recordings/{rec}", headers=AUTH).json()["frames"] < 1:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        c.post(f"/api/recordings/{rec}/stop", headers=AUTH)
        c.delete(f"/api/jobs/{movie}", headers=AUTH)
        finished(c, movie)
        live = c.get(f"/api/jobs/{movie}/result", headers=AUTH).content
        assert first_movie_frame_share(live) > PROTEIN
        body = {"width": 160, "height": 120, "overlay": False, "params": {"sigma_A": 2}}
        replayed = c.post(f"/api/recordings/{rec}/movie", headers=AUTH, json=body).json()["id"]
        finished(c, replayed)
        recorded = c.get(f"/api/jobs/{replayed}/result", headers=AUTH).content
        assert first_movie_frame_share(recorded) > PROTEIN
    sim.close()
    viewer.close()


def _labels(legend: p.Legend) -> set[str]:
    return {entry.label for entry in legend.entries}
