"""The WebSocket endpoints: `/ws/sim` for simulation adapters, `/ws/view` for browsers and scripts.

Each connection: Origin check, `hello` within a timeout, token -> role, then a receive loop that
decodes with the connection's limits, checks what the role may send and how fast, and dispatches
to the session. Every rejection is a coded `error`; only abuse closes the connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field

from starlette.responses import PlainTextResponse
from starlette.websockets import WebSocket, WebSocketDisconnect

import protocol as p
from protocol.codec import ref_of
from server.session.clients import Client, ClientState
from server.session.session import Session
from server.settings import ServerSettings
from server.web.auth import (
    SIMULATION_TYPES,
    STEERING_TYPES,
    ClientBudget,
    RateLimiter,
    client_address,
    grant,
    may_send,
    origin_allowed,
    refusal,
)
from server.web.hello import (
    Endpoint,
    RefusedError,
    claim_session,
    read_hello,
    receive_message,
)
from server.web.sendqueue import send_queue
from server.web.state import AppState
from server.web.transport import raise_limit

log = logging.getLogger("scalesteer.ws")

_client_ids = itertools.count(1)
MAX_ERRORS_PER_10S = 50
MAX_REFUSED_PER_10S = 2000
"""Messages refused for their rate within 10 s before the connection closes: a client that
keeps sending at many times its rate (20 times the steering rate's burst) is not slowing down."""
OFFLOAD_BYTES = 1 << 20
PONG_BACKLOG = 64
"""A ping is not answered while this many messages wait to be sent to its peer."""


@dataclass
class Guard:
    """A connection's rate limits (its client's, shared with the client's other connections)
    and the count of its own recent protocol errors."""

    steer: RateLimiter
    any: RateLimiter
    owner: tuple[str, str]
    """The client (role, address) whose selection-worker time this connection uses."""
    errors: deque[float] = field(default_factory=lambda: deque(maxlen=64))
    refused: deque[float] = field(default_factory=lambda: deque(maxlen=MAX_REFUSED_PER_10S + 1))
    """When its messages over the rate limit came: valid messages, refused for their rate."""
    told: float = -math.inf
    """When a refusal of this simulation's messages was last logged and told to viewers."""

    @classmethod
    def of(cls, budget: ClientBudget, owner: tuple[str, str]) -> Guard:
        return cls(budget.steer, budget.any, owner)

    def note_error(self, err: p.ProtocolError) -> str | None:
        """Record a refused message; returns why the connection closes now, if it does. A
        message over the rate limit is not an invalid one: a burst of valid steering is
        answered `rate_limited` message by message and the connection stays, unless the
        client keeps sending at many times its rate (`MAX_REFUSED_PER_10S`)."""
        now = time.monotonic()
        if err.code == p.ErrorCode.RATE_LIMITED:
            kept, limit, what = self.refused, MAX_REFUSED_PER_10S, "messages over the rate limit"
        else:
            kept, limit, what = self.errors, MAX_ERRORS_PER_10S, "invalid messages"
        kept.append(now)
        while now - kept[0] >= 10.0:  # only the last 10 s count
            kept.popleft()
        if len(kept) > limit:
            return f"too many {what} (more than {limit} within 10 s)"
        return None


async def _send_now(ws: WebSocket, message: p.Message) -> None:
    with contextlib.suppress(Exception):
        await ws.send_bytes(p.encode(message))


async def handle(ws: WebSocket, state: AppState, endpoint: Endpoint) -> None:
    settings = state.settings
    if not origin_allowed(settings, ws.headers.get("origin"), ws.headers.get("host")):
        state.metrics.errors.labels("forbidden").inc()
        await ws.close(code=1008, reason="origin not allowed")
        return
    if state.connections.total >= settings.max_connections and not state.connections.make_room():
        state.metrics.errors.labels("capacity").inc()
        await ws.send_denial_response(
            PlainTextResponse(
                f"the server holds its limit of {settings.max_connections} connections; "
                "try again later",
                status_code=503,
                headers={"Retry-After": "5"},
            )
        )
        return
    await ws.accept()
    client: Client | None = None
    session = None
    sender: asyncio.Task[None] | None = None
    counted: str | None = None
    budget: ClientBudget | None = None
    state.connections.total += 1
    notice: asyncio.Future[None] = asyncio.get_running_loop().create_future()
    state.connections.waiting[id(notice)] = notice
    try:
        try:
            hello = await read_hello(ws, state, endpoint, notice)
        finally:
            state.connections.waiting.pop(id(notice), None)
        role = grant(settings, hello.token, hello.role)
        if role is None:
            code, why, where = refusal(settings, hello.token, hello.role)
            raise RefusedError(p.ProtocolError(code, why, where, hello.seq), 1008)
        token_kind = "viewer" if role == "viewer" else "server"
        if state.connections.by_token[token_kind] >= settings.max_connections_per_token:
            raise RefusedError(
                p.ProtocolError(
                    p.ErrorCode.CAPACITY,
                    f"{settings.max_connections_per_token} connections already hold this "
                    "token; try again later",
                    "hello.token",
                    hello.seq,
                ),
                1013,
            )
        state.connections.by_token[token_kind] += 1
        counted = token_kind
        try:
            session = await state.sessions.get_or_create(
                hello.session or "default", create=role != "viewer"
            )
        except p.ProtocolError as err:
            raise RefusedError(err.with_ref(hello.seq), 1008) from None
        if role != "simulation" and (full := _session_full(session, role, settings)):
            raise RefusedError(
                p.ProtocolError(p.ErrorCode.CAPACITY, full, "hello.session", hello.seq), 1013
            )
        if role == "simulation":
            claim_session(session, hello)
            raise_limit(ws.scope, settings.limits.max_message_bytes)
        elif role == "steerer":  # reads whole: a 250 KB message took 6-10 ms in pieces, 0.4-1.8
            raise_limit(ws.scope, settings.viewer_limits.max_message_bytes)
        # browsers and scripts send only small control messages; simulations send frames
        limits = settings.limits if endpoint == "sim" else settings.viewer_limits
        client = Client(
            client_id=f"c{next(_client_ids)}",
            role=role,
            name=hello.client,
            ws=ws,
            instance=hello.instance,
            queued=send_queue(ws.scope),
        )
        address = client_address(ws.client.host if ws.client is not None else None)
        budget = state.budgets.take(role, address, limits.max_steer_per_s)
        guard = Guard.of(budget, (role, address))
        client.send(
            p.Welcome(session_id=session.id, client_id=client.client_id, role=role, limits=limits)
        )
        sender = asyncio.create_task(
            client.run_sender(state.metrics.images_sent.inc), name=f"send-{client.client_id}"
        )
        session.attach(client)
        state.owners.joined(session, client.instance)
        log.info("%s %s joined session %s as %s", endpoint, client.client_id, session.id, role)
        await _receive_loop(ws, state, session, client, guard, limits)
    except RefusedError as refused:
        state.metrics.errors.labels(refused.error.code.value).inc()
        if client is not None:
            client.close()
        await _send_now(ws, p.error_message(refused.error))
        with contextlib.suppress(Exception):
            await ws.close(code=refused.close_code, reason=refused.error.code.value)
    except (WebSocketDisconnect, asyncio.CancelledError):
        pass
    except Exception:
        log.exception("connection failed")
    finally:
        state.connections.total -= 1
        if counted is not None:
            state.connections.by_token[counted] -= 1
        if budget is not None:
            state.budgets.give_back(budget)
        if client is not None:
            if session is not None:
                session.detach(client)
                state.owners.left(session, client.instance)
            if client.state is ClientState.CLOSING and sender is not None:
                # dropped for not reading: let the sender deliver the error and the close frame
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(asyncio.shield(sender), 5.0)
            client.close()
        if sender is not None:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender


async def _receive_loop(
    ws: WebSocket,
    state: AppState,
    session: Session,
    client: Client,
    guard: Guard,
    limits: p.Limits,
) -> None:
    while client.state is ClientState.CONNECTED:
        try:
            raw = await receive_message(ws, limits)
            if raw is None:
                return
            big = len(raw) > OFFLOAD_BYTES
            # a steering request naming a key its message has no field for is refused by name
            if big:  # big frames: validate off the event loop
                message = await asyncio.to_thread(_decode, client.role, raw, limits)
            else:
                message = _decode(client.role, raw, limits)
            try:
                await _dispatch(session, client, guard, message)
                # messages already buffered would otherwise be handled back to back; let the
                # sender and every other connection have their turn after each one
                await asyncio.sleep(0)
                if big and isinstance(message, p.Frame):
                    # the next big frame is read once a render took this one: few fit in the
                    # socket's buffers, so acks behind them wait one render at most
                    await session.frame_taken(session.settings.frame_wait_s)
            except p.ProtocolError:
                raise
            except Exception:  # a server fault: logged here, reported without details
                log.exception("handling %s from %s failed", message.type, client.client_id)
                raise p.ProtocolError(
                    p.ErrorCode.INTERNAL,
                    "the server failed to handle this message; see its log",
                    message.type,
                    message.seq,
                ) from None
        except p.ProtocolError as err:
            state.metrics.errors.labels(err.code.value).inc()
            client.send(p.error_message(err))
            if client.role == "simulation" and time.monotonic() - guard.told >= 10.0:
                # a simulation's refused frame leaves viewers waiting: say why, once per 10 s
                guard.told = time.monotonic()
                log.warning("session %s: refused from its simulation: %s", session.id, err)
                session.broadcast(
                    p.Error(code=err.code, message=f"the simulation's message was refused: {err}")
                )
            closing = guard.note_error(err)
            if closing is not None:
                closed = p.ProtocolError(p.ErrorCode.RATE_LIMITED, closing)
                raise RefusedError(closed, 1008) from None


def _forbidden(role: p.Role, kind: str, seq: int | None) -> p.ProtocolError:
    why = "a viewer cannot steer" if role == "viewer" else f"role {role} may not send {kind}"
    return p.ProtocolError(p.ErrorCode.FORBIDDEN, why, "type", seq)


def _decode(role: p.Role, raw: bytes, limits: p.Limits) -> p.Message:
    """The message in `raw`, refused as forbidden before its fields are checked when `role`
    may not send its type: a viewer's `topology` was answered with the fields it lacked, as
    if it could send one that had them."""
    obj = p.unpack(raw, limits)
    kind = obj.get("type") if isinstance(obj, dict) else None
    if isinstance(kind, str) and kind in p.MESSAGE_TYPES and not may_send(role, kind):
        raise _forbidden(role, kind, ref_of(obj))
    return p.validate(obj, limits, STEERING_TYPES)


async def _dispatch(session: Session, client: Client, guard: Guard, message: p.Message) -> None:
    kind = message.type
    if not may_send(client.role, kind):
        raise _forbidden(client.role, kind, message.seq)
    # a simulation's own messages are never rate-limited: its frames are read one at a time and
    # the newest replaces the last (ingest is paced by `frame_taken`, not refused)
    if not (client.role == "simulation" and kind in SIMULATION_TYPES):
        steering = kind in STEERING_TYPES
        limiter = guard.steer if steering else guard.any
        if not limiter.allow():
            what = "steering messages" if steering else "messages other than steering"
            raise p.ProtocolError(
                p.ErrorCode.RATE_LIMITED,
                f"too many {kind} messages: {what} are limited to {limiter.rate:g} a second "
                "for each client (its role and address, all its connections together); "
                "slow down",
                "type",
                message.seq,
            )
    if client.role == "simulation" and session.sim is not client:
        return  # a replaced simulation connection: its last words are not applied
    match message:
        case p.Topology():
            session.on_topology(message)
        case p.Frame():
            session.on_frame(message)
        case p.ParamsAck():
            session.on_ack(message)
        case p.EngineInfo():
            session.on_engine(message)
        case p.Event():
            session.on_event(message)
        case p.View():
            session.set_view(client, message)
        case p.FrameAck():
            session.on_frame_ack(client, message)
        case p.Pick():
            client.send(await session.pick(client, message))
        case p.Select():
            client.send(await session.select(client, message, guard.owner))
        case p.Ping():
            # pings are latency probes: under a flood, answer only while the peer keeps up
            if client.backlog < PONG_BACKLOG:
                client.send(
                    p.Pong(
                        ref=message.seq, client_time=message.client_time, server_time=time.time()
                    )
                )
        case p.Pong() | p.Error():
            if isinstance(message, p.Error):
                log.debug(  # peer-chosen text: quoted, cut short, not at info level
                    "client %s reported %s: %r",
                    client.client_id,
                    message.code,
                    message.message[:200],
                )
        case _:
            await session.steer(client, message)


def _session_full(session: Session, role: p.Role, settings: ServerSettings) -> str | None:
    """Why `session` has no place for a new `role` client (None: it has): all its places are
    taken, or, for a viewer, all but the `steerer_places` kept for steerers."""
    limit = settings.max_clients_per_session
    if len(session.clients) >= limit:
        return f"session {session.id!r} holds its limit of {limit} viewers and steerers"
    viewers = sum(1 for c in session.clients.values() if c.role == "viewer")
    if role == "viewer" and viewers >= limit - settings.steerer_places:
        return (
            f"session {session.id!r} holds its limit of {limit - settings.steerer_places} viewers "
            f"(max_clients_per_session less the steerer_places kept for steerers)"
        )
    return None
