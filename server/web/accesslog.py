"""The server's logs without its tokens.

The dashboard's links carry the token in their query (`/?token=...`, like Jupyter's), and
uvicorn writes every request's path and query to its access log (and every WebSocket handshake's
to its error log), where anyone who reads the logs would find a token that grants every role.
`RedactTokens` replaces the value of every query parameter whose name holds `token` before a
record is formatted, the name read as the server reads it (percent-decoded: `?tok%65n=` is a
token too).
"""

from __future__ import annotations

import logging
import re
from urllib.parse import unquote_plus

_PARAM = re.compile(r"([?&])([^=&#\s\"]*)=([^&#\s\"]*)")
REDACTED = "[redacted]"
LOGGERS = ("uvicorn.access", "uvicorn.error")
"""uvicorn's request lines (HTTP) and handshake lines (WebSocket)."""


def redact(text: str) -> str:
    """`text` with the values of `token` query parameters replaced."""

    def value(m: re.Match[str]) -> str:
        if "token" in unquote_plus(m.group(2)).lower():
            return f"{m.group(1)}{m.group(2)}={REDACTED}"
        return m.group(0)

    return _PARAM.sub(value, text)


class RedactTokens(logging.Filter):
    """Replaces tokens in a record's message and arguments (it never drops a record)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        return True


def install() -> None:
    """Add the filter to uvicorn's loggers (once; after uvicorn configured its logging)."""
    for name in LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactTokens) for f in logger.filters):
            logger.addFilter(RedactTokens())
