"""Random and mutated byte strings never escape the decoder as anything but ProtocolError."""

from __future__ import annotations

import random

import msgpack
from hypothesis import given, settings
from hypothesis import strategies as st

import protocol as p
from tests.protocol.samples import samples


def _decode_or_error(raw: bytes) -> str:
    try:
        p.decode(raw, p.Limits(max_message_bytes=1 << 20))
    except p.ProtocolError as err:
        assert isinstance(err.code, p.ErrorCode)
        return err.code.value
    return "ok"


def _mutations(rng: random.Random, seed: bytes) -> bytes:
    data = bytearray(seed)
    for _ in range(rng.randint(1, 6)):
        op = rng.randrange(5)
        if op == 0 and data:
            data[rng.randrange(len(data))] = rng.randrange(256)
        elif op == 1:
            data.insert(rng.randrange(len(data) + 1), rng.randrange(256))
        elif op == 2 and data:
            del data[rng.randrange(len(data))]
        elif op == 3 and data:
            cut = rng.randrange(len(data))
            data = data[:cut]
        else:
            i = rng.randrange(len(data) + 1)
            data[i:i] = bytes(rng.choice([0xC1, 0xDD, 0xDF, 0xC6, 0xFF, 0x7F]) for _ in range(4))
    return bytes(data)


def test_fuzz_mutated_vectors() -> None:
    rng = random.Random(20261122)
    seeds = [p.encode(m) for m in samples().values()]
    outcomes: dict[str, int] = {}
    for i in range(3000):
        raw = _mutations(rng, seeds[i % len(seeds)])
        code = _decode_or_error(raw)
        outcomes[code] = outcomes.get(code, 0) + 1
    assert sum(outcomes.values()) == 3000
    assert outcomes.get("invalid_message", 0) > 100  # the fuzzer really produced bad input


def test_fuzz_structured_garbage() -> None:
    rng = random.Random(7)
    types = [*p.MESSAGE_TYPES, "nope", 3, None]
    junk = [
        None,
        True,
        -1,
        2**70 // 2**10,
        1.5,
        float("nan"),
        "x" * 70,
        b"\x00" * 5,
        [],
        {},
        [1, "a"],
    ]
    for _ in range(1500):
        obj = {"type": rng.choice(types)}
        for _ in range(rng.randint(0, 6)):
            obj[
                rng.choice(
                    [
                        "seq",
                        "positions",
                        "step",
                        "role",
                        "camera",
                        "params",
                        "atom",
                        "data",
                        "n_atoms",
                        "shape",
                    ]
                )
            ] = rng.choice(junk)
        if rng.random() < 0.3:
            obj["positions"] = {
                "dtype": rng.choice(["<f4", "<f8", "x"]),
                "shape": [rng.choice([-1, 0, 3, 10**15]), 3],
                "data": b"\x00" * rng.randrange(64),
            }
        _decode_or_error(msgpack.packb(obj, use_bin_type=True))


@settings(max_examples=600, deadline=None)
@given(st.binary(max_size=256))
def test_fuzz_random_bytes(raw: bytes) -> None:
    _decode_or_error(raw)
