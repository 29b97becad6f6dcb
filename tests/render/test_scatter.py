"""The device-side gather of sort-last's parts (server/render/scatter.py): each device uploads
1/N of a frame, picks every part's atoms out of it and measures it. CPU devices stand in for
GPUs; on a CUDA host the distinct CUDA devices (or one, twice) are used too."""

from __future__ import annotations

import numpy as np
import pytest

from server.render import device as render_device
from server.render.scatter import Scatter
from tests.render.test_multi import multi_devices

DEVICES = [pytest.param(["cpu", "cpu", "cpu"], id="cpu")]
if render_device.cuda_count() > 0:
    DEVICES.append(pytest.param(multi_devices(), id="cuda", marks=pytest.mark.gpu))


@pytest.mark.parametrize("devices", DEVICES)
def test_every_part_gets_its_atoms_in_order_and_the_frame_is_measured(devices: list[str]) -> None:
    rng = np.random.default_rng(7)
    n = 1003
    pos = rng.uniform(-30.0, 30.0, (n, 3)).astype(np.float32)
    axis = 1
    # overlapping parts (slabs with halos), sorted whole-system indices; one part empty
    members = [
        np.flatnonzero(pos[:, axis] < 5.0).astype(np.int32),
        np.flatnonzero(pos[:, axis] > -5.0).astype(np.int32),
        np.zeros(0, dtype=np.int32),
    ]
    members = (members * 3)[: len(devices)]
    scatter = Scatter(devices, members, axis, pos[:, axis].copy())
    moved = pos.copy()
    moved[17, axis] += 2.5
    moved[900, 0] -= 40.0
    found = scatter.send(moved)
    for k, m in enumerate(members):
        got = scatter.inbox[k].numpy()[: len(m)]
        assert np.array_equal(got, moved[m])
    assert found.moved == pytest.approx(2.5, abs=1e-5)
    assert np.allclose(found.lo, moved.min(axis=0)) and np.allclose(found.hi, moved.max(axis=0))
    assert found.bad == 0
    moved[500] = np.nan
    moved[3, 2] = np.inf
    assert scatter.send(moved).bad == 2
    assert all(b > 0 for b in scatter.device_bytes())


def test_a_frame_without_atoms() -> None:
    empty = np.zeros((0, 3), dtype=np.float32)
    scatter = Scatter(["cpu", "cpu"], [np.zeros(0, np.int32)] * 2, 0, empty[:, 0].copy())
    found = scatter.send(empty)
    assert found.bad == 0 and found.moved == 0.0
