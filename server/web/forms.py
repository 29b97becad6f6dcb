"""Endpoints whose input is form fields (uploads beside them): any other body is refused."""

from __future__ import annotations

import collections.abc
import types
from typing import Annotated, Any, Union, get_args, get_origin

from fastapi import Depends, HTTPException, Request

from server.web.validation import quoted

FORM_TYPES = ("multipart/form-data", "application/x-www-form-urlencoded")
_LISTS = (list, tuple, set, frozenset, collections.abc.Sequence)


def repeatable(annotation: Any) -> bool:
    """Whether a form parameter of this type takes the field several times (a list of
    uploads: `trajectory` given once per file)."""
    origin = get_origin(annotation)
    if origin is Annotated:
        return repeatable(get_args(annotation)[0])
    if origin is Union or origin is types.UnionType:
        return any(repeatable(arg) for arg in get_args(annotation))
    return origin in _LISTS or annotation in _LISTS


async def form_body(request: Request) -> None:
    """Endpoints of form fields refuse any other body (415): a JSON body there would be read as
    no fields at all, and the defaults would run (a 1,800-frame movie for `{"fps": 10}`). A
    field the endpoint has no parameter for, or one given twice, is refused by name (422): a
    misspelt `widht` was dropped and the default width drawn, and of two `width`s the last
    one was taken, as if the request had said what it meant (a list, such as `trajectory`,
    takes its field once per item). An empty value (`width=`) is
    refused too: it was taken as no field, and the default drawn in silence."""
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
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if not has_body or dependant is None:
        return
    known = {field.alias for field in dependant.body_params}
    lists = {f.alias for f in dependant.body_params if repeatable(f.field_info.annotation)}
    seen: set[str] = set()
    for name, value in (await request.form()).multi_items():  # parsed already: the cached form
        if name not in known:
            takes = ", ".join(sorted(known))
            raise HTTPException(
                422, f"{quoted(name)}: unknown form field (this endpoint takes {takes})"
            )
        if name in seen and name not in lists:
            raise HTTPException(422, f"{quoted(name)}: form field given more than once")
        if isinstance(value, str) and not value:
            raise HTTPException(
                422, f"{quoted(name)}: empty form field (leave it out to take its default)"
            )
        seen.add(name)


FormBody = Annotated[None, Depends(form_body)]
