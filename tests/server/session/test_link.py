"""The link estimate: frame pacing and bit-rate control from video acknowledgements, with time
passed in (no sleeping)."""

from __future__ import annotations

from server.session.link import LADDER_KBPS, LinkEstimate, rung


def test_rungs_floor_to_the_ladder() -> None:
    assert rung(10_000) == 10_000
    assert rung(9_999) == 6_000
    assert rung(1e9) == LADDER_KBPS[0]
    assert rung(10) == LADDER_KBPS[-1]


class Harness:
    """Sends a frame whenever the link is ready, each acked `rtt_s` later (time in 60 Hz ticks)."""

    def __init__(self, link: LinkEstimate, fps: float = 60.0) -> None:
        self.link, self.fps = link, fps
        self.t = 0.0
        self.fid = 0
        self.pending: list[tuple[float, int]] = []

    def run(self, rtt_s: float, seconds: float) -> None:
        end = self.t + seconds
        while self.t < end:
            while self.pending and self.pending[0][0] <= self.t:
                self.link.on_ack(self.pending.pop(0)[1], self.t)
            if self.link.ready(self.t):
                self.fid += 1
                self.link.on_sent(self.fid, 20_000, self.t)
                self.pending.append((self.t + rtt_s, self.fid))
            self.t += 1 / self.fps


def test_a_clean_link_raises_the_target_step_by_step() -> None:
    link = LinkEstimate(target_kbps=2_000, max_kbps=10_000)
    h = Harness(link)
    h.run(0.04, 3.0)
    assert 2_000 * 1.1 <= link.target_kbps < 2_000 * 1.1**4
    h.run(0.04, 30.0)
    assert link.target_kbps == 10_000  # up to the ceiling, no further
    assert link.delivered_fps(h.t) > 55  # and every frame went: nothing held them


def test_queueing_delay_cuts_the_target_and_paces_frames() -> None:
    link = LinkEstimate(target_kbps=10_000)
    h = Harness(link)
    h.run(0.03, 2.0)  # base round trip 30 ms (34 in 60 Hz ticks)
    before = link.target_kbps
    sent_before = link.sent
    h.run(0.4, 2.0)  # a queue of 370 ms builds up
    assert link.target_kbps < 0.9 * before
    # frames wait for acks: far fewer than 60/s went while the round trip was 400 ms
    assert link.sent - sent_before < 60
    assert link.base_rtt_s < 0.04


def test_one_late_ack_is_a_hiccup_two_are_a_queue() -> None:
    link = LinkEstimate(target_kbps=10_000)
    for i, (sent, acked) in enumerate([(0.0, 0.03), (0.1, 0.13), (0.2, 0.5)]):
        link.on_sent(i, 10_000, sent)
        link.on_ack(i, acked)
    assert link.target_kbps == 10_000
    link.on_sent(3, 10_000, 0.6)
    link.on_ack(3, 0.95)
    assert link.target_kbps < 10_000


def test_a_still_scene_does_not_collapse_the_target() -> None:
    """Little is delivered because little is sent: a cut never goes below half the target."""
    link = LinkEstimate(target_kbps=8_000)
    link.on_sent(1, 100, 0.0)
    link.on_ack(1, 0.02)
    link.on_sent(2, 100, 1.0)
    link.on_sent(3, 100, 1.01)
    link.on_ack(2, 1.5)
    link.on_ack(3, 1.6)
    assert link.target_kbps >= 0.85 * 0.5 * 8_000


def test_overflow_halves_and_a_silent_viewer_is_not_throttled_for_ever() -> None:
    link = LinkEstimate(target_kbps=8_000)
    link.overflowed(0.0)
    assert link.target_kbps == 4_000
    for i in range(8):
        link.on_sent(i, 1000, 0.01 * i)
    assert not link.ready(0.1)
    assert not link.stalled(1.0)
    # acks stopped: one frame a second still goes (a probe), no more
    assert link.stalled(2.5) and link.ready(2.5)
    assert not link.ready(3.0)
    assert link.ready(3.6)
    link.forget_in_flight()
    assert link.ready(2.5) and link.in_flight() == 0


def test_acks_are_cumulative_and_rates_are_measured() -> None:
    link = LinkEstimate()
    for i in range(1, 11):
        link.on_sent(i, 12_500, 0.1 * i)
    link.on_ack(10, 1.05)  # everything up to 10 arrived
    assert link.in_flight() == 0 and link.bytes_in_flight() == 0
    assert link.delivered_kbps(1.05) == 10 * 12_500 * 8 / 1000
    assert link.delivered_fps(1.05) == 10
    link.on_ack(10, 1.1)  # a repeated ack changes nothing
    assert link.acked == 1
