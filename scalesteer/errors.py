"""What the Python client raises: one exception that carries the server's error code and path.

A WebSocket `error` message and an HTTP error answer both become a `ScalesteerError`, so a
notebook catches one type and reads `code` (a `protocol.ErrorCode`), `path` (the field that was
wrong, e.g. `render_params.params.sigma_A`) and, for REST calls, the HTTP `status`.
"""

from __future__ import annotations

import re

from protocol import Error, ErrorCode

# HTTP answers of the REST API, read as the wire protocol's codes (docs/server.md, "Limits")
_CODE_OF_STATUS = {
    400: ErrorCode.INVALID_MESSAGE,
    401: ErrorCode.UNAUTHORIZED,
    403: ErrorCode.FORBIDDEN,
    404: ErrorCode.NOT_FOUND,
    408: ErrorCode.NOT_READY,
    409: ErrorCode.CONFLICT,
    413: ErrorCode.TOO_LARGE,
    422: ErrorCode.INVALID_MESSAGE,
    429: ErrorCode.RATE_LIMITED,
    503: ErrorCode.CAPACITY,
}
# "params.layers.1.selection: ..." names the form field that was wrong
_FIELD_PREFIX = re.compile(r"^([A-Za-z_]\w*(?:\.\w+)*): ")


class ScalesteerError(Exception):
    """A refusal by the server (or by the protocol's models before anything was sent).

    `code`: the wire error code; `path`: the field it names (None when it names none); `ref`:
    the `seq` of the message refused; `status`: the HTTP status of a refused REST call."""

    def __init__(
        self,
        code: ErrorCode | str,
        message: str,
        path: str | None = None,
        *,
        ref: int | None = None,
        status: int | None = None,
    ) -> None:
        self.code = ErrorCode(code)
        self.message = message
        self.path = path
        self.ref = ref
        self.status = status
        where = f" (at {path})" if path and path not in message else ""
        super().__init__(f"{self.code.value}: {message}{where}")

    @classmethod
    def of(cls, error: Error) -> ScalesteerError:
        """The exception for an `error` message from the server."""
        return cls(error.code, error.message, error.path, ref=error.ref)

    @classmethod
    def of_http(cls, status: int, detail: str) -> ScalesteerError:
        """The exception for a REST answer `status` whose body said `detail`."""
        code = _CODE_OF_STATUS.get(status, ErrorCode.INTERNAL)
        match = _FIELD_PREFIX.match(detail)
        return cls(code, detail, match.group(1) if match else None, status=status)


class ServerStartError(RuntimeError):
    """The local server could not be started (its log's last lines say why)."""
