"""The committed golden byte vectors decode to the expected messages and re-encode bit-exactly.

Regenerate only after an intended, documented protocol change:
    python -m tests.protocol.samples --write
"""

from __future__ import annotations

import json

import pytest

import protocol as p
from tests.protocol.samples import VECTORS, samples


def test_a_vector_per_message_type() -> None:
    assert {f.stem for f in VECTORS.glob("*.msgpack")} == set(p.MESSAGE_TYPES)


@pytest.mark.parametrize("kind", sorted(p.MESSAGE_TYPES))
def test_vector(kind: str) -> None:
    raw = (VECTORS / f"{kind}.msgpack").read_bytes()
    expected = samples()[kind]
    assert p.decode(raw) == expected
    assert p.encode(expected) == raw
    sidecar = json.loads((VECTORS / f"{kind}.json").read_text())
    assert sidecar["message"]["type"] == kind
