"""A slow or absent server never slows the MD loop down.

The property under test is non-blocking hand-over, so the comparison is between the same
reporter (same interval, same frame building) with no server at all and with a server that has
stopped reading: the latter's TCP buffers are full, the connection thread is stuck in `send`, and
the MD thread must not notice. Rates are taken as the best of interleaved short runs, which is
robust against other processes sharing the CPU.
"""

from __future__ import annotations

import socket
import time

import openmm.app as app

from simulation_adapters.openmm_reporter import SteeringReporter
from tests.adapters.openmm_helpers import argon_recipe
from tests.adapters.sim_peer import SimPeer


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def best_rate(sims: dict[str, app.Simulation], rounds: int = 12, steps: int = 80) -> dict:
    """Best steps/s of each simulation over interleaved runs, in alternating order (ABBA) so
    that a slow drift of the machine's load favours neither."""
    rates: dict[str, list[float]] = {name: [] for name in sims}
    names = list(sims)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            sim = sims[name]
            t0 = time.perf_counter()
            sim.step(steps)
            rates[name].append(steps / (time.perf_counter() - t0))
    return {name: max(values) for name, values in rates.items()}


MIN_RATIO = 0.8
"""The step rate with a stuck server, as a share of the rate without one. A frame send that
blocked the MD would take it to the server's drain rate, a small fraction; on two busy cores
the two rates of one healthy run differ by up to 11 % (0.89 seen), so 0.9 failed runs that
were right."""


def test_md_rate_with_a_server_that_never_reads_matches_the_unconnected_rate(
    no_leaked_threads: None,
) -> None:
    recipe = argon_recipe(n_side=16)  # 4096 atoms: 48 kB frames fill the socket buffers fast
    with SimPeer(never_read=True) as slow:
        sims = {"unconnected": recipe.make(), "never_reads": recipe.make()}
        reporters = {
            "unconnected": SteeringReporter(f"ws://127.0.0.1:{closed_port()}/ws/sim", interval=5),
            "never_reads": SteeringReporter(slow.ws_url, token="secret", interval=5),
        }
        try:
            for name, sim in sims.items():
                sim.reporters.append(reporters[name])
                reporters[name].attach(sim)
            stuck = reporters["never_reads"].connection
            assert stuck.wait_connected(5)
            for _ in range(200):  # run until the server's backlog makes frames drop
                if stuck.stats.frames_dropped >= 5:
                    break
                sims["never_reads"].step(50)
            sent_before = stuck.stats.frames_sent
            reported_before = reporters["never_reads"].frames_reported
            assert stuck.stats.frames_dropped >= 5

            rates = best_rate(sims)
            if rates["never_reads"] < MIN_RATIO * rates["unconnected"]:
                # one more set of rounds: a burst of load from elsewhere can cost a set
                again = best_rate(sims)
                rates = {name: max(rates[name], again[name]) for name in rates}
                reported_before += 12 * 80 // 5  # count only the last set
            print(f"best steps/s: {rates}, frames dropped: {stuck.stats.frames_dropped}")

            # the MD kept handing frames over while none could leave
            handed_over = reporters["never_reads"].frames_reported - reported_before
            assert handed_over == 12 * 80 // 5  # every report of the timed runs
            assert stuck.stats.frames_sent - sent_before <= 2
            assert not reporters["unconnected"].connection.connected
            assert rates["never_reads"] >= MIN_RATIO * rates["unconnected"], rates
        finally:
            for reporter in reporters.values():
                reporter.close(timeout=1.0)
