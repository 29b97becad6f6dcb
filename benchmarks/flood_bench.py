"""A viewer's round trip while other sockets flood the server with tiny WebSocket frames.

The server runs as its own process (CPU device, no simulation). A viewer sends protocol pings
one after another while 1, 64 or 200 raw sockets without a token send empty pings, or one
socket sends one-byte messages, as fast as the server reads them, and read nothing (timed from
when every flooding socket is connected). The control is the same viewer's round trip with no
flood, in the same run; each case reports its ratio to it.

    python benchmarks/flood_bench.py --out benchmarks/results/flood_cpu_2core.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from websockets.frames import Frame, Opcode

from tests.server.peers import Peer
from tests.server.processes import VIEWER_TOKEN, ServerProcess
from tests.server.rawsockets import flood, round_trips

CASES = (("none", 0), ("empty pings", 1), ("one-byte messages", 1))
CASES += (("empty pings", 64), ("empty pings", 200))


def stats(rtts: list[float]) -> dict[str, float]:
    ms = sorted(1000 * r for r in rtts)
    return {
        "count": len(ms),
        "p50_ms": statistics.median(ms),
        "p90_ms": ms[int(0.9 * (len(ms) - 1))],
        "max_ms": ms[-1],
    }


def commit() -> str:
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True)
    return out.stdout.decode().strip()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=4.0, help="each flood's length")
    ap.add_argument("--repeats", type=int, default=2, help="rounds of every case, in turn")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    frames = {
        "empty pings": Frame(Opcode.PING, b"").serialize(mask=True),
        "one-byte messages": Frame(Opcode.BINARY, b"\x80").serialize(mask=True),
    }
    runs: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as state:
        server = ServerProcess(Path(state))
        try:
            viewer = Peer(server.view_url, "viewer", VIEWER_TOKEN)
            for _ in range(args.repeats):
                for kind, sockets in CASES:
                    load = flood(server, frames.get(kind, b""), args.seconds, sockets)
                    key = f"{kind} x{sockets}" if sockets else "no flood"
                    runs.setdefault(key, []).extend(round_trips(viewer, load))
            viewer.close()
        finally:
            server.stop()
    cases = {key: stats(rtts) for key, rtts in runs.items()}
    control = cases["no flood"]["p50_ms"]
    for key, case in cases.items():
        case["p50_ratio"] = case["p50_ms"] / control
        print(f"{key:>24}: p50 {case['p50_ms']:8.2f} ms ({case['p50_ratio']:6.1f}x)", end="")
        print(f"  p90 {case['p90_ms']:8.2f}  max {case['max_ms']:8.2f}  n {case['count']}")
    result = {
        "benchmark": "flood",
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "commit": commit(),
        "host_cores": os.cpu_count(),
        "python": platform.python_version(),
        "seconds": args.seconds,
        "repeats": args.repeats,
        "cases": cases,
    }
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
