"""What a viewer's link can take, measured from its video frame acknowledgements.

Each video frame sent to a viewer is remembered (when, how many bytes) until the viewer's
`frame_ack` says it was decoded and drawn. From that the estimate knows the round trip of a
frame, the frames and bytes in flight, and the rate the link delivered. Two controls follow:

- **frame rate**: a viewer is `ready` for another frame only while its oldest frame in flight
  is younger than its base round trip plus a slack; a link that cannot keep up therefore gets
  fewer frames instead of a queue (the queue would be latency);
- **bit rate**: delay-based, in the manner of WebRTC's congestion control: a round trip that
  grows above the base (queueing) or a frame that waits too long cuts the target to what the
  link delivered; a clean second raises it by a step, up to the ceiling.

Time is an argument everywhere, so the policy is tested without sleeping.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

LADDER_KBPS = (40_000, 25_000, 16_000, 10_000, 6_000, 4_000, 2_500, 1_600, 1_000, 600, 350)
"""Bit-rate rungs: viewers of one view whose targets fall on the same rung share a stream."""


def rung(kbps: float) -> int:
    """The highest rung at or below `kbps` (the lowest rung below the ladder)."""
    for r in LADDER_KBPS:
        if r <= kbps:
            return r
    return LADDER_KBPS[-1]


@dataclass
class LinkEstimate:
    """One viewer's link, as its video acknowledgements show it."""

    target_kbps: float = 10_000.0
    max_kbps: float = 40_000.0
    min_kbps: float = 350.0
    slack_s: float = 0.05
    """How much longer than the base round trip the oldest frame in flight may be out."""
    max_in_flight: int = 8
    _in_flight: dict[int, tuple[float, int]] = field(default_factory=dict)
    _delivered: deque[tuple[float, int]] = field(default_factory=deque)
    _rtts: deque[tuple[float, float]] = field(default_factory=deque)
    srtt_s: float | None = None
    _last_cut: float = float("-inf")
    _last_raise: float = float("-inf")
    _clean_since: float | None = None
    _last_probe: float = float("-inf")
    _late: int = 0
    """Acks in a row whose round trip showed a queue (one alone may be a hiccup)."""
    acked: int = 0
    sent: int = 0

    # ---------------------------------------------------------------- events

    def on_sent(self, frame_id: int, nbytes: int, now: float) -> None:
        if len(self._in_flight) >= 64:  # acks that never come (a stalled viewer) are forgotten
            del self._in_flight[min(self._in_flight)]
        self._in_flight[frame_id] = (now, nbytes)
        self.sent += 1
        if self._clean_since is None:
            self._clean_since = now

    def on_ack(self, frame_id: int, now: float) -> None:
        """Frame `frame_id` was drawn; acks are cumulative (older frames count as delivered)."""
        sent = self._in_flight.get(frame_id)
        if sent is None:
            return
        for fid in [f for f in self._in_flight if f <= frame_id]:
            _sent_at, nbytes = self._in_flight.pop(fid)
            self._delivered.append((now, nbytes))
        self.acked += 1
        rtt = now - sent[0]
        self._rtts.append((now, rtt))
        self.srtt_s = rtt if self.srtt_s is None else 0.875 * self.srtt_s + 0.125 * rtt
        self._trim(now)
        if rtt > self.base_rtt_s + self.slack_s:
            self._late += 1
            if self._late >= 2:
                self._cut(now)
        else:
            self._late = 0
            self._maybe_raise(now)

    # ---------------------------------------------------------------- readings

    @property
    def base_rtt_s(self) -> float:
        """The smallest round trip of the last 10 s: the link without a queue."""
        return min((r for _, r in self._rtts), default=0.0)

    def in_flight(self) -> int:
        return len(self._in_flight)

    def bytes_in_flight(self) -> int:
        return sum(n for _, n in self._in_flight.values())

    def delivered_kbps(self, now: float, window_s: float = 1.0) -> float:
        got = sum(n for t, n in self._delivered if t > now - window_s)
        return got * 8 / 1000 / window_s

    def delivered_fps(self, now: float, window_s: float = 1.0) -> float:
        return sum(1 for t, _ in self._delivered if t > now - window_s) / window_s

    def oldest_age(self, now: float) -> float:
        return max((now - t for t, _ in self._in_flight.values()), default=0.0)

    def ready(self, now: float) -> bool:
        """Whether another frame may go now (else the viewer skips this one). A viewer whose
        acks stopped (a stalled link, a script that does not ack) gets one a second."""
        if not self._in_flight:
            return True
        if self.stalled(now):
            if now - self._last_probe < 1.0:
                return False
            self._last_probe = now
            return True
        if len(self._in_flight) >= self.max_in_flight:
            self._cut(now)
            return False
        if self.oldest_age(now) > self.base_rtt_s + self.slack_s + 0.05:
            self._cut(now)
            return False
        return True

    def stalled(self, now: float, after_s: float = 2.0) -> bool:
        """Nothing acknowledged for `after_s` while frames are out."""
        return bool(self._in_flight) and self.oldest_age(now) > after_s

    def overflowed(self, now: float) -> None:
        """The viewer's queue overflowed (it lost frames and waits for a keyframe): halve."""
        self.target_kbps = max(self.min_kbps, 0.5 * self.target_kbps)
        self._last_cut = now
        self._clean_since = now

    def forget_in_flight(self) -> None:
        """The viewer starts over (a new stream): frames of the old one will never be acked."""
        self._in_flight.clear()
        self._clean_since = None

    # ---------------------------------------------------------------- control

    def _trim(self, now: float) -> None:
        while self._delivered and self._delivered[0][0] < now - 2.0:
            self._delivered.popleft()
        while self._rtts and self._rtts[0][0] < now - 10.0:
            self._rtts.popleft()

    def _cut(self, now: float) -> None:
        """Queueing: drop to 85 % of what the link delivered, at most once per round trip."""
        if now - self._last_cut < max(0.2, self.srtt_s or 0.0):
            return
        # what got through, but never below half the target: a still scene delivers little
        # because little is sent, not because the link is slow
        delivered = self.delivered_kbps(now)
        base = max(min(self.target_kbps, delivered), 0.5 * self.target_kbps)
        self.target_kbps = max(self.min_kbps, 0.85 * base)
        self._last_cut = now
        self._clean_since = now

    def _maybe_raise(self, now: float) -> None:
        """After a clean second, a step up (10 %), and again each clean second."""
        start = self._clean_since if self._clean_since is not None else now
        if now - start < 1.0 or now - self._last_raise < 1.0:
            return
        self.target_kbps = min(self.max_kbps, self.target_kbps * 1.1)
        self._last_raise = now
