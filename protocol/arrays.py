"""Arrays on the wire: `{dtype, shape, data}` with raw little-endian bytes, never lists.

Validation checks dtype, shape and byte length against each other and against the connection's
limits before any numpy array exists, so a hostile declared shape costs nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Annotated, Any

import numpy as np
import numpy.typing as npt
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationInfo
from pydantic_core import PydanticCustomError

from protocol.limits import DEFAULT_LIMITS, Limits

#: dtypes a peer may send; all explicitly little-endian (or byte-sized).
ALLOWED_DTYPES: frozenset[str] = frozenset({"<f4", "<f8", "<i4", "<i8", "<u4", "<u2", "|u1"})
MAX_NDIM = 4


def limits_from(info: ValidationInfo) -> Limits:
    """The limits passed as validation context, or the defaults."""
    ctx = info.context
    if isinstance(ctx, dict):
        lim = ctx.get("limits")
        if isinstance(lim, Limits):
            return lim
    return DEFAULT_LIMITS


class WireArray(BaseModel):
    """An n-dimensional array as raw bytes. Use `from_numpy` / `to_numpy`."""

    model_config = ConfigDict(frozen=True, extra="ignore")

    dtype: str = Field(description="numpy dtype string, e.g. '<f4', '<i4', '|u1'")
    shape: tuple[Annotated[int, Field(ge=0)], ...] = Field(max_length=MAX_NDIM)
    data: bytes = Field(description="raw little-endian bytes, C order")

    @classmethod
    def from_numpy(cls, array: npt.ArrayLike, dtype: str | None = None) -> WireArray:
        """Pack an array; `dtype` converts first (e.g. float64 positions to '<f4')."""
        a = np.asarray(array)
        if dtype is not None:
            a = a.astype(np.dtype(dtype), copy=False)
        dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
        a = np.ascontiguousarray(a, dtype=dt)
        return cls(dtype=a.dtype.str, shape=tuple(int(s) for s in a.shape), data=a.tobytes())

    def to_numpy(self) -> npt.NDArray[Any]:
        """A read-only view of the bytes (no copy)."""
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype)).reshape(self.shape)

    @property
    def count(self) -> int:
        return math.prod(self.shape)


def all_finite(a: npt.NDArray[Any]) -> bool:
    """True when no element is NaN or Inf, in one pass without a temporary array.

    A sum is NaN or Inf whenever an element is; a non-finite sum of finite elements (an
    overflow) is told apart by the exact element test, which only such arrays pay for.
    """
    if a.size == 0:
        return True
    with np.errstate(over="ignore", invalid="ignore"):
        if bool(np.isfinite(a.sum())):
            return True
    return bool(np.isfinite(a).all())


def _check_wire(arr: WireArray, limits: Limits) -> None:
    if arr.dtype not in ALLOWED_DTYPES:
        raise PydanticCustomError(
            "invalid_array",
            "dtype {dtype} not allowed (one of {allowed})",
            {"dtype": repr(arr.dtype), "allowed": ", ".join(sorted(ALLOWED_DTYPES))},
        )
    count = arr.count  # python ints: a declared 10**12 cannot overflow
    cap = limits.max_atoms * 9
    if count > cap:
        raise PydanticCustomError(
            "too_large",
            "array declares {count} elements, limit is {cap}",
            {"count": count, "cap": cap},
        )
    expected = count * np.dtype(arr.dtype).itemsize
    if expected != len(arr.data):
        raise PydanticCustomError(
            "invalid_array",
            "shape {shape} of {dtype} needs {expected} bytes, got {got}",
            {
                "shape": list(arr.shape),
                "dtype": arr.dtype,
                "expected": expected,
                "got": len(arr.data),
            },
        )


def array_spec(
    dtype: str,
    ndim: int,
    trailing: tuple[int, ...] = (),
    *,
    finite: bool = False,
    atoms: bool = True,
) -> Callable[[WireArray, ValidationInfo], WireArray]:
    """A validator for one array field: exact dtype, rank, fixed trailing dims, finiteness.

    `atoms=True` means the first axis counts atoms and is bounded by `Limits.max_atoms`.
    """

    def check(arr: WireArray, info: ValidationInfo) -> WireArray:
        limits = limits_from(info)
        _check_wire(arr, limits)
        if arr.dtype != dtype:
            raise PydanticCustomError(
                "invalid_array",
                "dtype must be {want}, got {got}",  # no conversions: pydantic fills {name}
                {"want": repr(dtype), "got": repr(arr.dtype)},
            )
        if len(arr.shape) != ndim or (trailing and tuple(arr.shape[1:]) != trailing):
            want = "(n" + "".join(f", {t}" for t in trailing) + ")" if trailing else f"{ndim}-d"
            raise PydanticCustomError(
                "invalid_array",
                "shape must be {want}, got {got}",
                {"want": want, "got": list(arr.shape)},
            )
        if atoms and arr.shape and arr.shape[0] > limits.max_atoms:
            raise PydanticCustomError(
                "too_large",
                "{n} atoms exceed the limit of {cap}",
                {"n": arr.shape[0], "cap": limits.max_atoms},
            )
        if finite and arr.dtype[1] == "f" and not all_finite(arr.to_numpy()):
            raise PydanticCustomError("not_finite", "array contains NaN or Inf", {})
        return arr

    return check


Positions = Annotated[WireArray, AfterValidator(array_spec("<f4", 2, (3,), finite=True))]
"""(n, 3) float32 positions or vectors, finite."""
Box = Annotated[WireArray, AfterValidator(array_spec("<f4", 2, (3,), finite=True, atoms=False))]
"""(3, 3) float32 box vectors (rows), angstrom."""
AtomFloats = Annotated[WireArray, AfterValidator(array_spec("<f4", 1, finite=True))]
"""(n,) float32 per-atom values."""
AtomInts = Annotated[WireArray, AfterValidator(array_spec("<i4", 1))]
"""(n,) int32 per-atom values or indices."""
Bonds = Annotated[WireArray, AfterValidator(array_spec("<i4", 2, (2,)))]
"""(m, 2) int32 atom index pairs."""
Colors = Annotated[WireArray, AfterValidator(array_spec("|u1", 2, (4,)))]
"""(n, 4) uint8 RGBA colours."""
Floats = Annotated[WireArray, AfterValidator(array_spec("<f4", 1, finite=True, atoms=False))]
"""(k,) float32 values that are not per atom (histograms)."""
