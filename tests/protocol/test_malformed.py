"""Malformed input is rejected with the right code and field path, never an exception."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

import protocol as p
from tests.protocol.samples import samples


def raw_of(kind: str) -> dict[str, Any]:
    obj = p.unpack(p.encode(samples()[kind]))
    assert isinstance(obj, dict)
    return obj


def reject(obj: Any, limits: p.Limits = p.DEFAULT_LIMITS) -> p.ProtocolError:
    raw = obj if isinstance(obj, bytes) else msgpack.packb(obj, use_bin_type=True)
    with pytest.raises(p.ProtocolError) as info:
        p.decode(raw, limits)
    return info.value


def test_truncated_msgpack() -> None:
    raw = p.encode(samples()["frame"])
    for cut in (1, len(raw) // 2, len(raw) - 1):
        err = reject(raw[:cut])
        assert err.code == p.ErrorCode.INVALID_MESSAGE


def test_not_a_map() -> None:
    assert reject([1, 2, 3]).code == p.ErrorCode.INVALID_MESSAGE


def test_wrong_types_name_the_field() -> None:
    obj = raw_of("frame")
    obj["step"] = "ten"
    err = reject(obj)
    assert (err.code, err.path, err.ref) == (p.ErrorCode.INVALID_MESSAGE, "frame.step", 4)
    obj = raw_of("view")
    obj["camera"]["distance"] = [1]
    assert reject(obj).path == "view.camera.distance"


@pytest.mark.parametrize("field", ["distance", "ortho_height"])
def test_a_camera_past_any_coordinate_is_refused(field: str) -> None:
    """1e300 A away (beyond which float arithmetic overflows): refused by name; 1e8 is not."""
    obj = raw_of("view")
    obj["camera"][field] = 1.0e300
    assert reject(obj).path == f"view.camera.{field}"
    assert p.Camera(**{field: 1.0e8}).model_dump()[field] == 1.0e8


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_positions(bad: float) -> None:
    obj = raw_of("frame")
    pos = np.frombuffer(obj["positions"]["data"], "<f4").copy()
    pos[4] = bad
    obj["positions"]["data"] = pos.tobytes()
    err = reject(obj)
    assert err.code == p.ErrorCode.INVALID_MESSAGE
    assert err.path == "frame.positions"
    assert "NaN" in err.message


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("where", [0, 1_000, 299_999])
def test_non_finite_anywhere_in_a_big_frame_is_refused(bad: float, where: int) -> None:
    pos = np.random.default_rng(0).uniform(-50, 50, (100_000, 3)).astype(np.float32)
    pos.reshape(-1)[where] = bad
    obj = raw_of("frame")
    obj["positions"] = {"dtype": "<f4", "shape": [100_000, 3], "data": pos.tobytes()}
    err = reject(obj)
    assert (err.code, err.path) == (p.ErrorCode.INVALID_MESSAGE, "frame.positions")


def test_finite_values_whose_sum_overflows_are_accepted() -> None:
    big = np.finfo(np.float32).max
    pos = np.full((1_000, 3), big, np.float32)
    pos[::2] = -big / 2
    with np.errstate(over="ignore"):
        assert not np.isfinite(pos.sum())  # the quick test cannot decide; the exact one must
    obj = raw_of("frame")
    obj["positions"] = {"dtype": "<f4", "shape": [1_000, 3], "data": pos.tobytes()}
    frame = p.decode(msgpack.packb(obj, use_bin_type=True))
    assert isinstance(frame, p.Frame)
    assert np.array_equal(frame.positions.to_numpy(), pos)


def test_non_finite_scalars() -> None:
    obj = raw_of("frame")
    obj["time_ps"] = float("nan")
    assert reject(obj).path == "frame.time_ps"
    obj = raw_of("pull")
    obj["target"] = [0.0, float("inf"), 0.0]
    assert reject(obj).path.startswith("pull.target")


def test_shape_byte_length_mismatch() -> None:
    obj = raw_of("frame")
    obj["positions"]["shape"] = [4, 3]
    err = reject(obj)
    assert err.code == p.ErrorCode.INVALID_MESSAGE and err.path == "frame.positions"
    assert "bytes" in err.message


def test_wrong_dtype_and_rank() -> None:
    obj = raw_of("frame")
    obj["positions"]["dtype"] = "<f8"
    obj["positions"]["shape"] = [3, 3]
    obj["positions"]["data"] = np.zeros(9, "<f8").tobytes()
    # the values named, not the template's placeholders (pydantic has no !r conversions)
    assert "dtype must be '<f4', got '<f8'" in reject(obj).message
    obj = raw_of("frame")
    obj["positions"]["shape"] = [9]
    assert "shape" in reject(obj).message
    obj = raw_of("frame")
    obj["positions"]["dtype"] = ">f4"
    assert "not allowed" in reject(obj).message


def test_declared_trillion_atoms_rejected_before_allocation() -> None:
    obj = raw_of("frame")
    obj["positions"]["shape"] = [10**12, 3]
    err = reject(obj)
    assert err.code == p.ErrorCode.TOO_LARGE and err.path == "frame.positions"


def test_atom_limit_from_connection_limits() -> None:
    small = p.Limits(max_atoms=2)
    err = reject(raw_of("frame"), small)
    assert err.code == p.ErrorCode.TOO_LARGE


def test_message_size_limit() -> None:
    raw = p.encode(samples()["frame"])
    err = reject(raw, p.Limits(max_message_bytes=len(raw) - 1))
    assert err.code == p.ErrorCode.TOO_LARGE


def test_unknown_type() -> None:
    err = reject({"type": "launch_missiles", "seq": 3})
    assert (err.code, err.path, err.ref) == (p.ErrorCode.UNKNOWN_TYPE, "type", 3)
    assert reject({"seq": 1}).code == p.ErrorCode.INVALID_MESSAGE


def test_missing_required_field() -> None:
    obj = raw_of("topology")
    del obj["bonds"]
    err = reject(obj)
    assert err.path == "topology.bonds" and "required" in err.message.lower()


def test_wrong_version() -> None:
    obj = raw_of("hello")
    obj["protocol_version"] = "2.0"
    err = reject(obj)
    assert err.code == p.ErrorCode.VERSION_MISMATCH and err.ref == 1
    obj["protocol_version"] = 1
    assert reject(obj).code == p.ErrorCode.VERSION_MISMATCH
    obj["protocol_version"] = "1.99"  # another minor version of the same major is accepted
    assert isinstance(p.decode(msgpack.packb(obj)), p.Hello)


def test_cross_field_consistency() -> None:
    obj = raw_of("topology")
    obj["names"] = ["X"]
    assert "names has 1 entries" in reject(obj).message
    obj = raw_of("topology")
    obj["bonds"]["data"] = np.array([[0, 7], [0, 2]], "<i4").tobytes()
    assert "bond index" in reject(obj).message
    obj = raw_of("forces")
    obj["indices"]["data"] = np.array([-1], "<i4").tobytes()
    assert reject(obj).path == "forces"
    assert "needs field 'frame'" in reject({"type": "control", "action": "seek"}).message
    assert "exactly one" in reject({"type": "pull", "atom": 1}).message


def test_unknown_fields_are_ignored_for_forward_compatibility() -> None:
    obj = raw_of("ping")
    obj["added_in_1_1"] = {"x": 1}
    assert p.decode(msgpack.packb(obj)) == samples()["ping"]


def test_a_request_names_a_key_its_message_has_no_field_for() -> None:
    """Ignoring unknown fields is for a newer peer's messages; a request to change something
    (the types the server passes) with a key dropped in silence would leave its sender
    wondering why nothing changed."""
    requests = frozenset({"render_params", "sim_params", "control"})
    cases = {
        "render_params.params.sigma_a": {"type": "render_params", "params": {"sigma_a": 2.0}},
        "render_params.params.lighting.ambiant": {
            "type": "render_params",
            "params": {"sigma_A": 2.0, "lighting": {"ambiant": 0.3}},
        },
        "render_params.params.layers.0.bogus": {
            "type": "render_params",
            "params": {"layers": [{"name": "x", "selection": "all", "bogus": 1}]},
        },
        "render_params.params.transfer_function.1.opacity": {
            "type": "render_params",
            "params": {"transfer_function": [{"x": 0.1}, {"x": 0.5, "opacity": 1.0}]},
        },
        "sim_params.temperatur_K": {"type": "sim_params", "temperatur_K": 300.0},
        "control.steps": {"type": "control", "action": "step", "steps": 5},
    }
    for where, obj in cases.items():
        raw = msgpack.packb({**obj, "seq": 7})
        with pytest.raises(p.ProtocolError) as info:
            p.decode(raw, p.DEFAULT_LIMITS, requests)
        err = info.value
        assert err.code == p.ErrorCode.INVALID_MESSAGE and err.ref == 7
        assert (err.path, err.message) == (where, f"{where}: unknown field")
        assert p.decode(raw).type == obj["type"]  # without `requests`: ignored, as a peer's
    ok = msgpack.packb({"type": "render_params", "params": {"lighting": {"ambient": 1}}})
    message = p.decode(ok, p.DEFAULT_LIMITS, requests)
    assert isinstance(message, p.SetRenderParams)
    assert message.changes() == {"lighting": {"ambient": 1.0}}


def test_true_or_false_is_not_taken_for_a_number() -> None:
    """pydantic reads a bool as 1 or 0 where a number goes: `sigma_A: true` drew at 1 A."""
    for obj, where in (
        ({"type": "render_params", "params": {"sigma_A": True}}, "render_params.params.sigma_A"),
        (
            {"type": "render_params", "params": {"lighting": {"ambient": False}}},
            "render_params.params.lighting.ambient",
        ),
        ({"type": "control", "action": "step", "n_steps": True}, "control.n_steps"),
        ({"type": "sim_params", "temperature_K": True}, "sim_params.temperature_K"),
    ):
        err = reject(obj)
        assert err.code == p.ErrorCode.INVALID_MESSAGE and err.path == where, err
        assert err.message == f"{where}: true or false is not a number", err
    # booleans where booleans go, numbers where numbers go
    ok = {"type": "render_params", "params": {"sigma_A": 2, "lighting": {"key_light": True}}}
    message = p.decode(msgpack.packb(ok))
    assert isinstance(message, p.SetRenderParams)
    assert message.changes() == {"sigma_A": 2.0, "lighting": {"key_light": True}}
    with pytest.raises(ValidationError, match="true or false is not a number"):
        p.RenderParams.model_validate({"iso_level": True})  # REST and files alike


def test_made_up_keys_do_not_grow_the_number_field_table() -> None:
    """The table of which fields hold numbers learns only real fields: keys a client makes up
    (here a thousand booleans in a ping) leave it as it was."""
    from protocol.messages import _NUMBER_FIELDS

    p.decode(msgpack.packb({"type": "ping", "client_time": 1.0}))
    before = len(_NUMBER_FIELDS)
    made_up = {f"k{i}": True for i in range(1000)}
    assert isinstance(p.decode(msgpack.packb({"type": "ping", **made_up})), p.Ping)
    assert len(_NUMBER_FIELDS) == before


def test_error_message_echoes_ref() -> None:
    err = reject({"type": "frame", "seq": 41})
    reply = p.error_message(err)
    back = p.decode(p.encode(reply))
    assert isinstance(back, p.Error)
    assert back.ref == 41 and back.code == "invalid_message" and back.path == "frame.step"


def test_topology_of_many_atoms_decodes() -> None:
    n = 250_000
    topo = p.Topology(
        n_atoms=n,
        elements=["C"] * n,
        names=["CA"] * n,
        residue_ids=p.WireArray.from_numpy(np.arange(n), "<i4"),
        residue_names=["ALA"] * n,
        chain_ids=["A"] * n,
        bonds=p.WireArray.from_numpy(np.zeros((0, 2)), "<i4"),
    )
    assert p.decode(p.encode(topo)).n_atoms == n
    err = reject(p.unpack(p.encode(topo)), p.Limits(max_atoms=1000))
    assert err.code == p.ErrorCode.TOO_LARGE
