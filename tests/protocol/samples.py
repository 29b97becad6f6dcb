"""One representative instance of every message type, used for the golden byte vectors.

`python -m tests.protocol.samples --write` regenerates `tests/protocol/vectors/` (the bytes and a
JSON sidecar that the browser client's tests decode against).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

import protocol as p

VECTORS = Path(__file__).parent / "vectors"


def _arr(values: Any, dtype: str) -> p.WireArray:
    return p.WireArray.from_numpy(np.asarray(values), dtype)


def samples() -> dict[str, p.Message]:
    pos = np.array([[0.0, 1.5, -2.25], [3.0, 4.0, 5.0], [-1.0, 0.5, 2.0]])
    return {
        "hello": p.Hello(seq=1, role="steerer", token="t0k3n", client="golden", session="demo"),
        "welcome": p.Welcome(seq=2, session_id="demo", client_id="c1", role="steerer"),
        "topology": p.Topology(
            seq=3,
            n_atoms=3,
            elements=["O", "H", "H"],
            names=["OW", "HW1", "HW2"],
            residue_ids=_arr([1, 1, 1], "<i4"),
            residue_names=["HOH"] * 3,
            chain_ids=["A"] * 3,
            bonds=_arr([[0, 1], [0, 2]], "<i4"),
            radii=_arr([1.52, 1.2, 1.2], "<f4"),
            charges=_arr([-0.834, 0.417, 0.417], "<f4"),
            title="water",
        ),
        "frame": p.Frame(
            seq=4,
            step=1000,
            time_ps=2.0,
            positions=_arr(pos, "<f4"),
            box=_arr(np.eye(3) * 30.0, "<f4"),
            observables={"temperature_K": 301.5, "potential_kJmol": -1234.5},
        ),
        "params_ack": p.ParamsAck(
            seq=5, ref=9, step=1200, time_ps=2.4, applied={"temperature_K": 350.0}
        ),
        "sim_params": p.SimParams(
            seq=6, temperature_K=350.0, timestep_fs=2.0, engine={"barostat": True}
        ),
        "control": p.Control(seq=7, action="seek", frame=12),
        "forces": p.Forces(
            seq=8, indices=_arr([2], "<i4"), forces=_arr([[10.0, 0.0, -5.0]], "<f4")
        ),
        "pull": p.Pull(seq=9, atom=2, target=(1.0, 2.0, 3.0), spring_k=5.0),
        "view": p.View(
            seq=10,
            camera=p.Camera(
                target=(1.0, 2.0, 3.0), distance=60.0, orientation=(0.0, 0.0, 1.0, 0.0)
            ),
            width=320,
            height=240,
            device_pixel_ratio=2.0,
            interacting=True,
        ),
        "render_params": p.SetRenderParams(seq=11, params={"sigma_A": 2.5, "mode": "volume"}),
        "pick": p.Pick(seq=12, x=10, y=20),
        "select": p.Select(seq=18, text="protein and not name H*"),
        "selected": p.Selected(
            seq=19, ref=18, text="protein and", error="ended too soon", position=11
        ),
        "picked": p.Picked(
            seq=13,
            ref=12,
            atom=1,
            element="H",
            name="HW1",
            residue_id=1,
            residue_name="HOH",
            chain="A",
            position=(3.0, 4.0, 5.0),
            depth=42.5,
            layer="ligand",
        ),
        "image": p.Image(
            seq=14,
            ref=11,
            frame_id=7,
            step=1000,
            format="jpeg",
            data=b"\xff\xd8\xff\xd9",
            width=2,
            height=1,
            still=False,
            render_ms=3.5,
            encode_ms=1.25,
            server_time=1.7e9,
        ),
        "frame_ack": p.FrameAck(seq=15, frame_id=7, decode_ms=1.5),
        "state": p.State(
            seq=15,
            ref=4,
            by="c1",
            render_params=p.RenderParams(
                sigma_A=2.0,
                layers=[
                    p.Layer(name="protein", selection="protein"),
                    p.Layer(name="ligand", selection="resname LIG", sigma_A=0.7, opacity=0.5),
                ],
            ),
            sim=p.SimStatus(state="running", step=1000, time_ps=2.0, n_atoms=3),
            clients=[p.ClientInfo(client_id="c1", role="steerer", client="golden")],
            cell=p.Cell(
                origin=(0.0, 0.0, 0.0),
                vectors=((40.0, 0.0, 0.0), (0.0, 40.0, 0.0), (20.0, 20.0, 28.25)),
            ),
        ),
        "stats": p.Stats(
            seq=16, render_fps=60.0, render_ms=12.5, frames_sent=100, frames_dropped=3
        ),
        "ping": p.Ping(seq=17, client_time=123.5),
        "pong": p.Pong(seq=18, ref=17, client_time=123.5, server_time=1.7e9),
        "error": p.Error(
            seq=19,
            code=p.ErrorCode.INVALID_MESSAGE,
            message="frame.positions: bad",
            path="frame.positions",
            ref=4,
        ),
        "engine": p.EngineInfo(
            seq=20,
            name="OpenMM 8.3 (LangevinMiddleIntegrator)",
            controls=["pause", "resume", "step", "reset", "stop"],
            params={
                "temperature_K": p.ParamRange(min=1.0, max=1000.0, unit="K", recommended=300.0),
                "timestep_fs": p.ParamRange(min=0.1, max=2.5, unit="fs", recommended=2.0),
            },
            unavailable={"seek": "a live simulation has no frames to seek"},
            pull=p.PullLimits(max_force=50.0, max_spring_k=10.0),
            guard="roll back, release the pulls, pause",
        ),
        "tracked": p.Tracked(
            seq=22, step=1200, atoms=[3, 17], positions=[(1.0, 2.0, 3.0), (-4.5, 0.25, 9.0)]
        ),
        "event": p.Event(
            seq=21, level="error", code="guard", message="blew up; rolled back", step=1200
        ),
    }


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, bytes):
        return {"$bytes": obj.hex()}
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    return obj


def _arrays(message: p.Message) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in type(message).model_fields:
        value = getattr(message, name)
        if isinstance(value, p.WireArray):
            out[name] = {
                "dtype": value.dtype,
                "shape": list(value.shape),
                "values": value.to_numpy().ravel().tolist(),
            }
    return out


def write(directory: Path = VECTORS) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for name, message in samples().items():
        raw = p.encode(message)
        (directory / f"{name}.msgpack").write_bytes(raw)
        sidecar = {"message": _jsonable(p.unpack(raw)), "arrays": _arrays(message)}
        (directory / f"{name}.json").write_text(
            json.dumps(sidecar, indent=1, sort_keys=True) + "\n"
        )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--write", action="store_true", help="regenerate the committed vectors")
    if ap.parse_args().write:
        write()
