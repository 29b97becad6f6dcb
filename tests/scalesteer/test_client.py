"""`scalesteer.Client` and `Session` against a real server on a loopback port: steering checked
by the protocol's models, the server's refusals as exceptions with its code and path, the
state, pictures as arrays, subscriptions, recordings and batch jobs."""

from __future__ import annotations

import threading
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import scalesteer
from protocol import ErrorCode, SimStatus
from scalesteer import ScalesteerError
from tests.conftest import LiveServer


def test_render_params_are_steered_and_the_state_follows(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    other = client.session(session.name)  # a second steerer of the same session
    params = session.set(sigma_A=3.0, lighting={"ambient": 0.5})
    assert params.sigma_A == 3.0 and params.lighting.ambient == 0.5
    assert params.lighting.diffuse == 0.7  # a nested patch changes only what it names
    other.wait_for(lambda s: s.render_params.sigma_A == 3.0, timeout=10)
    assert [e["changes"] for e in session.log() if e["event"] == "render_params"][-1] == {
        "sigma_A": 3.0,
        "lighting.ambient": 0.5,
    }


def test_a_bad_value_is_refused_before_anything_is_sent(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    with pytest.raises(ScalesteerError) as refused:
        session.set(sigma_A=-1.0)
    assert refused.value.code is ErrorCode.INVALID_MESSAGE
    assert refused.value.path == "render_params.params.sigma_A"
    with pytest.raises(ScalesteerError) as unknown:
        session.control("jump")
    assert unknown.value.path == "control.action"
    with pytest.raises(ScalesteerError) as typo:  # a key no field has is named, not dropped
        session.set(sigmaa=2.0)
    assert typo.value.path == "render_params.params.sigmaa" and "unknown field" in str(typo.value)
    with pytest.raises(ScalesteerError) as nested:
        session.set(lighting={"ambiant": 0.4})
    assert nested.value.path == "render_params.params.lighting.ambiant"
    with pytest.raises(TypeError, match="a list of layers"):
        session.set_layers("protein")  # type: ignore[arg-type]
    assert not [e for e in session.log() if e["event"] == "render_params"]


def test_the_servers_refusal_carries_its_code_and_path(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    before = session.layers
    with pytest.raises(ScalesteerError) as refused:
        session.set_layers([{"name": "bad", "selection": "protein and"}])
    err = refused.value
    assert err.code is ErrorCode.INVALID_MESSAGE
    assert err.path == "render_params.params.layers.0.selection"
    assert "character 12" in err.message and err.ref is not None
    assert session.layers == before, "nothing changed"
    with pytest.raises(ScalesteerError) as replay:  # the simulation refuses what it cannot do
        session.set_sim(temperature_K=350.0)
    assert replay.value.code is ErrorCode.INVALID_MESSAGE and "temperature_K" in str(replay.value)


def test_rest_refusals_carry_the_http_status_and_the_code(
    live_server: LiveServer, client: scalesteer.Client
) -> None:
    wrong = scalesteer.connect(live_server.url, "not-the-token")
    with pytest.raises(ScalesteerError) as unauthorized:
        wrong.sessions()
    assert unauthorized.value.status == 401 and unauthorized.value.code is ErrorCode.UNAUTHORIZED
    with pytest.raises(ScalesteerError) as refused:  # the WebSocket says so too
        wrong.session("x")
    assert refused.value.code is ErrorCode.UNAUTHORIZED and refused.value.path == "hello.token"
    wrong.close()
    empty = client.session("empty")
    with pytest.raises(ScalesteerError) as no_frame:
        empty.image(64, 48)
    assert no_frame.value.status == 409 and no_frame.value.code is ErrorCode.CONFLICT


def test_a_viewer_token_watches_but_may_not_steer(
    live_server: LiveServer, client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    # the dashboard's read-only link as it is: its role=viewer is taken from it
    viewer = scalesteer.connect(f"{live_server.url}/?role=viewer&token={live_server.viewer_token}")
    assert viewer.role == "viewer"
    watched = viewer.session(session.name)
    assert watched.sim.n_atoms == 3341
    with pytest.raises(ScalesteerError) as refused:
        watched.set(sigma_A=2.0)
    assert refused.value.code is ErrorCode.FORBIDDEN
    with pytest.raises(ScalesteerError) as opening:  # was "not_found: no session named ..."
        viewer.open(small_universe, frame=0)
    assert opening.value.code is ErrorCode.FORBIDDEN and "viewer cannot open" in str(opening.value)
    viewer.close()
    # the viewer token asking to steer: said so, not "missing or wrong token"
    steering = scalesteer.connect(live_server.url, live_server.viewer_token)
    with pytest.raises(ScalesteerError) as read_only:
        steering.session(session.name)
    assert read_only.value.code is ErrorCode.FORBIDDEN and "read-only" in str(read_only.value)
    steering.close()


def test_an_atom_group_and_one_frame(client: scalesteer.Client, universe: Any) -> None:
    # (the whole solvated universe opens in tests/browser/test_notebook.py and the examples)
    protein = client.open(universe.select_atoms("protein"), frame=4)
    assert protein.sim.n_atoms == 3341
    # the trajectory's frame 4 alone (the XTC's frames are 100 ps apart)
    protein.wait_for(lambda s: s.sim.time_ps == pytest.approx(400.0), timeout=10)
    assert universe.trajectory.ts.frame == 0, "the user's universe keeps its own frame"
    picture = protein.image(96, 72)
    assert picture.shape == (72, 96, 3) and picture.std() > 5
    water = client.open(universe.select_atoms("resname SOL and index 40000:40299"), frame=0)
    assert water.sim.n_atoms == 300
    assert {s["id"] for s in client.sessions()} >= {protein.name, water.name}


def test_images_and_observables_are_delivered_to_callbacks(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, fps=20, loop=True)
    images: list[scalesteer.StreamedImage] = []
    statuses: list[SimStatus] = []
    got = threading.Event()

    def on_image(image: scalesteer.StreamedImage) -> None:
        images.append(image)
        if len(images) >= 3:
            got.set()

    with session.on_image(on_image, 80, 60), session.on_observables(statuses.append):
        assert got.wait(60)
    # live images on the CPU may be shrunk to the frame budget, never grown past the view
    assert all(i.size[0] <= 80 and i.size[1] <= 60 for i in images)
    assert images[-1].array().shape[:2] == images[-1].size[::-1]
    assert images[-1].array().std() > 5
    frame_ids = [i.frame_id for i in images]
    assert frame_ids == sorted(frame_ids) and len(set(frame_ids)) == len(frame_ids)
    assert len({s.step for s in statuses}) >= 2, "the replay's steps advance"
    paused = session.pause()
    assert paused.ok and paused.step is not None
    session.wait_for(lambda s: s.sim.state == "paused", timeout=10)
    seek = session.control("seek", frame=7)
    assert seek.applied["frame"] == 7


def test_a_recording_and_a_batch_job(
    client: scalesteer.Client, small_universe: Any, tmp_path: Path
) -> None:
    from MDAnalysisTests.datafiles import DCD, PSF

    session = client.open(small_universe, fps=30)
    recording = session.record()
    session.wait_for(lambda s: s.sim.step >= 5, timeout=30)
    session.set(sigma_A=2.5)
    recording.stop()
    assert recording.state == "finished" and recording.frames >= 1
    assert any(m.get("kind") == "render" for m in recording.marks), recording.marks
    saved = recording.download(tmp_path / "run.zip")
    assert any(n.endswith("/frames.xtc") for n in zipfile.ZipFile(saved).namelist())

    seen: list[tuple[str, tuple[int, int]]] = []
    job = client.submit_job(
        PSF, DCD, output="zip", width=64, height=48, stop=6, stride=3, params={"sigma_A": 2.0}
    )
    job.wait(timeout=120, progress=lambda j: seen.append((j.state, j.progress)))
    assert seen[-1] == ("done", (2, 2))
    out = job.download(tmp_path / "frames.zip")
    assert len([n for n in zipfile.ZipFile(out).namelist() if n.endswith(".png")]) == 2
    assert job.cancel().state == "done"  # an ended job is left as it is: it had been deleted
    job.download(tmp_path / "again.zip")
    job.delete()
    with pytest.raises(ScalesteerError) as gone:
        job.refresh()
    assert gone.value.code is ErrorCode.NOT_FOUND
    with pytest.raises(ScalesteerError) as bad:
        client.submit_job(PSF, DCD, params={"sigma_A": 99})
    assert bad.value.path == "params.sigma_A"  # checked here, before the upload


def test_params_send_only_what_they_name_so_a_file_still_opens_on_its_molecule(
    client: scalesteer.Client, live_server: LiveServer
) -> None:
    """`params` had been sent as the whole model, `layers: []` with it (every atom): a
    solvated system came out as a box of water, where the same request over REST opened on
    the protein. And a misspelt key was dropped, where the server names it."""
    import httpx
    from MDAnalysisTests.datafiles import GRO

    from scalesteer.images import array

    size = {"width": "48", "height": "36"}
    mine = client.render(GRO, 48, 36, params={"sigma_A": 2.0})
    with httpx.Client(base_url=live_server.url, timeout=300) as c, open(GRO, "rb") as f:
        answer = c.post(
            "/api/render",
            headers={"Authorization": f"Bearer {live_server.token}"},
            data={**size, "params": '{"sigma_A": 2.0}'},
            files={"file": ("adk.gro", f)},
        )
    assert answer.status_code == 200, answer.text
    assert np.array_equal(mine, array(answer.content, "RGB"))  # the protein, solvent hidden
    with pytest.raises(ScalesteerError) as typo:
        client.render(GRO, 48, 36, params={"sigmaa": 2.0})
    assert typo.value.path == "params.sigmaa" and "unknown field" in str(typo.value)
    with pytest.raises(ScalesteerError) as camera:
        client.render(GRO, 48, 36, camera={"distanse": 5.0})
    assert camera.value.path == "camera.distanse"


def test_a_size_past_the_limits_names_the_side_to_change(client: scalesteer.Client) -> None:
    """A refused image size is a 422 whose path is the field to change: the side past the
    limit, or the longer side of an image of too many pixels."""
    from MDAnalysisTests.datafiles import GRO

    cases = (((5000, 36), "width"), ((36, 5000), "height"), ((3000, 4000), "height"))
    for (w, h), field in cases:
        with pytest.raises(ScalesteerError) as refused:
            client.render(GRO, w, h)
        err = refused.value
        assert err.status == 422 and err.code is ErrorCode.INVALID_MESSAGE, err
        assert err.path == field and f"{w}x{h}" in err.message, err


def test_the_dashboard_link_names_a_session_by_name_and_encodes_it(
    client: scalesteer.Client, small_universe: Any
) -> None:
    from urllib.parse import parse_qs, urlsplit

    session = client.open(small_universe, frame=0)
    link = urlsplit(client.dashboard_url(session))  # a Session, as the docs' table has it
    query = parse_qs(link.query)
    assert query["session"] == [session.name] and query["token"] == [client.token]
    odd = parse_qs(urlsplit(client.dashboard_url("a b&c")).query)
    assert odd["session"] == ["a b&c"] and odd["token"] == [client.token]


def test_checked_params_name_only_what_was_given() -> None:
    from protocol import RenderParams
    from scalesteer.session import checked_params

    assert checked_params({"sigma_A": 2.0, "lighting": {"ambient": 0.4}}) == {
        "sigma_A": 2.0,
        "lighting": {"ambient": 0.4},
    }
    session = RenderParams(sigma_A=3.0, iso_level=0.4)
    changed = checked_params({"sigma_A": 2.0}, base=session)
    assert changed["sigma_A"] == 2.0 and changed["iso_level"] == 0.4
    assert "layers" not in changed  # the session's own layers stay
    assert "layers" in checked_params({"layers": []}, base=session)  # unless named
    # a model names the fields it was given (session.render_params is one)
    assert checked_params(RenderParams(sigma_A=2.0)) == {"sigma_A": 2.0}


def test_an_openmm_simulation_in_one_line(client: scalesteer.Client) -> None:
    from tests.adapters.openmm_helpers import argon_recipe

    simulation = argon_recipe(n_side=4).make()
    session = client.open(simulation, interval=10, steps=200_000)
    state = session.wait_for(lambda s: s.engine is not None and s.sim.step > 0, timeout=60)
    assert state.sim.n_atoms == 64 and state.engine is not None and state.engine.kind == "md"
    ack = session.set_sim(temperature_K=150.0)
    assert ack.ok and ack.step is not None
    assert session.pause().ok
    source = session.source
    assert isinstance(source, scalesteer.sources.OpenMMSource) and source.running
    session.close()  # stops the run and takes the reporter off the simulation
    assert not source.running and source.steps_done < 200_000
    assert not simulation.reporters


def test_mdtraj_and_ase_objects(client: scalesteer.Client) -> None:
    md = pytest.importorskip("mdtraj")
    ase_build = pytest.importorskip("ase.build")
    from MDAnalysisTests.datafiles import PDB_small

    traj = md.load(PDB_small)
    from_mdtraj = client.open(traj)
    assert from_mdtraj.sim.n_atoms == traj.n_atoms
    assert from_mdtraj.image(64, 48).std() > 5
    ethanol = ase_build.molecule("CH3CH2OH")
    frames = [ethanol.copy() for _ in range(3)]
    for i, f in enumerate(frames):
        f.positions += 0.1 * i
    from_ase = client.open(frames, fps=30)
    assert from_ase.sim.n_atoms == 9
    from_ase.wait_for(lambda s: s.sim.step == 2, timeout=20)
    assert from_ase.image(64, 48).std() > 5


def test_objects_that_cannot_feed_a_session_are_named() -> None:
    from scalesteer.sources import SourceError, kind_of

    with pytest.raises(SourceError, match=r"numpy.ndarray"):
        kind_of(np.zeros(3))


def test_next_image_takes_the_size_asked_for(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    started = time.monotonic()
    image = session.next_image(72, 54)  # width, height, as on_image takes them
    assert image.array().shape == (54, 72, 3), time.monotonic() - started
    assert session.next_image(48, 36, timeout=60).array().shape == (36, 48, 3)


def test_a_part_of_a_universe_keeps_the_bonds_among_its_atoms(small_universe: Any) -> None:
    import MDAnalysis as mda

    from scalesteer.sources import structure_of
    from structures.reader import topology_of

    part = small_universe.select_atoms("resid 10:40")
    topology = structure_of(part, frame=0).topology
    merged = topology_of(mda.Merge(part))  # the part as a universe of its own
    assert topology.n_atoms == part.n_atoms
    assert np.array_equal(topology.bonds.to_numpy(), merged.bonds.to_numpy())
    assert topology.names == merged.names and topology.elements == merged.elements
    assert np.array_equal(topology.residue_ids.to_numpy(), merged.residue_ids.to_numpy())


def test_careless_calls_are_named_and_leave_nothing_behind(
    live_server: LiveServer, small_universe: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """Found trying the client as a newcomer: `next_image(0, 0)` raised pydantic's own error
    and left its view on the session, so every later image (and `close()`) failed with it; a
    canvas past the image limits got no image at all; a camera given as a string, a bool for
    a number and a callback that is not one were refused in words about something else, or
    not at all; a failing callback printed a traceback an image; and `next_image` on a link
    that had ended waited out its whole timeout."""
    client = scalesteer.connect(live_server.url, live_server.token)
    session = client.open(small_universe, fps=20, loop=True)
    for width, height, path in ((0, 0, "view.width"), (64.5, 48, "view.width"),
                                (64, True, "view.height"), (2**64, 10, "view.width")):  # fmt: skip
        with pytest.raises(ScalesteerError) as refused:
            session.next_image(width, height)
        assert refused.value.code == ErrorCode.INVALID_MESSAGE and refused.value.path == path
    with pytest.raises(ScalesteerError, match=r"render\.width"):
        session.image(float("nan"), 48)
    with pytest.raises(ScalesteerError, match="camera: a Camera or a mapping"):
        session.image(64, 48, camera="abc")  # type: ignore[arg-type]
    with pytest.raises(ScalesteerError, match="params: a mapping of render parameters"):
        session.image(64, 48, params="abc")  # type: ignore[arg-type]
    with pytest.raises(ScalesteerError) as refused:
        session.set(sigma_A=True)
    assert refused.value.path == "render_params.params.sigma_A"
    with pytest.raises(TypeError, match="callable"):
        session.on_image(42, 80, 60)  # type: ignore[arg-type]
    assert session.next_image(64, 48).array().shape == (48, 64, 3), "nothing was left behind"
    # past the limits (4096 px a side): shrunk to fit, as the server's limits say
    big = session.next_image(5000, 3000)
    assert max(big.size) <= 4096 and big.size[0] / big.size[1] == pytest.approx(5 / 3, rel=0.02)

    def failing(_image: scalesteer.StreamedImage) -> None:
        raise RuntimeError("the user's bug")

    with caplog.at_level("ERROR", logger="scalesteer.client"):
        with session.on_image(failing, 64, 48) as sub:
            deadline = time.monotonic() + 60
            while sub.failures < 5 and time.monotonic() < deadline:
                time.sleep(0.05)
        assert sub.failures >= 5
        told = [r for r in caplog.records if r.name == "scalesteer.client"]
        assert 1 <= len(told) <= 2 and told[0].exc_info is not None, told
    session.close()
    with pytest.raises(ScalesteerError) as refused:
        session.next_image(64, 48, timeout=120)  # at once, not after the timeout
    assert refused.value.code == ErrorCode.NOT_READY
    with pytest.raises(ScalesteerError, match="closed"):  # it would never be called
        session.on_image(lambda _image: None, 64, 48)
    client.close()
    with pytest.raises(ScalesteerError, match="closed"):
        client.session("another")
    with pytest.raises(ScalesteerError, match="closed") as refused:
        client.sessions()
    assert refused.value.code == ErrorCode.NOT_READY
