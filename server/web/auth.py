"""Who may do what: tokens grant roles, Origins are checked, steering is rate-limited per client."""

from __future__ import annotations

import hmac
import time
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from protocol import ErrorCode, Role
from server.settings import ServerSettings, is_loopback

STEERING_TYPES = frozenset({"sim_params", "control", "forces", "pull", "render_params"})
SIMULATION_TYPES = frozenset({"topology", "frame", "params_ack", "engine", "event"})
VIEWER_TYPES = frozenset({"view", "pick", "select", "ping", "pong", "error", "frame_ack"})


def _same(a: str | None, b: str | None) -> bool:
    return a is not None and b is not None and hmac.compare_digest(a.encode(), b.encode())


def grant(settings: ServerSettings, token: str | None, role: Role) -> Role | None:
    """The role a token earns for the requested role, or None when refused.

    The server token grants any role; the viewer token only `viewer`.
    """
    if settings.open_on_loopback or _same(token, settings.token):
        return role
    if role == "viewer" and _same(token, settings.viewer_token):
        return "viewer"
    return None


def refusal(settings: ServerSettings, token: str | None, role: Role) -> tuple[ErrorCode, str, str]:
    """Why `grant` refused: (error code, message, field). The viewer token asking for another
    role is told so (forbidden, as REST's 403), not that its token is wrong."""
    if token_role(settings, token) == "viewer":
        why = f"the viewer token is read-only: role {role} needs the server token"
        return ErrorCode.FORBIDDEN, why, "hello.role"
    return ErrorCode.UNAUTHORIZED, "missing or wrong token", "hello.token"


def token_role(settings: ServerSettings, token: str | None) -> Role | None:
    """The strongest role a token carries (REST access)."""
    if settings.open_on_loopback or _same(token, settings.token):
        return "steerer"
    if _same(token, settings.viewer_token):
        return "viewer"
    return None


def may_send(role: Role, kind: str) -> bool:
    """Whether a connection with `role` may send a message of type `kind`."""
    if kind in VIEWER_TYPES:
        return True
    if role == "simulation":
        return kind in SIMULATION_TYPES
    if role == "steerer":
        return kind in STEERING_TYPES
    return False


LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


def _hostname(host_header: str) -> str:
    host = host_header.strip().lower()
    if host.startswith("["):  # [::1]:8000
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def host_allowed(settings: ServerSettings, host_header: str | None) -> bool:
    """A loopback-bound server answers only to loopback names (or allow-listed hosts), so a
    web page cannot reach it through a DNS name rebound to 127.0.0.1."""
    if not is_loopback(settings.host):
        return True
    if not host_header:
        return False
    extra = {urlsplit(o).hostname for o in settings.allowed_origins if o != "*"}
    return _hostname(host_header) in LOOPBACK_NAMES | {h for h in extra if h}


def origin_allowed(settings: ServerSettings, origin: str | None, host_header: str | None) -> bool:
    """Browsers must come from this server's own origin or the allow-list; scripts send none."""
    if origin is None:
        return True
    origin = origin.rstrip("/")
    if origin in settings.allowed_origins or "*" in settings.allowed_origins:
        return True
    own = {f"http://{settings.host}:{settings.port}", f"https://{settings.host}:{settings.port}"}
    if host_header and host_allowed(settings, host_header):
        own |= {f"http://{host_header}", f"https://{host_header}"}
    if settings.host in ("127.0.0.1", "localhost", "::1"):
        own |= {f"http://localhost:{settings.port}", f"http://127.0.0.1:{settings.port}"}
    return origin in own


@dataclass
class RateLimiter:
    """Token bucket: `rate` per second with a burst of `burst`."""

    rate: float
    burst: float
    tokens: float = -1.0
    stamp: float = 0.0

    def allow(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        if self.tokens < 0:
            self.tokens, self.stamp = self.burst, now
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    def wait_s(self) -> float:
        """Seconds until the next call would be allowed."""
        return max(0.0, (1.0 - self.tokens) / self.rate)

    def full(self, now: float) -> bool:
        """Whether the bucket has refilled (a fresh one would be no different)."""
        return self.tokens < 0 or self.tokens + (now - self.stamp) * self.rate >= self.burst


LOOPBACK_CLIENT = "loopback"
"""The one address every loopback client is counted as."""


def client_address(host: str | None) -> str:
    """The address a client's rate limits and budgets follow: its connection's, with every
    loopback address (all of 127.0.0.0/8 and ::1) counted as one, since a local process may
    bind any of them and would otherwise get a fresh budget from each."""
    if not host:
        return ""
    ip = host[7:] if host.startswith("::ffff:") else host  # IPv4 written as IPv6
    return LOOPBACK_CLIENT if is_loopback(ip) else host


ANY_PER_STEER = 20
"""Other messages (views, picks, pings) a client may send per steering message allowed."""


@dataclass
class ClientBudget:
    """What one client may still send: steering messages, and all others."""

    steer: RateLimiter
    any: RateLimiter
    users: int = 0
    """Connections of this client open now."""


@dataclass
class ClientBudgets:
    """Rate limits per client, not per connection: a client is a role at a remote address, so
    one that reconnects (or opens several connections) finds its budget as it left it. Budgets
    nobody uses are forgotten once they have refilled."""

    _budgets: dict[tuple[str, str], ClientBudget] = field(default_factory=dict)

    def take(self, role: str, address: str, steer_per_s: float) -> ClientBudget:
        """The budget of `role` at `address` (steering at `steer_per_s`, bursts as large),
        counted as used until `give_back`."""
        now = time.monotonic()
        for key, idle in list(self._budgets.items()):
            if idle.users == 0 and idle.steer.full(now) and idle.any.full(now):
                del self._budgets[key]
        budget = self._budgets.get((role, address))
        if budget is None:
            others = ANY_PER_STEER * steer_per_s
            budget = self._budgets[(role, address)] = ClientBudget(
                RateLimiter(steer_per_s, max(1.0, steer_per_s)),
                RateLimiter(others, max(1.0, others)),
            )
        budget.users += 1
        return budget

    def give_back(self, budget: ClientBudget) -> None:
        budget.users -= 1

    def __len__(self) -> int:
        return len(self._budgets)
