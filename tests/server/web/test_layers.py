"""Layers through a real server: a solvated system opens on its protein, selections are
checked (errors name the position, nothing changes), counted on request, follow the frames
when distance-based, and picking names the layer."""

from __future__ import annotations

import io
import json
import time

import httpx
import numpy as np
import pytest
from PIL import Image

import protocol as p
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame, molecule

pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import GRO, XTC

AUTH = {"Authorization": "Bearer test-token"}
BACKGROUND = np.asarray(p.RenderParams().background) * 255


def _background_share(jpeg: bytes) -> float:
    img = np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")).astype(np.float64)
    return float((np.abs(img - BACKGROUND).max(axis=-1) < 12).mean())


def test_a_solvated_replay_opens_on_the_protein(live_server: LiveServer) -> None:
    """MDAnalysisTests' GRO/XTC: 47,681 atoms, 93 % water and ions."""
    with httpx.Client(base_url=live_server.url, timeout=180) as c:
        with open(GRO, "rb") as top, open(XTC, "rb") as traj:
            r = c.post(
                "/api/replays",
                headers=AUTH,
                files=[("topology", ("solvated.gro", top)), ("trajectory", ("solvated.xtc", traj))],
                data={"fps": "5"},
            )
        assert r.status_code == 201, r.text
        name = r.json()["session"]
        deadline = time.monotonic() + 120
        while c.get(f"/api/sessions/{name}", headers=AUTH).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, name)
        state = viewer.expect(
            p.State, 120, where=lambda m: bool(m.render_params and m.render_params.layers)
        )
        assert state.render_params is not None
        layers = state.render_params.layers
        assert [(x.name, x.selection) for x in layers] == [("polymer", "protein or nucleic")]
        viewer.expect(p.Image, 120)
        # the camera (fitted before the first image) frames the protein (3,341 atoms), not the
        # water box around it
        cam = live_server.app_state.sessions.get(name).camera
        assert cam is not None and cam.distance < 180  # 149 A for the protein, 233 for all

        def share(params: str | None) -> float:
            data = {"session": name, "camera": cam.model_dump_json(), "format": "jpeg"}
            data.update(width="160", height="120")
            if params is not None:
                data["params"] = params
            r = c.post("/api/render", headers=AUTH, data=data)
            assert r.status_code == 200, r.text
            return _background_share(r.content)

        protein = share(None)  # the session's own parameters: its default layers
        water = share(json.dumps({"layers": []}))  # every atom: a block of water
        assert protein > 0.75, f"background share of the protein view {protein:.2f}"
        assert water < 0.4, f"background share of the whole system {water:.2f}"
        viewer.close()
        c.delete(f"/api/replays/{name}", headers=AUTH)


def test_layer_selections_are_checked_counted_and_picked(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "lay")
    topo, pos = molecule(24)
    sim.send(topo)
    sim.send(frame(pos, 0))
    steerer = Peer(live_server.view_url, "steerer", live_server.token, "lay")
    steerer.expect(p.Image, 60)
    # counting a selection changes nothing; a bad one says where it is wrong
    s5 = steerer.send(p.Select(text="resname ALA GLU"))
    got = steerer.expect(p.Selected, where=lambda m: m.ref == s5)
    want = sum(r in ("ALA", "GLU") for r in topo.residue_names)
    assert got.count == want and got.error == "" and not got.dynamic
    s6 = steerer.send(p.Select(text="name CA and (resid 4"))
    bad = steerer.expect(p.Selected, where=lambda m: m.ref == s6)
    assert bad.count is None and bad.position == len("name CA and (resid 4") and bad.error
    s7 = steerer.send(p.Select(text="around 3 resid 1"))
    near = steerer.expect(p.Selected, where=lambda m: m.ref == s7)
    assert near.dynamic and near.count is not None and near.count > 0
    # a layer list with an invalid selection is refused whole
    layers = [
        {"name": "all", "selection": "all", "opacity": 0.5},
        {"name": "oops", "selection": "protien"},
    ]
    s8 = steerer.send(p.SetRenderParams(params={"layers": layers}))
    err = steerer.expect(p.Error, where=lambda m: m.ref == s8)
    assert err.path == "render_params.params.layers.1.selection"
    assert "character 1" in err.message and "protien" in err.message
    # a valid one is shared with every viewer, and the picture follows it
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "lay")
    viewer.expect(p.Image, 60)
    good = [
        {"name": "first", "selection": "index 0:11"},
        {"name": "rest", "selection": "index 12:23", "sigma_A": 0.8},
    ]
    steerer.send(p.SetRenderParams(params={"layers": good}))
    shared = viewer.expect(
        p.State,
        30,
        where=lambda m: m.render_params is not None and len(m.render_params.layers) == 2,
    )
    assert shared.render_params is not None
    assert shared.render_params.layers[1].sigma_A == 0.8
    # a viewer cannot change the layers
    s10 = viewer.send(p.SetRenderParams(params={"layers": []}))
    denied = viewer.expect(p.Error, where=lambda m: m.ref == s10)
    assert denied.code == p.ErrorCode.FORBIDDEN
    # picking names the layer of the atom under the pixel
    s11 = steerer.send(p.View(width=64, height=48))
    steerer.expect(p.Image, 60, where=lambda m: m.ref == s11)
    names = set()
    for x, y in [(32, 24), (20, 24), (44, 24), (32, 16), (32, 32), (26, 20), (38, 28)]:
        sent = steerer.send(p.Pick(x=x, y=y))
        hit = steerer.expect(p.Picked, where=lambda m, s=sent: m.ref == s)
        if hit.atom is not None:
            assert hit.layer == ("first" if hit.atom <= 11 else "rest")
            names.add(hit.layer)
    assert names
    sim.close()
    steerer.close()
    viewer.close()


def test_rest_renders_and_jobs_check_layers(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "restlay")
    topo, pos = molecule(24)
    sim.send(topo)
    sim.send(frame(pos, 0))
    with httpx.Client(base_url=live_server.url, timeout=60) as c:
        deadline = time.monotonic() + 30
        while c.get("/api/sessions/restlay", headers=AUTH).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        time.sleep(0.3)
        base = {"session": "restlay", "width": "64", "height": "48", "format": "png"}
        bad = c.post(
            "/api/render",
            headers=AUTH,
            data={**base, "params": json.dumps({"layers": [{"selection": "name CA and ("}]})},
        )
        assert bad.status_code == 422
        assert "layers.0.selection" in bad.json()["detail"]
        typo = c.post(
            "/api/render",
            headers=AUTH,
            data={**base, "params": json.dumps({"layers": [{"selection": "all", "sigma": 2}]})},
        )
        assert typo.status_code == 422 and "params.layers.0.sigma" in typo.json()["detail"]
        one = c.post(
            "/api/render",
            headers=AUTH,
            data={**base, "params": json.dumps({"layers": [{"selection": "index 0:5"}]})},
        )
        full = c.post(
            "/api/render", headers=AUTH, data={**base, "params": json.dumps({"layers": []})}
        )
        assert one.status_code == 200 and full.status_code == 200
        assert one.content != full.content
        job = c.post(
            "/api/jobs",
            headers=AUTH,
            data={"dataset": "x.pdb", "params": json.dumps({"layers": [{"selection": "byres ("}]})},
        )
        assert job.status_code == 422 and "layers.0.selection" in job.json()["detail"]
    sim.close()
