"""What the server's event loop spends receiving one large simulation frame, whole or in
fragments: websockets' sans-I/O protocol (the one the server runs under uvicorn) fed the bytes a
client sends, in 64 KB reads as a socket delivers them, then the fragments joined as uvicorn
joins them. CPU only; the event loop does this work for every frame.

    python benchmarks/ws_parse_bench.py --out benchmarks/results/ws_parse_<host>.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

from websockets.protocol import Protocol, Side, State

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import protocol as p


def wire(payload: bytes, fragment: bool) -> bytes:
    """The bytes a client puts on the socket for `payload` (masked, as clients must)."""
    client = Protocol(Side.CLIENT, state=State.OPEN, max_size=None)
    parts = p.fragments(payload) if fragment else payload
    if isinstance(parts, list):
        for k, part in enumerate(parts):
            send = client.send_binary if k == 0 else client.send_continuation
            send(bytes(part), fin=k == len(parts) - 1)
    else:
        client.send_binary(parts)
    return b"".join(client.data_to_send())


def receive(data: bytes, read: int = 65536) -> tuple[float, float]:
    """Seconds in all and the longest single step to parse `data` into one message."""
    server = Protocol(Side.SERVER, state=State.OPEN, max_size=None)
    frames: list[bytes] = []
    longest = 0.0
    t0 = time.perf_counter()
    for i in range(0, len(data), read):
        a = time.perf_counter()
        server.receive_data(data[i : i + read])
        for event in server.events_received():
            frames.append(event.data)
            if event.fin:
                message = frames[0] if len(frames) == 1 else b"".join(frames)
                assert len(message) > 0
                frames = []
        longest = max(longest, time.perf_counter() - a)
    return time.perf_counter() - t0, longest


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mbytes", type=float, default=12.0, help="message size (1M atoms: 12)")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    payload = os.urandom(int(args.mbytes * 1e6))
    result: dict[str, object] = {
        "benchmark": "ws_parse",
        "host": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "message_bytes": len(payload),
        "fragment_bytes": p.FRAGMENT_BYTES,
    }
    for name, fragment in (("whole", False), ("fragments", True)):
        data = wire(payload, fragment)
        runs = [receive(data) for _ in range(args.repeats)]
        totals = sorted(r[0] * 1e3 for r in runs)
        longest = sorted(r[1] * 1e3 for r in runs)
        result[name] = {
            "total_ms_median": totals[len(totals) // 2],
            "longest_step_ms_median": longest[len(longest) // 2],
        }
    whole, frag = result["whole"], result["fragments"]
    assert isinstance(whole, dict) and isinstance(frag, dict)
    result["ratio_total"] = whole["total_ms_median"] / frag["total_ms_median"]
    print(json.dumps(result, indent=1))
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
