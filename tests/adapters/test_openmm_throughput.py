"""A server that never reads never holds the MD loop: the adapter hands every frame over without
waiting on the server (`SimulationConnection.send_frame`: a one-slot mailbox, the newest frame
replacing one not yet sent).

The server here accepts the connection and then never reads (`SimPeer(never_read=True)`, with a
4 KB receive buffer), so once the socket's buffers are full the connection thread is stuck in
`send` for good. The MD then hands over more frames than those buffers can hold: a send
that waited on the server would never return (the generous join timeout only catches that hang),
and one that queued frames instead of replacing them would count no drops. The MD step rate
beside an unconnected run is a speed, not this mechanism: `benchmarks/adapter_bench.py`.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

from simulation_adapters.openmm_reporter import SteeringReporter
from tests.adapters.openmm_helpers import argon_recipe
from tests.adapters.sim_peer import SimPeer

N_SIDE = 16
"""4096 atoms: 48 kB frames fill the socket buffers within a few dozen reports."""
HANG_S = 300.0
"""Only a hung MD thread takes this long (the run takes seconds)."""


def buffered_bytes_at_most() -> int:
    """What the loopback connection can hold for a peer that never reads: the sender's send
    buffer (autotuned up to `tcp_wmem`'s maximum), and 1 MiB for the rest (websockets' 32 KiB
    write buffer on the sender; on the peer, its 4 KB receive buffer, one read of the event
    loop and the one message its queue holds)."""
    try:
        wmem = int(Path("/proc/sys/net/ipv4/tcp_wmem").read_text().split()[2])
    except (OSError, ValueError, IndexError):
        wmem = 4 * 2**20  # Linux's default maximum
    return wmem + 2**20


EXTRA = 64
"""Reports beyond what the buffers can hold: each must replace the frame before it."""


def test_md_with_a_server_that_never_reads_hands_every_frame_over_and_drops_the_unsent(
    no_leaked_threads: None,
) -> None:
    recipe = argon_recipe(n_side=N_SIDE)
    with SimPeer(never_read=True) as peer:
        sim = recipe.make()
        reporter = SteeringReporter(peer.ws_url, token="secret", interval=1)
        try:
            sim.reporters.append(reporter)
            reporter.attach(sim)
            link = reporter.connection
            assert link.wait_connected(10)
            assert not link.lossless
            # a frame carries 12 bytes an atom and more: at most `room` fit in the buffers
            room = math.ceil(buffered_bytes_at_most() / (12 * sim.topology.getNumAtoms()))
            steps = room + EXTRA  # one report a step
            before = reporter.frames_reported

            md = threading.Thread(target=sim.step, args=(steps,), name="md-loop")
            md.start()
            md.join(HANG_S)
            made = reporter.frames_reported - before
            assert not md.is_alive(), (
                f"the MD loop hung on a server that never reads: {made} of {steps} reports "
                f"made, {link.stats.frames_sent} frames sent"
            )

            stats = link.stats
            print(
                f"{steps} reports, {stats.frames_sent} frames sent, {stats.frames_dropped} "
                f"replaced before they were sent, room for at most {room}"
            )
            assert sim.currentStep == steps
            assert reporter.frames_reported - before == steps  # every report handed over
            assert peer.received == []  # the server read nothing
            # each frame handed over was sent (into the socket's buffers), replaced by a newer
            # one, or is the one in the mailbox or stuck in `send`
            unsent = reporter.frames_reported - stats.frames_sent - stats.frames_dropped
            assert 0 <= unsent <= 2
            assert stats.frames_sent <= room
            assert stats.frames_dropped >= reporter.frames_reported - room - 2
        finally:
            reporter.close(timeout=1.0)
