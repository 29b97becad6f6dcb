"""Request validation failures as one sentence naming each field (and the file a field held),
instead of FastAPI's list of pydantic errors: the dashboard shows `detail` as it comes."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

MAX_SHOWN = 40
"""Characters of a refused value quoted back."""


def _where(loc: Sequence[Any]) -> str:
    parts = [str(x) for x in loc if x not in ("body", "query", "path", "header")]
    return ".".join(parts) or "the request"


def quoted(name: str, most: int = 80) -> str:
    """A name the client sent, quoted back in an error at most `most` characters long: a
    100,000-character session name was echoed whole."""
    text = repr(name)
    return text if len(text) <= most else text[: most - 1] + "…"


def _value(raw: Any) -> str:
    return quoted(raw, MAX_SHOWN) if isinstance(raw, str) else type(raw).__name__


def sentence(errors: Sequence[Any]) -> str:
    """`trajectory: expected a file, got the text '[]'; fps: ...`"""
    said = []
    for err in errors:
        where = _where(err.get("loc", ()))
        msg = str(err.get("msg", "invalid"))
        kind = err.get("type", "")
        if "UploadFile" in msg:
            said.append(f"{where}: expected a file, got the text {_value(err.get('input'))}")
        elif kind == "missing":
            said.append(f"{where}: required")
        elif kind == "json_invalid":  # its loc is a character offset, not a field
            why = str((err.get("ctx") or {}).get("error", "")).strip()
            at = [x for x in err.get("loc", ()) if isinstance(x, int)]
            place = f" at character {at[0]}" if at else ""
            said.append(f"the body is not valid JSON{place}" + (f" ({why})" if why else ""))
        else:
            msg = msg.removeprefix("Value error, ")
            said.append(f"{where}: {_lower_first(msg) if msg else 'invalid'}")
    return "; ".join(said) or "the request is not valid"


def _lower_first(msg: str) -> str:
    """`Input should be ...` -> `input should be ...`, but a word in capitals (`JSON`,
    `URL`) stays as it is."""
    first = msg.split(" ", 1)[0]
    return msg if first.isupper() else msg[0].lower() + msg[1:]


async def validation_failed(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return JSONResponse({"detail": sentence(exc.errors())}, status_code=422)
