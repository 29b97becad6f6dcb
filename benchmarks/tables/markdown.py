"""What every README table states and how it is laid out: the files it read, the GPU each one
records ("no GPU" for a run on the CPU device, "GPU not recorded" where a file says neither),
and markdown rows of figures taken from the files as they are."""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

Results = dict[str, Any]


Source = tuple[str, Results]
"""A results file's name (in results/) and its loaded JSON."""


NOT_RECORDED = "GPU not recorded"


NO_GPU = "no GPU"


class TableError(ValueError):
    """A results file lacks what its table reads, or the README's markers do not match TABLES."""


def gpu_of(res: Results) -> str:
    """The GPU a results file says it ran on, "no GPU" for a run on the CPU device, or
    "GPU not recorded" where the file says neither."""
    gpus = res.get("gpus")
    if isinstance(gpus, list) and gpus:
        names = sorted(set(gpus))
        return f"{len(gpus)}x {names[0]}" if len(names) == 1 else " + ".join(gpus)
    gpu = res.get("gpu")
    if isinstance(gpu, str) and gpu and gpu != "cpu":
        return gpu
    device = res.get("device")
    if isinstance(device, str) and device and device != "cpu" and not device.startswith("cuda"):
        return device
    devices = res.get("devices")
    on_cpu = gpu == "cpu" or device == "cpu"
    if isinstance(devices, list) and devices and all(d == "cpu" for d in devices):
        on_cpu = True
    if on_cpu or "no GPU" in str(res.get("machine", "")):
        return NO_GPU
    return NOT_RECORDED


def cores_of(res: Results) -> int | None:
    """The host's CPU cores where the file records them."""
    for key in ("host_cpus", "cpus"):
        if isinstance(res.get(key), int):
            return int(res[key])
    match = re.search(r"(\d+) cores", str(res.get("machine", "")))
    return int(match.group(1)) if match else None


def caption(sources: Iterable[Source], note: str = "") -> str:
    """The line above a table: each file it read, the GPU it records, cores, date, warp, and
    a note (what the run was set to, from the files)."""
    parts = []
    for name, res in sources:
        bits = [gpu_of(res)]
        cores = cores_of(res)
        if cores:
            bits.append(f"{cores} host cores")
        if res.get("date"):
            bits.append(str(res["date"]))
        if res.get("warp"):
            bits.append(f"warp {res['warp']}")
        parts.append(f"`{name}` ({', '.join(bits)})")
    return "From " + "; ".join(parts) + (f"; {note}" if note else "") + ":"


def table(header: list[str], align: str, rows: Iterable[list[str]]) -> list[str]:
    """A markdown table; `align` has one letter per column, r (numbers) or l."""
    marks = {"r": "---:", "l": "---"}
    out = ["| " + " | ".join(header) + " |", "| " + " | ".join(marks[a] for a in align) + " |"]
    out += ["| " + " | ".join(row) + " |" for row in rows]
    return out


def num(x: float | None, digits: int = 2) -> str:
    """A figure with thousands separators; blank where the file has none."""
    return "" if x is None else f"{x:,.{digits}f}"


def count(n: int) -> str:
    """An atom count as the README writes it: 496, 5,684, 100k, 1M."""
    if n >= 1_000_000 and n % 1_000_000 == 0:
        return f"{n // 1_000_000}M"
    if n >= 100_000 and n % 1_000 == 0:
        return f"{n // 1_000}k"
    return f"{n:,}"


def size(w: int, h: int) -> str:
    return f"{w}x{h}"


def stem(name: str, prefix: str) -> str:
    return name.removesuffix(".json").removeprefix(prefix)


def block(sources: list[Source], lines: list[str], note: str = "") -> str:
    """A table right under its caption line (GitHub's markdown starts a table there)."""
    return "\n".join([caption(sources, note), *lines]) + "\n"
