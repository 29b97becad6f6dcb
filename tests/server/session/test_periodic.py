"""A session's periodic frames: adenylate kinase in its rhombic dodecahedron (MDAnalysisTests'
TPR/XTC, the protein cut by the box) opens whole and centred, every position the session hands
on is the displayed one, steering the options redisplays the frame, and a pull given in a
fitted frame reaches the engine in its own."""

from __future__ import annotations

import asyncio
import warnings
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import protocol as p
from server.session.session import Session
from server.settings import ServerSettings
from structures.reader import topology_of
from tests.server.session.fakes import PaintBackend, client, run_on_own_loop, sent, services

mda = pytest.importorskip("MDAnalysis")
datafiles = pytest.importorskip("MDAnalysisTests.datafiles")

SETTINGS = ServerSettings(token="t", default_size=(40, 30), stats_interval_s=60.0)


@pytest.fixture(scope="module")
def adk() -> tuple[p.Topology, list[tuple[np.ndarray, np.ndarray]], Any]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(datafiles.TPR, datafiles.XTC)
        frames = [(ts.positions.copy(), ts.triclinic_dimensions.copy()) for ts in u.trajectory[:3]]
    return topology_of(u, guess_bonds=False), frames, u


def boxed(positions: np.ndarray, box: np.ndarray | None, step: int) -> p.Frame:
    return p.Frame(
        step=step,
        time_ps=step * 0.002,
        positions=p.WireArray.from_numpy(positions, "<f4"),
        box=None if box is None else p.WireArray.from_numpy(box, "<f4"),
    )


def run(test: Callable[[Session, PaintBackend], Coroutine[Any, Any, None]], tmp: Path) -> None:
    async def main() -> None:
        backend = PaintBackend()
        session = Session("s", SETTINGS, services(tmp, backend))
        try:
            await test(session, backend)
        finally:
            await session.close()
            session.services.steering_log.close()
            session.services.selections.close()

    run_on_own_loop(main, timeout_s=120)


async def settle(predicate: Callable[[], bool], timeout: float = 60.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not predicate():
        if loop.time() > end:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


def longest_bond(topology: p.Topology, positions: np.ndarray, atoms: np.ndarray) -> float:
    bonds = topology.bonds.to_numpy()
    inside = np.isin(bonds[:, 0], atoms)
    ends = bonds[inside]
    return float(np.linalg.norm(positions[ends[:, 0]] - positions[ends[:, 1]], axis=1).max())


def test_a_solvated_protein_opens_whole_and_centred(tmp_path: Path, adk: Any) -> None:
    topology, frames, u = adk
    protein = np.asarray(u.select_atoms("protein").indices)
    raw, box = frames[0]
    assert longest_bond(topology, raw, protein) > 40.0  # the box cuts it as sent

    async def body(session: Session, backend: PaintBackend) -> None:
        viewer = client("v", "viewer")
        session.attach(viewer)
        session.on_topology(topology)
        session.on_frame(boxed(raw, box, 0))
        await settle(lambda: session.positions is not None)
        shown = session.positions
        assert shown is not None and np.array_equal(session.raw_positions, raw)
        assert longest_bond(topology, shown, protein) < 2.5
        centre = shown[protein].mean(axis=0)
        np.testing.assert_allclose(centre, box.sum(axis=0) / 2, atol=1e-3)
        (request,) = backend.displayed
        assert request.options.mode == "molecules"
        assert request.options.centre is not None and len(request.options.centre) == len(protein)
        # every position handed on is the displayed one: the render, the markers, the cell
        await settle(lambda: bool(backend.requests))
        assert backend.requests[-1].snapshot.positions is shown
        session._send_status()
        cells = [m.cell for m in sent(viewer) if isinstance(m, p.State) and m.cell]
        np.testing.assert_allclose(np.asarray(cells[-1].vectors), box, atol=1e-3)

    run(body, tmp_path)


def test_a_frame_without_a_box_is_drawn_as_sent(tmp_path: Path, adk: Any) -> None:
    topology, frames, _u = adk
    raw, _box = frames[0]

    async def body(session: Session, backend: PaintBackend) -> None:
        session.on_topology(topology)
        session.on_frame(boxed(raw, None, 0))
        assert np.array_equal(session.positions, raw)  # at once, nothing to do
        assert not backend.displayed

    run(body, tmp_path)


def test_steering_the_periodic_options_redisplays_the_frame_while_paused(
    tmp_path: Path, adk: Any
) -> None:
    topology, frames, _u = adk
    raw, box = frames[0]

    async def body(session: Session, backend: PaintBackend) -> None:
        steerer = client("u")
        session.attach(steerer)
        session.on_topology(topology)
        session.on_frame(boxed(raw, box, 0))
        await settle(lambda: session.positions is not None)
        whole = session.positions
        await session.steer(steerer, p.SetRenderParams(seq=3, params={"periodic": "off"}))
        # centred still (center auto), the molecules as the box cut them
        await settle(lambda: session.positions is not whole)
        shown = session.positions
        assert shown is not None
        moved = shown - raw
        np.testing.assert_allclose(moved, np.broadcast_to(moved[0], moved.shape), atol=1e-3)
        await session.steer(steerer, p.SetRenderParams(seq=4, params={"center": "off"}))
        await settle(lambda: session.shown is None)  # as sent, nothing left to do
        assert np.array_equal(session.positions, raw)

    run(body, tmp_path)


def test_centre_and_fit_selections_must_name_fixed_atoms(tmp_path: Path, adk: Any) -> None:
    topology, frames, _u = adk

    async def body(session: Session, backend: PaintBackend) -> None:
        steerer = client("u")
        session.attach(steerer)
        session.on_topology(topology)
        session.on_frame(boxed(*frames[0], 0))
        bad = [
            ({"center": "selection", "center_selection": "around 5 protein"}, "center_selection"),
            ({"fit": "rotation", "fit_selection": "backbone and"}, "fit_selection"),
            ({"fit": "rotation", "fit_selection": "resname NOPE and name XX or bynum"}, "fit_"),
            # atoms it cannot use: none at all, or too few to fix a rotation
            ({"center": "selection", "center_selection": "resname NOPE"}, "center_selection"),
            ({"fit": "translation", "fit_selection": "index 999999"}, "fit_selection"),
            ({"fit": "rotation", "fit_selection": "name CA and resid 1 2"}, "fit_selection"),
        ]
        for seq, (params, field) in enumerate(bad):
            with pytest.raises(p.ProtocolError) as caught:
                await session.steer(steerer, p.SetRenderParams(seq=seq, params=params))
            assert caught.value.path.startswith(f"render_params.params.{field}")
            assert caught.value.code == p.ErrorCode.INVALID_MESSAGE
        message = str(caught.value)
        assert "matches 2 atoms; a rotation fit needs at least 3" in message, message
        ok = {"fit": "translation", "fit_selection": "name CA and resid 1"}  # one atom will do
        await session.steer(steerer, p.SetRenderParams(seq=9, params=ok))
        assert session.render_params.fit == "translation"
        await session.steer(steerer, p.SetRenderParams(seq=10, params={"fit": "off"}))
        assert session.render_params.center == "auto" and session.render_params.fit == "off"

    run(body, tmp_path)


def test_a_pull_in_a_fitted_frame_reaches_the_engine_in_its_own(tmp_path: Path, adk: Any) -> None:
    topology, frames, _u = adk

    async def body(session: Session, backend: PaintBackend) -> None:
        sim, steerer = client("sim", "simulation"), client("u")
        session.attach(sim)
        session.attach(steerer)
        session.on_engine(
            p.EngineInfo(name="test", pull=p.PullLimits(max_force=100.0, max_spring_k=10.0))
        )
        session.on_topology(topology)
        await session.steer(steerer, p.SetRenderParams(seq=1, params={"fit": "rotation"}))
        for step, (raw, box) in enumerate(frames):
            session.on_frame(boxed(raw, box, step))
            await settle(lambda s=step: len(backend.displayed) > s and session.shown is not None)
        await settle(lambda: len(backend.displayed) == len(frames))
        await asyncio.sleep(0.05)
        shown = session.shown
        assert shown is not None
        rotation = shown.rotation
        assert np.abs(rotation - np.eye(3)).max() > 1e-3  # the last frame was rotated
        force = np.array([30.0, -10.0, 5.0])
        await session.steer(steerer, p.Pull(seq=2, atom=5, force=tuple(force)))
        sent_forces = [m for m in sent(sim) if isinstance(m, p.Forces)][-1]
        (atom,) = sent_forces.indices.to_numpy()
        engine = sent_forces.forces.to_numpy()[0]
        assert atom == 5
        # the engine's force, turned by the fit, is the one given in the displayed frame
        np.testing.assert_allclose(rotation @ engine, force, atol=1e-3)
        assert not np.allclose(engine, force, atol=1e-2)

    run(body, tmp_path)
