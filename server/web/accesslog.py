"""The server's logs without its tokens.

The dashboard's links carry the token in their query (`/?token=...`, like Jupyter's), and
uvicorn writes every request's path and query to its access log (and every WebSocket handshake's
to its error log), where anyone who reads the logs would find a token that grants every role.
`RedactTokens` replaces the value of every query parameter whose name holds `token` before a
record is formatted, the name read as the server reads it (percent-decoded: `?tok%65n=` is a
token too), and the server's own tokens wherever else they appear (`/api/sessions/<token>`).
It also cuts a request line past `MAX_LINE_CHARS`: a client's 100 KB query string had been
written whole into the log on every request.
"""

from __future__ import annotations

import logging
import re
from urllib.parse import unquote_plus

_PARAM = re.compile(r"([?&])([^=&#\s\"]*)=([^&#\s\"]*)")
REDACTED = "[redacted]"
LOGGERS = ("uvicorn.access", "uvicorn.error")
"""uvicorn's request lines (HTTP) and handshake lines (WebSocket)."""
MAX_LINE_CHARS = 2000
"""The most of one string (a path and query) a log record keeps."""


def shorten(text: str, limit: int = MAX_LINE_CHARS) -> str:
    """`text`, cut after `limit` characters with a note of how many were left out."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}...[{len(text) - limit} more characters]"


def redact(text: str, secrets: tuple[str, ...] = ()) -> str:
    """`text` with the values of `token` query parameters replaced, and `secrets` (the server's
    own tokens) wherever else they appear (a client that put one in a path)."""

    def value(m: re.Match[str]) -> str:
        if "token" in unquote_plus(m.group(2)).lower():
            return f"{m.group(1)}{m.group(2)}={REDACTED}"
        return m.group(0)

    text = _PARAM.sub(value, text)
    for secret in secrets:
        text = text.replace(secret, REDACTED)
    return text


class RedactTokens(logging.Filter):
    """Replaces tokens in a record's message and arguments, and cuts an argument past
    `MAX_LINE_CHARS` (it never drops a record)."""

    def __init__(self, secrets: tuple[str, ...] = ()) -> None:
        super().__init__()
        self.secrets = tuple(s for s in secrets if s)

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg, self.secrets)
        if isinstance(record.args, tuple):
            record.args = tuple(
                shorten(redact(a, self.secrets)) if isinstance(a, str) else a for a in record.args
            )
        return True


def install(secrets: tuple[str | None, ...] = ()) -> None:
    """Add the filter to uvicorn's loggers (after uvicorn configured its logging); `secrets`:
    the tokens, redacted wherever they appear."""
    known = tuple(s for s in secrets if s)
    for name in LOGGERS:
        logger = logging.getLogger(name)
        for old in [f for f in logger.filters if isinstance(f, RedactTokens)]:
            logger.removeFilter(old)
        logger.addFilter(RedactTokens(known))
