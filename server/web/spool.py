"""Where request bodies wait while they are parsed: the server's own spool directory, bounded.

Starlette spools each uploaded file to a temporary file in the system's temporary directory
(`$TMPDIR`, often a small tmpfs shared with everything else) once it passes 1 MiB in memory.
Here uploads spool into `<state-dir>/spool` instead, each file keeps at most `IN_MEMORY_BYTES`
in memory, a form holds at most `MAX_FILES` files and `MAX_FIELDS` fields, and the bodies being
received at once are bounded together (`Spool.total`), so uploads cannot fill a disk or the
memory they were not given. Spooled files are anonymous (unlinked as they are made): a server
killed mid-upload leaves nothing behind.
"""

from __future__ import annotations

import logging
from contextlib import aclosing
from dataclasses import dataclass
from pathlib import Path
from tempfile import SpooledTemporaryFile
from typing import Any

from fastapi import HTTPException
from starlette.datastructures import FormData
from starlette.formparsers import MultiPartException, MultiPartParser
from starlette.requests import Request

SPOOL = "scalesteer.spool"
"""Scope key of the server's `Spool` (set by `server.web.middleware.UploadLimit`)."""
IN_MEMORY_BYTES = 256 * 1024
"""Bytes of one uploaded file kept in memory before it moves to the spool directory."""
MAX_FILES = 32
MAX_FIELDS = 64
"""Files and plain fields of one form (a field is at most 1 MiB)."""
PARSER_LOG = "python_multipart"
"""The multipart parser's logger. Its warnings are about the body a client sent, most of them
the message of the exception it raises next, which the client is answered with
(`_multipart_refusal`): logged as well, a client could write a line into the server's log with
every malformed request. Only its errors are kept."""
logging.getLogger(PARSER_LOG).setLevel(logging.ERROR)


@dataclass
class Spool:
    """The spool directory and what may wait in it: `limit` bytes per request body, `total`
    bytes of all the bodies being received at once, `viewer_total` of them for requests that
    do not hold the server token (the read-only link is handed out widely: its holders must
    not be able to take the whole spool from the server token's uploads)."""

    directory: Path
    limit: int
    total: int
    viewer_total: int | None = None
    """None: as `total`."""
    held: int = 0
    """Bytes of bodies being received now (declared lengths are held from the start)."""
    viewer_held: int = 0

    def take(self, size: int, viewer: bool = False) -> str | None:
        """Hold `size` more bytes of body (`viewer`: of a request without the server token);
        the reason, naming the limit, when that would pass one (and nothing is held)."""
        viewer_total = self.total if self.viewer_total is None else self.viewer_total
        if self.held + size > self.total:
            return (
                f"the server is receiving {self.held} bytes of uploads already, its limit is "
                f"{self.total} (max_spool_bytes); try again later"
            )
        if viewer and self.viewer_held + size > viewer_total:
            return (
                f"uploads without the server token take {self.viewer_held} bytes of the spool "
                f"already, their limit is {viewer_total} (viewer_spool_bytes); try again later"
            )
        self.held += size
        if viewer:
            self.viewer_held += size
        return None

    def give_back(self, size: int, viewer: bool = False) -> None:
        self.held -= size
        if viewer:
            self.viewer_held -= size


class SpoolingParser(MultiPartParser):
    """Starlette's multipart parser, its files spooled into `directory`."""

    spool_max_size = IN_MEMORY_BYTES

    def __init__(self, *args: Any, directory: Path, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.directory = directory

    def on_headers_finished(self) -> None:
        super().on_headers_finished()
        upload = self._current_part.file
        if upload is not None:  # a file part: its (still empty) spool goes to our directory
            spooled = SpooledTemporaryFile(  # noqa: SIM115 (closed with the form)
                max_size=self.spool_max_size, dir=str(self.directory)
            )
            self._files_to_close_on_error[-1].close()
            self._files_to_close_on_error[-1] = spooled
            upload.file = spooled  # type: ignore[assignment]


def _multipart_refusal(exc: MultiPartException) -> str:
    """The parser's own words where it has them: its bare "Invalid multipart data." named
    neither a wrong boundary nor a broken part header."""
    cause = exc.__cause__
    if cause is None or not str(cause):
        return exc.message
    return (
        f"the multipart body could not be read: {str(cause)[:200]} (check the boundary the "
        "content-type names and each part's headers)"
    )


class SpoolingRequest(Request):
    """A request whose multipart form spools into the server's spool directory, within the
    spool's file and field counts (400 naming the count beyond them)."""

    async def _get_form(self, **limits: Any) -> FormData:
        spool: Spool | None = self.scope.get(SPOOL)
        content_type = self.headers.get("content-type", "").split(";")[0].strip().lower()
        if self._form is None and spool is not None and content_type == "multipart/form-data":
            limits["max_files"] = min(limits.get("max_files", MAX_FILES), MAX_FILES)
            limits["max_fields"] = min(limits.get("max_fields", MAX_FIELDS), MAX_FIELDS)
            try:
                async with aclosing(self.stream()) as stream:
                    parser = SpoolingParser(
                        self.headers, stream, directory=spool.directory, **limits
                    )
                    self._form = await parser.parse()
            except MultiPartException as exc:
                raise HTTPException(400, _multipart_refusal(exc)) from None
        form: FormData = await super()._get_form(**limits)
        return form
