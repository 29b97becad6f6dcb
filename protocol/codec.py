"""msgpack encoding and checked decoding of protocol messages.

`decode` never raises anything but `ProtocolError`: every malformed, oversized or hostile byte
string becomes a coded error naming the field path, which the receiver can send back as `error`.
"""

from __future__ import annotations

from typing import Any

import msgpack
from pydantic import TypeAdapter, ValidationError

from protocol.errors import ErrorCode, ProtocolError
from protocol.fields import error_location, unknown_keys
from protocol.limits import DEFAULT_LIMITS, Limits
from protocol.messages import MESSAGE_TYPES, PROTOCOL_VERSION, AnyMessage, Error, Message

_ADAPTER: TypeAdapter[AnyMessage] = TypeAdapter(AnyMessage)
_MAX_CONTAINER_ENTRIES = 100_000


FRAGMENT_BYTES = 256 * 1024
"""Messages larger than this go out as WebSocket fragments of this size (`fragments`)."""


def fragments(data: bytes) -> bytes | list[memoryview]:
    """What to hand a WebSocket `send`: a large message (a frame of many atoms) as fragments of
    `FRAGMENT_BYTES`, a small one whole. The receiver then parses and unmasks each fragment
    as it arrives instead of buffering the whole message and unmasking it in one go: for 12 MB
    that held a server's event loop for up to 8 ms at a time and took 2.6x the loop time in
    all (benchmarks/ws_parse_bench.py), time every other viewer's messages waited for."""
    if len(data) <= FRAGMENT_BYTES:
        return data
    view = memoryview(data)
    return [view[i : i + FRAGMENT_BYTES] for i in range(0, len(data), FRAGMENT_BYTES)]


def encode(message: Message) -> bytes:
    """Serialize a message; None fields are omitted (their default applies on decode)."""
    raw: bytes = msgpack.packb(
        message.model_dump(mode="python", exclude_none=True), use_bin_type=True
    )
    return raw


def unpack(raw: bytes, limits: Limits = DEFAULT_LIMITS) -> Any:
    """msgpack-decode with every length bounded by the message-size limit."""
    if not isinstance(raw, bytes | bytearray | memoryview):
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "message must be binary msgpack")
    if len(raw) > limits.max_message_bytes:
        raise ProtocolError(
            ErrorCode.TOO_LARGE,
            f"message of {len(raw)} bytes exceeds the limit of {limits.max_message_bytes}",
        )
    n = max(len(raw), 1)
    try:
        return msgpack.unpackb(
            raw,
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_bin_len=n,
            max_str_len=n,
            # per-atom string lists (names, elements) may be as long as the atom limit
            max_array_len=min(n, limits.max_atoms + _MAX_CONTAINER_ENTRIES),
            max_map_len=min(n, _MAX_CONTAINER_ENTRIES),
            max_ext_len=0,
        )
    except ValueError as exc:
        # a container longer than the atom limit allows is too large; any other declared
        # length beyond the message's own size means the bytes are cut or corrupt
        if "max_array_len" in str(exc) and limits.max_atoms + _MAX_CONTAINER_ENTRIES < n:
            raise ProtocolError(ErrorCode.TOO_LARGE, f"a list exceeds the limits ({exc})") from None
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "not valid msgpack: ValueError") from None
    except Exception as exc:  # msgpack raises many types for corrupt input
        raise ProtocolError(
            ErrorCode.INVALID_MESSAGE, f"not valid msgpack: {type(exc).__name__}"
        ) from None


def _path(loc: tuple[int | str, ...], kind: str) -> str:
    # pydantic puts the union tag first in the location; drop it, keep the fields
    parts = [str(p) for p in loc]
    if parts and parts[0] == kind:
        parts = parts[1:]
    parts = [p for p in parts if not p.startswith("function-")]
    return ".".join([kind, *parts])


_CODE_BY_PYDANTIC_TYPE = {
    "too_large": ErrorCode.TOO_LARGE,
    "union_tag_invalid": ErrorCode.UNKNOWN_TYPE,
}


def ref_of(obj: dict[str, Any]) -> int | None:
    """An unchecked message's `seq`, when it is one an error may name as its `ref`."""
    seq = obj.get("seq")
    return seq if isinstance(seq, int) and not isinstance(seq, bool) and 0 <= seq < 2**53 else None


def validate(
    obj: Any, limits: Limits = DEFAULT_LIMITS, requests: frozenset[str] = frozenset()
) -> Message:
    """Turn an unpacked object into a message, or raise a `ProtocolError`.

    Fields a model does not know are ignored (a newer peer's), except in the message types
    named in `requests`: a request to change something (the server passes its steering types)
    with a key no field has is refused by name, nested models and lists of them included. A
    misspelt `iso_levle` dropped in silence would be answered as if it had applied."""
    if not isinstance(obj, dict):
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "message must be a map", path="")
    ref = ref_of(obj)
    kind = obj.get("type")
    if not isinstance(kind, str):
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "missing string field 'type'", "type", ref)
    if kind not in MESSAGE_TYPES:
        raise ProtocolError(
            ErrorCode.UNKNOWN_TYPE, f"unknown message type {kind[:64]!r}", "type", ref
        )
    if kind == "hello":
        version = obj.get("protocol_version", PROTOCOL_VERSION)
        if not isinstance(version, str) or version.split(".")[0] != PROTOCOL_VERSION.split(".")[0]:
            raise ProtocolError(
                ErrorCode.VERSION_MISMATCH,
                f"protocol version {str(version)[:32]!r} is not compatible with {PROTOCOL_VERSION}",
                "hello.protocol_version",
                ref,
            )
    if kind in requests:
        unknown = unknown_keys(MESSAGE_TYPES[kind], obj, kind)
        if unknown is not None:
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE, f"{unknown}: unknown field", unknown, ref
            )
    try:
        message: Message = _ADAPTER.validate_python(obj, context={"limits": limits})
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        code = _CODE_BY_PYDANTIC_TYPE.get(err["type"], ErrorCode.INVALID_MESSAGE)
        loc, msg = error_location(err)
        path = _path(tuple(loc), kind)
        raise ProtocolError(code, f"{path}: {msg}", path, ref) from None
    except Exception as exc:  # a validator bug must not take the connection down
        raise ProtocolError(
            ErrorCode.INVALID_MESSAGE, f"{kind}: rejected ({type(exc).__name__})", kind, ref
        ) from None
    return message


def decode(
    raw: bytes, limits: Limits = DEFAULT_LIMITS, requests: frozenset[str] = frozenset()
) -> Message:
    """Bytes -> message; raises only `ProtocolError` (`requests`: see `validate`)."""
    return validate(unpack(raw, limits), limits, requests)


def error_message(err: ProtocolError) -> Error:
    """The `error` message that reports `err` to the peer."""
    return Error(code=err.code, message=err.message[:4096], path=err.path, ref=err.ref)
