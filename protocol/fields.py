"""Unknown keys in a client's own JSON: the wire models ignore fields they do not know (a newer
peer's), but a person's typo (`sigmaa`) must be named, not dropped, wherever a person writes the
JSON or keyword arguments: REST `params`, the command line's `--params` and `--layers`, the
Python client, and the steering messages the server reads on its WebSocket (whoever wrote them)."""

from __future__ import annotations

import typing
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
