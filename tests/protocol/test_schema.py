"""The JSON Schema export covers every message and the committed copy is current."""

from __future__ import annotations

import json
from pathlib import Path

from protocol.messages import MESSAGE_TYPES
from protocol.schema import json_schema, main

COMMITTED = Path(__file__).resolve().parents[2] / "docs" / "protocol.schema.json"


def test_schema_names_every_type() -> None:
    schema = json_schema()
    tags = set(schema["discriminator"]["mapping"])
    assert tags == set(MESSAGE_TYPES)


def test_committed_schema_is_current(tmp_path: Path) -> None:
    out = tmp_path / "s.json"
    assert main(["-o", str(out)]) == 0
    assert json.loads(out.read_text()) == json.loads(COMMITTED.read_text()), (
        "docs/protocol.schema.json is stale: run `make schema`"
    )
