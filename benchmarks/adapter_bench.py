"""The OpenMM adapter's MD step rate beside a server that never reads, against the same
reporter with no server at all (the control, in the same run).

Two identical argon simulations (4096 atoms, 48 kB frames, OpenMM's CPU platform on one
thread) carry a `SteeringReporter` each, reporting every 5 steps: one to a closed port, one to a
`/ws/sim` peer that stops reading after the handshake, whose socket buffers are full before the
timing starts (the adapter is dropping frames). The two run in interleaved rounds, in
alternating order (ABBA), so that a drift of the machine's load favours neither; each round's
steps/s is kept, and the ratio is taken of the best and of the median rounds. The mechanism
itself (every frame handed over, the unsent ones replaced, never a wait on the server) is
tested by tests/adapters/test_openmm_throughput.py.

    python benchmarks/adapter_bench.py --out benchmarks/results/adapter_cpu_2core.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import openmm.app as app

from simulation_adapters.openmm_reporter import SteeringReporter
from tests.adapters.openmm_helpers import argon_recipe
from tests.adapters.sim_peer import SimPeer


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rounds_of(sims: dict[str, app.Simulation], rounds: int, steps: int) -> dict[str, list[float]]:
    """Steps/s of each simulation in each round, the order alternating (ABBA)."""
    rates: dict[str, list[float]] = {name: [] for name in sims}
    names = list(sims)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            t0 = time.perf_counter()
            sims[name].step(steps)
            rates[name].append(steps / (time.perf_counter() - t0))
    return rates


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n-side", type=int, default=16, help="argon lattice side (16: 4096 atoms)")
    ap.add_argument("--interval", type=int, default=5, help="steps between reports")
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--steps", type=int, default=80, help="steps per round")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()

    recipe = argon_recipe(n_side=args.n_side)
    load_before = os.getloadavg()[0]
    with SimPeer(never_read=True) as peer:
        sims = {"unconnected": recipe.make(), "never_reads": recipe.make()}
        reporters = {
            "unconnected": SteeringReporter(
                f"ws://127.0.0.1:{closed_port()}/ws/sim", interval=args.interval
            ),
            "never_reads": SteeringReporter(peer.ws_url, token="secret", interval=args.interval),
        }
        try:
            for name, sim in sims.items():
                sim.reporters.append(reporters[name])
                reporters[name].attach(sim)
            stuck = reporters["never_reads"].connection
            if not stuck.wait_connected(30):
                raise SystemExit("the never-reading peer did not welcome the adapter")
            while stuck.stats.frames_dropped < 5:  # until the full buffers make frames drop
                sims["never_reads"].step(50)
            rates = rounds_of(sims, args.rounds, args.steps)
            stats = stuck.stats
            result: dict[str, Any] = {
                "benchmark": "adapter",
                "device": "cpu",
                "cpus": os.cpu_count(),
                "host": platform.processor() or platform.machine(),
                "date": time.strftime("%Y-%m-%d"),
                "load_average": [load_before, os.getloadavg()[0]],
                "n_atoms": sims["unconnected"].topology.getNumAtoms(),
                "interval": args.interval,
                "rounds": args.rounds,
                "steps_per_round": args.steps,
                "steps_per_s": {
                    name: {"best": max(v), "median": statistics.median(v), "rounds": v}
                    for name, v in rates.items()
                },
                "frames_sent": stats.frames_sent,
                "frames_dropped": stats.frames_dropped,
                "frames_reported": reporters["never_reads"].frames_reported,
            }
            un, nr = result["steps_per_s"]["unconnected"], result["steps_per_s"]["never_reads"]
            result["ratio_best"] = nr["best"] / un["best"]
            result["ratio_median"] = nr["median"] / un["median"]
        finally:
            for reporter in reporters.values():
                reporter.close(timeout=1.0)
    print(json.dumps(result, indent=1))
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
