"""The parse budget shared by every connection read in pieces, on a real event loop.

A piece a turn for each connection let N flooding sockets parse N pieces a turn (200 sockets
of empty pings took another viewer's round trip to 0.6 s): here the turns are counted, not
timed, so the check holds on any machine.
"""

from __future__ import annotations

import asyncio

from server.web.fairfeed import TURN_BYTES, FairFeed, Usage

PIECE = 1024


class Peer:
    """A connection with `pieces` pieces to parse; each parse is logged."""

    def __init__(self, name: str, pieces: int, log: list[str]) -> None:
        self.name, self.pieces, self.log = name, pieces, log
        self.usage = Usage()

    def wants_feed(self) -> bool:
        return self.pieces > 0

    def feed_piece(self) -> int:
        self.pieces -= 1
        self.usage.add(PIECE, asyncio.get_running_loop().time())
        self.log.append(self.name)
        return PIECE


async def turns(log: list[str], n: int) -> None:
    """Let `n` turns of the loop pass, marking each in `log` ("|")."""
    for _ in range(n):
        log.append("|")
        await asyncio.sleep(0)


def per_turn(log: list[str]) -> list[list[str]]:
    out: list[list[str]] = [[]]
    for entry in log:
        if entry == "|":
            out.append([])
        else:
            out[-1].append(entry)
    return out


def test_many_flooding_connections_share_one_budget_and_a_light_one_goes_next() -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        feed = FairFeed.of(loop)
        log: list[str] = []
        flooders = [Peer(f"f{i}", 10_000, log) for i in range(200)]
        for peer in flooders:
            feed.submit(peer, 0.0)
        await turns(log, 120)  # every flooder has parsed by now (4 pieces a turn)
        assert all(peer.pieces < 10_000 for peer in flooders)
        viewer = Peer("viewer", 1, log)
        assert not feed.try_now(PIECE), "a piece went past the waiting connections"
        feed.submit(viewer, viewer.usage.at_time(loop.time()))
        await turns(log, 3)
        parsed = per_turn(log)
        assert max(len(turn) for turn in parsed) * PIECE <= TURN_BYTES, parsed
        arrived = next(i for i, turn in enumerate(parsed) if "viewer" in turn)
        assert arrived >= len(parsed) - 4 and parsed[arrived][0] == "viewer", parsed[-4:]
        for peer in flooders:
            peer.pieces = 0
        await turns(log, 2)

    asyncio.run(main())


def test_a_lone_small_read_is_parsed_at_once_within_the_turns_budget() -> None:
    async def main() -> None:
        feed = FairFeed.of(asyncio.get_running_loop())
        assert all(feed.try_now(PIECE) for _ in range(TURN_BYTES // PIECE))
        assert not feed.try_now(PIECE)  # this turn's budget is spent
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert feed.try_now(PIECE)  # a new turn, a new budget

    asyncio.run(main())


def test_the_connection_that_parsed_least_lately_goes_first() -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        feed = FairFeed.of(loop)
        log: list[str] = []
        heavy, light = Peer("heavy", 1, log), Peer("light", 1, log)
        heavy.usage.add(100 * PIECE, loop.time())
        light.usage.add(PIECE, loop.time())
        feed.try_now(TURN_BYTES)  # this turn's budget spent: both wait for the next
        feed.submit(heavy, heavy.usage.at_time(loop.time()))
        feed.submit(light, light.usage.at_time(loop.time()))
        await turns(log, 2)
        assert [entry for entry in log if entry != "|"] == ["light", "heavy"]

    asyncio.run(main())
