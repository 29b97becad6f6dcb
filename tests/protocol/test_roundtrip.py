"""Every message type survives encode -> decode -> encode bit-exactly, arrays included."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings

import protocol as p
from tests.protocol.strategies import MESSAGES


def test_every_message_type_has_a_strategy() -> None:
    assert set(MESSAGES) == set(p.MESSAGE_TYPES)


@pytest.mark.parametrize("kind", sorted(p.MESSAGE_TYPES))
def test_round_trip(kind: str) -> None:
    @settings(max_examples=40, deadline=None)
    @given(MESSAGES[kind])
    def check(message: p.Message) -> None:
        raw = p.encode(message)
        back = p.decode(raw)
        assert type(back) is type(message)
        assert back == message
        assert p.encode(back) == raw
        for name in type(message).model_fields:
            value = getattr(message, name)
            if isinstance(value, p.WireArray):
                got = getattr(back, name).to_numpy()
                want = value.to_numpy()
                assert got.dtype == want.dtype and got.shape == want.shape
                assert got.tobytes() == want.tobytes()

    check()


def test_arrays_are_raw_little_endian_bytes() -> None:
    big = np.arange(6, dtype=">f4").reshape(2, 3)
    wire = p.WireArray.from_numpy(big)
    assert wire.dtype == "<f4"
    assert wire.data == np.arange(6, dtype="<f4").tobytes()
    assert np.array_equal(wire.to_numpy(), big)


def test_render_params_patch_keeps_only_given_fields() -> None:
    msg = p.decode(p.encode(p.SetRenderParams(params={"sigma_A": 3.0})))
    assert isinstance(msg, p.SetRenderParams)
    assert msg.changes() == {"sigma_A": 3.0}
    merged = p.RenderParams().model_copy(update=msg.changes())
    assert merged.sigma_A == 3.0 and merged.mode == "iso"


def test_large_messages_go_out_in_fragments_that_join_to_the_message() -> None:
    small = b"x" * p.FRAGMENT_BYTES
    assert p.fragments(small) is small  # one piece: no fragmentation
    big = bytes(range(256)) * (3 * p.FRAGMENT_BYTES // 256 + 7)
    parts = p.fragments(big)
    assert isinstance(parts, list) and len(parts) == 4
    assert all(len(part) == p.FRAGMENT_BYTES for part in parts[:-1])
    assert b"".join(parts) == big
