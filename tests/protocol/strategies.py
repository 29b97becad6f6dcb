"""Hypothesis strategies producing valid instances of every message type."""

from __future__ import annotations

from typing import Any

import numpy as np
from hypothesis import strategies as st

import protocol as p

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
unit = st.floats(min_value=0.0, max_value=1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite)
rgb = st.tuples(unit, unit, unit)
seq = st.none() | st.integers(min_value=0, max_value=2**53 - 1)
name = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=8)
key = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=16)


@st.composite
def wire(draw: st.DrawFn, dtype: str, shape: tuple[int, ...]) -> p.WireArray:
    n = int(np.prod(shape)) if shape else 1
    if dtype.endswith("f4"):
        values = draw(
            st.lists(
                st.floats(width=32, allow_nan=False, allow_infinity=False), min_size=n, max_size=n
            )
        )
    elif dtype == "|u1":
        values = draw(st.lists(st.integers(0, 255), min_size=n, max_size=n))
    else:
        values = draw(st.lists(st.integers(-(2**31), 2**31 - 1), min_size=n, max_size=n))
    return p.WireArray.from_numpy(np.asarray(values).reshape(shape), dtype)


@st.composite
def topology(draw: st.DrawFn) -> p.Topology:
    n = draw(st.integers(0, 12))
    m = draw(st.integers(0, 6)) if n else 0
    bonds = np.asarray(
        draw(
            st.lists(
                st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), min_size=m, max_size=m
            )
        )
        if n
        else [],
        dtype=np.int32,
    ).reshape(m, 2)
    strs = lambda k: st.lists(st.text(alphabet="ABCDEFGHNOSPZ", max_size=k), min_size=n, max_size=n)  # noqa: E731
    optional = lambda: st.none() | wire("<f4", (n,))  # noqa: E731
    return p.Topology(
        seq=draw(seq),
        n_atoms=n,
        elements=draw(strs(2)),
        names=draw(strs(4)),
        residue_ids=draw(wire("<i4", (n,))),
        residue_names=draw(strs(3)),
        chain_ids=draw(strs(1)),
        bonds=p.WireArray.from_numpy(bonds, "<i4"),
        radii=draw(optional()),
        charges=draw(optional()),
        title=draw(name),
    )


@st.composite
def frame(draw: st.DrawFn) -> p.Frame:
    n = draw(st.integers(0, 16))
    return p.Frame(
        seq=draw(seq),
        step=draw(st.integers(0, 2**62)),
        time_ps=draw(finite),
        positions=draw(wire("<f4", (n, 3))),
        box=draw(st.none() | wire("<f4", (3, 3))),
        velocities=draw(st.none() | wire("<f4", (n, 3))),
        observables=draw(st.dictionaries(key, finite, max_size=4)),
    )


@st.composite
def forces(draw: st.DrawFn) -> p.Forces:
    k = draw(st.integers(0, 8))
    idx = draw(st.lists(st.integers(0, 1000), min_size=k, max_size=k))
    return p.Forces(
        seq=draw(seq),
        indices=p.WireArray.from_numpy(np.asarray(idx, dtype=np.int32), "<i4"),
        forces=draw(wire("<f4", (k, 3))),
    )


@st.composite
def camera(draw: st.DrawFn) -> p.Camera:
    q = np.asarray(draw(st.tuples(*[st.floats(-1, 1)] * 4)))
    q = q / np.linalg.norm(q) if np.linalg.norm(q) > 1e-3 else np.array([1.0, 0, 0, 0])
    return p.Camera(
        target=draw(vec3),
        distance=draw(st.floats(0.1, 1e4)),
        orientation=tuple(float(x) for x in q),
        projection=draw(st.sampled_from(["perspective", "orthographic"])),
        fov_deg=draw(st.floats(5, 120)),
        ortho_height=draw(st.floats(0.1, 1e3)),
    )


render_params = st.builds(
    p.RenderParams,
    mode=st.sampled_from(["iso", "volume"]),
    sigma_A=st.floats(0.05, 50),
    iso_level=st.floats(0.01, 100),
    transfer_function=st.lists(
        st.builds(p.TFPoint, x=st.floats(0, 10), color=rgb, alpha=unit), max_size=5
    ),
    color_by=st.sampled_from(["element", "residue", "chain", "uniform", "bfactor", "charge"]),
    background=rgb,
    jpeg_quality=st.integers(10, 100),
    layers=st.lists(
        st.builds(
            p.Layer,
            name=st.text(max_size=12),
            selection=st.text(min_size=1, max_size=40),
            visible=st.booleans(),
            sigma_A=st.none() | st.floats(0.05, 50),
            opacity=unit,
        ),
        max_size=3,
    ),
)


@st.composite
def render_patch(draw: st.DrawFn) -> p.SetRenderParams:
    full = draw(render_params).model_dump()
    keys = draw(st.sets(st.sampled_from(sorted(full))))
    return p.SetRenderParams(seq=draw(seq), params={k: full[k] for k in keys})


def _any(draw: st.DrawFn) -> dict[str, Any]:
    return {"seq": draw(seq)}


MESSAGES: dict[str, st.SearchStrategy[Any]] = {
    "hello": st.builds(
        p.Hello,
        seq=seq,
        role=st.sampled_from(["simulation", "steerer", "viewer"]),
        token=st.none() | st.text(max_size=32),
        client=name,
    ),
    "welcome": st.builds(
        p.Welcome,
        seq=seq,
        session_id=name,
        client_id=name,
        role=st.sampled_from(["simulation", "steerer", "viewer"]),
    ),
    "topology": topology(),
    "frame": frame(),
    "params_ack": st.builds(
        p.ParamsAck,
        seq=seq,
        ref=st.integers(0, 2**53 - 1),
        ok=st.booleans(),
        step=st.none() | st.integers(0, 2**40),
        detail=name,
        applied=st.dictionaries(key, finite, max_size=3),
    ),
    "sim_params": st.builds(
        p.SimParams,
        seq=seq,
        temperature_K=st.none() | st.floats(1, 10_000),
        timestep_fs=st.none() | st.floats(0.1, 20),
        friction_per_ps=st.none() | st.floats(0, 1000),
        frame_interval=st.none() | st.integers(1, 10_000),
        engine=st.dictionaries(
            key, st.booleans() | st.integers(-100, 100) | finite | name, max_size=3
        ),
    ),
    "control": st.sampled_from(["pause", "resume", "reset", "step", "stop"]).flatmap(
        lambda a: st.builds(p.Control, seq=seq, action=st.just(a), n_steps=st.integers(1, 1000))
    ),
    "forces": forces(),
    "pull": st.builds(
        p.Pull, seq=seq, atom=st.integers(0, 10**6), target=vec3, spring_k=st.floats(0.1, 1000)
    ),
    "view": st.builds(
        p.View,
        seq=seq,
        camera=camera(),
        width=st.integers(1, 4096),
        height=st.integers(1, 4096),
        device_pixel_ratio=st.floats(0.5, 4),
        interacting=st.booleans(),
        video=st.lists(st.sampled_from(["h264", "h264-baseline", "av1", "vp9"]), max_size=4),
    ),
    "render_params": render_patch(),
    "pick": st.builds(p.Pick, seq=seq, x=st.integers(0, 4096), y=st.integers(0, 4096)),
    "select": st.builds(p.Select, seq=seq, text=st.text(max_size=60)),
    "selected": st.builds(
        p.Selected,
        seq=seq,
        ref=seq,
        text=st.text(max_size=60),
        count=st.none() | st.integers(0, 10**7),
        position=st.none() | st.integers(0, 60),
    ),
    "picked": st.builds(
        p.Picked,
        seq=seq,
        ref=seq,
        atom=st.none() | st.integers(0, 10**6),
        element=name,
        position=st.none() | vec3,
    ),
    "image": st.builds(
        p.Image,
        seq=seq,
        frame_id=st.integers(0, 2**40),
        format=st.sampled_from(["jpeg", "png", "h264", "av1", "vp9"]),
        data=st.binary(max_size=64),
        width=st.integers(1, 4096),
        height=st.integers(1, 4096),
        render_ms=st.floats(0, 1e3),
        histogram=st.none() | wire("<f4", (8,)),
        codec=st.none() | st.sampled_from(["avc1.640033", "vp09.00.51.08"]),
        key=st.none() | st.booleans(),
        stream=st.none() | st.integers(0, 2**31),
        bitrate_kbps=st.none() | st.floats(0, 1e5),
    ),
    "frame_ack": st.builds(
        p.FrameAck, seq=seq, frame_id=st.integers(0, 2**40), decode_ms=st.floats(0, 1e3)
    ),
    "state": st.builds(
        p.State,
        seq=seq,
        render_params=st.none() | render_params,
        sim=st.none()
        | st.builds(
            p.SimStatus,
            state=st.sampled_from(["waiting", "running", "paused", "disconnected"]),
            step=st.integers(0, 10**9),
        ),
        clients=st.none()
        | st.lists(
            st.builds(
                p.ClientInfo,
                client_id=name,
                role=st.sampled_from(["simulation", "steerer", "viewer"]),
            ),
            max_size=3,
        ),
    ),
    "stats": st.builds(
        p.Stats, seq=seq, render_fps=st.floats(0, 1e4), frames_sent=st.integers(0, 10**9)
    ),
    "ping": st.builds(p.Ping, seq=seq, client_time=finite),
    "pong": st.builds(p.Pong, seq=seq, ref=seq, client_time=finite, server_time=finite),
    "error": st.builds(
        p.Error,
        seq=seq,
        code=st.sampled_from(list(p.ErrorCode)),
        message=st.text(max_size=64),
        path=st.none() | name,
        ref=seq,
    ),
    "engine": st.builds(
        p.EngineInfo,
        seq=seq,
        name=st.text(max_size=40),
        kind=st.sampled_from(["md", "replay", "imd"]),
        controls=st.lists(st.sampled_from(["pause", "resume", "step", "seek"]), max_size=4),
        params=st.dictionaries(
            name,
            st.builds(p.ParamRange, min=finite, max=finite, unit=st.text(max_size=8)),
            max_size=3,
        ),
        unavailable=st.dictionaries(name, st.text(max_size=40), max_size=3),
        pull=st.none()
        | st.builds(p.PullLimits, max_force=st.floats(0.1, 1e5), max_spring_k=st.floats(0.1, 1e4)),
        n_frames=st.none() | st.integers(0, 10**6),
    ),
    "tracked": st.builds(
        p.Tracked,
        seq=seq,
        step=st.none() | st.integers(0, 10**9),
        atoms=st.lists(st.integers(0, 10**6), max_size=4),
        positions=st.lists(st.tuples(finite, finite, finite), max_size=4),
    ),
    "event": st.builds(
        p.Event,
        seq=seq,
        level=st.sampled_from(["info", "warning", "error"]),
        code=name,
        message=st.text(max_size=64),
        step=st.none() | st.integers(0, 10**9),
    ),
}
