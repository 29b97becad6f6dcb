"""Error codes of the wire protocol and the exception that carries one.

A code is stable and machine-readable; the message is for people and names the field path.
"""

from __future__ import annotations

from enum import StrEnum


class ErrorCode(StrEnum):
    """Stable error codes; never renumbered or reused (see docs/protocol.md)."""

    INVALID_MESSAGE = "invalid_message"
    UNKNOWN_TYPE = "unknown_type"
    TOO_LARGE = "too_large"
    UNAUTHORIZED = "unauthorized"
    FORBIDDEN = "forbidden"
    RATE_LIMITED = "rate_limited"
    VERSION_MISMATCH = "version_mismatch"
    NOT_READY = "not_ready"
    NOT_FOUND = "not_found"
    INTERNAL = "internal"
    CONFLICT = "conflict"
    """The session already has a simulation from another adapter instance."""
    CAPACITY = "capacity"
    """The server, the session or the token holds its limit of connections; try again later.
    With the path `view.video`: of video streams (the view gets JPEG images meanwhile)."""


class ProtocolError(Exception):
    """A rejected message: carries what the peer needs to build an `error` reply."""

    def __init__(
        self, code: ErrorCode, message: str, path: str | None = None, ref: int | None = None
    ) -> None:
        super().__init__(f"{code.value}: {message}")
        self.code = code
        self.message = message
        self.path = path
        self.ref = ref

    def with_ref(self, ref: int | None) -> ProtocolError:
        """The same error, echoing the offending message's `seq`."""
        return ProtocolError(self.code, self.message, self.path, ref)
