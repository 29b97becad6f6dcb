"""Naming the field a client got wrong. Unknown keys in a client's own JSON: the wire models
ignore fields they do not know (a newer peer's), but a person's typo (`sigmaa`) must be named,
not dropped, wherever a person writes the JSON or keyword arguments: REST `params`, the command
line's `--params` and `--layers`, the Python client, and the steering messages the server reads
on its WebSocket (whoever wrote them). And the field of a refused value (`error_location`)."""

from __future__ import annotations

import typing
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel


def unknown_keys(cls: type[BaseModel], data: Any, where: str) -> str | None:
    """The path of the first key in `data` that `cls` (or a model nested in it) has no field
    for, or None."""
    if not isinstance(data, dict):
        return None
    for key, value in data.items():
        info = cls.model_fields.get(str(key))
        if info is None:
            return f"{where}.{key}"
        for model in _models_in(info.annotation):
            items = enumerate(value) if isinstance(value, list) else [(None, value)]
            for i, item in items:
                path = f"{where}.{key}" if i is None else f"{where}.{key}.{i}"
                found = unknown_keys(model, item, path)
                if found:
                    return found
    return None


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The models an annotation holds: itself, or inside Optional, list[...], Annotated."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]


def error_location(err: Mapping[str, Any]) -> tuple[list[str], str]:
    """A pydantic error's path and message. A check of the whole model that names a field
    (`true` given for `sigma_A`, `messages.Model`) is filed by pydantic under the model's own
    path: the field is put on the path and taken off the front of the message."""
    loc = [str(x) for x in err["loc"] if not str(x).startswith("function-")]
    msg = str(err["msg"])
    field = (err.get("ctx") or {}).get("field")
    if field is not None:
        loc.append(str(field))
        msg = msg.removeprefix(f"{field}: ")
    return loc, msg
