"""Endpoints whose input is form fields (uploads beside them): any other body is refused."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request

FORM_TYPES = ("multipart/form-data", "application/x-www-form-urlencoded")


def form_body(request: Request) -> None:
    """Endpoints of form fields refuse any other body (415): a JSON body there would be read as
    no fields at all, and the defaults would run (a 1,800-frame movie for `{"fps": 10}`)."""
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    has_body = request.headers.get("content-length", "0") != "0" or (
        "transfer-encoding" in request.headers
    )
    if has_body and kind not in FORM_TYPES:
        raise HTTPException(
            415,
            f"this endpoint takes form fields ({' or '.join(FORM_TYPES)}), "
            f"not {kind or 'a body without a content type'}; JSON goes in fields such as params",
        )


FormBody = Annotated[None, Depends(form_body)]
