"""`serve --gpus`: a session's images rendered across several devices (two CPU devices standing
in for two GPUs), with each device's time in the stats, and the same picture as one device."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import protocol as p
from server.render.device import resolve_many
from server.render.errors import RenderError
from tests.conftest import make_settings, start_server
from tests.server.peers import Peer, frame, molecule


def image_of(settings_dir: Path, **overrides: object) -> tuple[np.ndarray, p.Stats]:
    server = start_server(make_settings(settings_dir, default_size=(96, 64), **overrides))
    try:
        sim = Peer(server.ws_url, "simulation", server.token, "multi")
        topo, pos = molecule()
        sim.send(topo)
        sim.send(frame(pos, 0))
        viewer = Peer(server.view_url, "viewer", server.viewer_token, "multi")
        image = viewer.expect(p.Image, where=lambda m: m.still is not False)
        stats = viewer.expect(p.Stats, where=lambda m: m.render_fps > 0)
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


def test_the_gpus_option_names_what_is_wrong() -> None:
    assert resolve_many("cpu, cpu") == ("cpu", "cpu")
    with pytest.raises(RenderError, match="name at least one device"):
        resolve_many(" , ")
    with pytest.raises(RenderError, match="cuda:7"):
        resolve_many("7")
