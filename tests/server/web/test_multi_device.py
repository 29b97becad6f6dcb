"""`serve --gpus`: a session's images rendered across several devices (two CPU devices standing
in for two GPUs), with each device's time in the stats, and the same picture as one device."""

from __future__ import annotations

import io
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

import protocol as p
from server.render.device import resolve_many
from server.render.errors import RenderError
from tests.conftest import make_settings, start_server
from tests.server.peers import Peer, frame, molecule


def image_of(
    settings_dir: Path, atoms: int = 24, **overrides: object
) -> tuple[np.ndarray, p.Stats]:
    server = start_server(make_settings(settings_dir, default_size=(96, 64), **overrides))
    try:
        sim = Peer(server.ws_url, "simulation", server.token, "multi")
        topo, pos = molecule(atoms)
        sim.send(topo)
        sim.send(frame(pos, 0))
        viewer = Peer(server.view_url, "viewer", server.viewer_token, "multi")
        image = viewer.expect(p.Image, where=lambda m: m.still is not False)
        stats = viewer.expect(p.Stats, where=lambda m: m.render_fps > 0)
        health = httpx.get(f"{server.url}/healthz", timeout=30).json()
        assert health["devices"] == (["cpu", "cpu"] if "gpus" in overrides else ["cpu"])
        sim.close()
        viewer.close()
        with Image.open(io.BytesIO(image.data)) as im:
            return np.asarray(im.convert("RGB")), stats
    finally:
        server.stop()


def test_two_devices_stream_the_one_device_picture(tmp_path: Path) -> None:
    one, _ = image_of(tmp_path / "one")
    two, stats = image_of(tmp_path / "two", gpus="cpu,cpu")
    assert sorted(stats.device_ms) == ["cpu#0", "cpu#1"]
    assert stats.device == "cpu,cpu"
    assert np.array_equal(one, two)


def test_a_system_one_device_does_not_hold_is_split_across_the_devices(tmp_path: Path) -> None:
    """`--device-atoms` below the system's size: two devices draw it by slabs of space
    (sort-last), the picture one device with room for it draws; one device alone refuses it,
    saying why."""
    one, _ = image_of(tmp_path / "one", atoms=240)
    two, stats = image_of(tmp_path / "two", atoms=240, gpus="cpu,cpu", device_atoms=150)
    assert sorted(stats.device_ms) == ["cpu#0", "cpu#1"]
    diff = np.abs(one.astype(np.int16) - two.astype(np.int16))
    assert int(diff.max()) <= 3 and float(diff.mean()) < 0.05
    server = start_server(make_settings(tmp_path / "alone", device_atoms=150))
    try:
        sim = Peer(server.ws_url, "simulation", server.token, "multi")
        topo, pos = molecule(240)
        sim.send(topo)
        sim.send(frame(pos, 0))
        viewer = Peer(server.view_url, "viewer", server.viewer_token, "multi")
        error = viewer.expect(p.Error, where=lambda m: "240 atoms" in m.message)
        assert "allows 150" in error.message
        assert error.code == p.ErrorCode.TOO_LARGE  # valid input, too large for this server
        sim.close()
        viewer.close()
    finally:
        server.stop()


def test_a_one_off_render_of_a_system_one_device_does_not_hold(tmp_path: Path) -> None:
    """`POST /api/render` of a system over `--device-atoms`: drawn across two devices by space
    as one roomy device draws it; refused with the reason (422) by one device alone."""
    topo, pos = molecule(240)
    pdb = tmp_path / "helix.pdb"
    at = "HETATM{:5d} {:<4s} MOL A   1    {:8.3f}{:8.3f}{:8.3f}  1.00  0.00          {:>2s}"
    lines = [
        at.format(i + 1, e, x, y, z, e)
        for i, (e, (x, y, z)) in enumerate(zip(topo.elements, pos, strict=True))
    ]
    pdb.write_text("\n".join([*lines, "END", ""]))
    boxed = tmp_path / "boxed.pdb"  # a periodic box: displayed before it is split
    cryst = "CRYST1   80.000   80.000   80.000  90.00  90.00  90.00 P 1           1"
    boxed.write_text("\n".join([cryst, *lines, "END", ""]))

    def post(name: str, params: str, file: Path = pdb, **overrides: object) -> httpx.Response:
        server = start_server(make_settings(tmp_path / name, **overrides))
        try:
            with httpx.Client(base_url=server.url, timeout=120) as c, file.open("rb") as f:
                auth = {"Authorization": f"Bearer {server.token}"}
                data = {"width": "64", "height": "48", "format": "png", "params": params}
                return c.post("/api/render", headers=auth, files={"file": f}, data=data)
        finally:
            server.stop()

    whole = '{"layers": []}'  # every atom, no layers
    want = post("roomy", whole)
    assert want.status_code == 200, want.text
    got = post("split", whole, gpus="cpu,cpu", device_atoms=150)
    assert got.status_code == 200, got.text
    a = np.asarray(Image.open(io.BytesIO(want.content)).convert("RGB"), dtype=np.int16)
    b = np.asarray(Image.open(io.BytesIO(got.content)).convert("RGB"), dtype=np.int16)
    assert int(np.abs(a - b).max()) <= 1
    want = post("roomy-boxed", whole, boxed)
    assert want.status_code == 200, want.text
    got = post("split-boxed", whole, boxed, gpus="cpu,cpu", device_atoms=150)
    assert got.status_code == 200, got.text
    a = np.asarray(Image.open(io.BytesIO(want.content)).convert("RGB"), dtype=np.int16)
    b = np.asarray(Image.open(io.BytesIO(got.content)).convert("RGB"), dtype=np.int16)
    assert int(np.abs(a - b).max()) <= 1
    refused = post("alone", whole, device_atoms=150)
    assert refused.status_code == 422
    assert "240 atoms" in refused.text and "allows 150" in refused.text
    layered = post("layers", "{}", gpus="cpu,cpu", device_atoms=150)  # the opening layers
    assert layered.status_code == 422
    assert "has 240 atoms: layers are drawn on one device" in layered.text


def test_the_gpus_option_names_what_is_wrong() -> None:
    assert resolve_many("cpu, cpu") == ("cpu", "cpu")
    with pytest.raises(RenderError, match="name at least one device"):
        resolve_many(" , ")
    with pytest.raises(RenderError, match="cuda:7"):
        resolve_many("7")
