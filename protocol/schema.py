"""JSON Schema of every message, for the browser client and the docs.

`python -m protocol.schema [-o FILE]` (or `scalesteer schema`) writes it.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from pydantic import TypeAdapter

from protocol.messages import PROTOCOL_VERSION, AnyMessage


def json_schema() -> dict[str, Any]:
    schema: dict[str, Any] = TypeAdapter(AnyMessage).json_schema(mode="validation")
    schema["title"] = "scalesteer protocol message"
    schema["$comment"] = f"protocol version {PROTOCOL_VERSION}; encoding: msgpack"
    return schema


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scalesteer schema", description=__doc__)
    ap.add_argument("-o", "--output", help="file to write (default: stdout)")
    args = ap.parse_args(argv)
    text = json.dumps(json_schema(), indent=2, sort_keys=True) + "\n"
    if args.output:
        with open(args.output, "w", encoding="utf-8") as fh:
            fh.write(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
