"""The WebSocket transport: uvicorn's sans-I/O protocol with a small message limit until the
peer has said who it is.

uvicorn applies one `ws_max_size` to every connection before the application sees a byte; with
the simulations' limit (64 MiB) anyone could make the server buffer that much per socket without
a token. Here the limit starts at the viewers' (256 KiB) and the application raises it, through a
scope extension, only for a simulation whose `hello` was accepted. Frames over the limit are
refused from their header, before their payload is read (close code 1009).
"""

from __future__ import annotations

from collections.abc import Callable, MutableMapping
from typing import Any

from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

MESSAGE_LIMIT = "scalesteer.message_limit"
"""Scope extension: `{"set": callable(int)}` sets this connection's incoming message limit."""


def guarded_protocol(pre_hello_bytes: int) -> type[WebSocketsSansIOProtocol]:
    """A protocol class whose connections accept at most `pre_hello_bytes` per message until
    the application raises the limit."""

    class GuardedWebSocketProtocol(WebSocketsSansIOProtocol):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.conn.max_message_size = min(pre_hello_bytes, self.config.ws_max_size)

        def handle_connect(self, event: Any) -> None:
            super().handle_connect(event)
            scope = getattr(self, "scope", None)
            if scope is not None:
                scope["extensions"][MESSAGE_LIMIT] = {"set": self._set_limit}

        def _set_limit(self, size: int) -> None:
            self.conn.max_message_size = min(int(size), self.config.ws_max_size)

    return GuardedWebSocketProtocol


def raise_limit(scope: MutableMapping[str, Any], size: int) -> None:
    """Let this connection send messages of up to `size` bytes (a no-op on other servers)."""
    extension = scope.get("extensions", {}).get(MESSAGE_LIMIT)
    setter: Callable[[int], None] | None = extension.get("set") if extension else None
    if setter is not None:
        setter(size)
