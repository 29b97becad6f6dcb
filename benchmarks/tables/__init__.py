"""The numbers tables of benchmarks/README.md, made from the committed results files.

Every table is a pure function from loaded results (the JSON a benchmark wrote) to markdown
(`render.py`, `geodesic.py`, `parts.py`, `server.py`) and names the files it read and the GPU
each one records (`markdown.py`), so no figure in the README is typed by hand. `TABLES` says
which results files each table reads: the newest full run of its benchmark on each GPU it
shows. The README holds each table between `<!-- bench-tables: NAME -->` and
`<!-- /bench-tables -->`.

    python -m benchmarks.tables            # rewrite the README's tables (make bench-tables)
    python -m benchmarks.tables --check    # exit 1, naming the tables, if the README differs

A results file that lacks what its table reads is refused with the table, the file and the
field named (`TableError`), as a schema check would. Only the standard library is used, so the
tables can be made and checked on any machine.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .geodesic import (
    geodesic_fast_fill,
    geodesic_fill,
    geodesic_gate,
    geodesic_line_weights,
    geodesic_route_major,
    geodesic_route_math,
    geodesic_route_once,
    route_sharing,
    side_walk,
    visible_bricks,
)
from .markdown import Results, Source, TableError
from .parts import part_trial
from .render import (
    layers,
    multi_device,
    periodic,
    periodic_live,
    reach,
    render_densities,
    render_kernels,
    render_passes,
    render_variants,
    sort_last,
    temporal,
)
from .server import (
    adapter,
    batch,
    cpu_demo_chromium,
    cpu_interactive,
    flood,
    latency_delivery,
    latency_stages,
    latency_steer,
    multi_session,
    oneoff,
    pipeline,
    trajectory,
    video_live,
    video_quality,
    widget,
    ws_parse,
)

HERE = Path(__file__).resolve().parents[1]
RESULTS = HERE / "results"
README = HERE / "README.md"

__all__ = ["README", "RESULTS", "TABLES", "Table", "TableError", "differing", "fill", "generate"]


@dataclass(frozen=True)
class Table:
    """A README table: the results files it reads (in results/) and what makes it."""

    files: tuple[str, ...]
    make: Callable[[list[Source]], str]


TABLES: dict[str, Table] = {
    "render-today": Table(
        ("render_h200_shares.json", "render_h200_shares_volume.json"), render_variants
    ),
    "render-densities": Table(("render_h200_densities.json",), render_densities),
    "render-passes": Table(("render_cpu_round7_passes.json",), render_passes),
    "geodesic-sides": Table(
        ("render_h200_geodesic_sides.json", "render_cpu_2core_geodesic_sides.json"),
        render_variants,
    ),
    "side-walk": Table(("side_walk_work.json",), side_walk),
    "route-sharing": Table(("side_walk_work.json",), route_sharing),
    "part-trial": Table(
        (
            "render_h200_part_trial.json",
            "render_h200_part_trial_volume.json",
            "render_h200_part_trial_geodesic.json",
            "render_h200_part_trial_again.json",
        ),
        part_trial,
    ),
    "geodesic-fast-fill": Table(
        ("render_h200_densities_fast_fill.json", "render_h200_densities_precise_fill.json"),
        geodesic_fast_fill,
    ),
    "geodesic-line-weights": Table(
        (
            "render_h200_densities.json",
            "render_h200_densities_running_least.json",
            "render_h200_densities_line_weights_again.json",
            "render_h200_densities_running_least_again.json",
        ),
        geodesic_line_weights,
    ),
    "render-kernels": Table(("render_h200_profile_today.json",), render_kernels),
    "geodesic-route-math": Table(
        (
            "render_h200_geodesic_route_math_qform.json",
            "render_h200_geodesic_route_math_qform_before.json",
            "render_h200_geodesic_route_math_qform_again.json",
            "render_h200_geodesic_route_math_qform_before_again.json",
            "render_h200_geodesic_route_math.json",
            "render_h200_geodesic_route_math_before.json",
            "render_h200_geodesic_route_math_across.json",
            "render_h200_geodesic_route_math_again.json",
            "render_h200_geodesic_route_math_before_again.json",
            "render_h200_geodesic_route_math_classical.json",
            "render_h200_geodesic_route_math_classical_1m.json",
        ),
        geodesic_route_math,
    ),
    "geodesic-fill-registers": Table(
        ("render_h200_geodesic_fill_registers.json",), render_variants
    ),
    "geodesic-fill": Table(
        (
            "render_h200_densities_bricks_and_queues.json",
            "render_h200_densities_before_bricks.json",
            "render_h200_densities_bricks_only.json",
        ),
        geodesic_fill,
    ),
    "geodesic-fill-groups": Table(("render_h200_geodesic_fill_lanes.json",), render_variants),
    "geodesic-mean-queue": Table(("render_h200_geodesic_mean_queue_lanes.json",), render_variants),
    "geodesic-grid-or-routes": Table(
        (
            "render_h200_geodesic_grid_or_routes.json",
            "render_cpu_2core_geodesic_grid_or_routes.json",
        ),
        render_variants,
    ),
    "geodesic-fill-threads": Table(
        ("render_cpu_2core_geodesic_fill_threads.json",), render_variants
    ),
    "ray-threads": Table(("render_cpu_2core_ray_threads.json",), render_variants),
    "ray-threads-volume": Table(("render_cpu_2core_ray_threads_volume.json",), render_variants),
    "visible-bricks": Table(("visible_bricks_cpu.json",), visible_bricks),
    "geodesic-gate": Table(("render_h200_geodesic_gate.json",), geodesic_gate),
    "geodesic-route-major": Table(("render_h200_geodesic_route_major.json",), geodesic_route_major),
    "geodesic-route-once": Table(("render_h200_geodesic_route_once.json",), geodesic_route_once),
    "reach": Table(("reach_accuracy.json",), reach),
    "latency-steer": Table(("latency_h200_live_1m.json", "latency_h200_960.json"), latency_steer),
    "latency-stages": Table(("latency_h200_960.json",), latency_stages),
    "latency-delivery": Table(
        ("latency_h200_live_1m.json", "latency_h200_round6_views.json"), latency_delivery
    ),
    "pipeline": Table(("pipeline_h200.json",), pipeline),
    "oneoff": Table(
        ("latency_h200_oneoff_bands.json", "latency_cpu_2core_oneoff_bands.json"), oneoff
    ),
    "multi-device": Table(
        (
            "multi_device_cpu_2core.json",
            "multi_device_h200x2_round2.json",
            "multi_device_h200x4.json",
        ),
        multi_device,
    ),
    "sort-last": Table(
        (
            "sort_last_h200x2.json",
            "sort_last_h200x2_scatter.json",
            "sort_last_h200_scatter.json",
            "sort_last_h200_two_parts_gather.json",
            "sort_last_h200_10m.json",
            "sort_last_h200_100m.json",
            "sort_last_h200_100m_scatter.json",
            "sort_last_h200_four_parts.json",
        ),
        sort_last,
    ),
    "multi-session": Table(
        (
            "multi_session_h200x2.json",
            "multi_session_h200x2_10k.json",
            "multi_session_h200x2_round2.json",
        ),
        multi_session,
    ),
    "layers": Table(("layers_h100_round2.json",), layers),
    "video-quality": Table(("video_h200_round4.json",), video_quality),
    "video-live": Table(("video_h200_round4.json",), video_live),
    "temporal": Table(("temporal_h100.json",), temporal),
    "batch": Table(("batch_h100.json", "batch_cpu_2core.json"), batch),
    "cpu-interactive": Table(("cpu_interactive_2core.json",), cpu_interactive),
    "ws-parse": Table(("ws_parse_h200_host.json", "ws_parse_cpu_2core.json"), ws_parse),
    "flood": Table(("flood_cpu_2core.json",), flood),
    "trajectory": Table(("trajectory_cpu_2core.json",), trajectory),
    "periodic": Table(("periodic_h200.json", "periodic_cpu_2core.json"), periodic),
    "periodic-live": Table(("periodic_h200.json",), periodic_live),
    "cpu-demo-chromium": Table(
        (
            "cpu_demo_chromium_2core.json",
            "cpu_demo_chromium_2core_as_loaded.json",
            "cpu_demo_chromium_2core_quiet.json",
        ),
        cpu_demo_chromium,
    ),
    "widget": Table(("widget_cpu_2core.json",), widget),
    "adapter": Table(("adapter_cpu_2core.json",), adapter),
}
"""Each README table and the results files it reads: the newest full run of its benchmark on
each GPU it shows (older runs are in results/archive/)."""


def load(results: Path, name: str) -> Results:
    """A results file, refused with its name if it is missing or not JSON."""
    path = results / name
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise TableError(f"{name}: not in {results}") from e
    except json.JSONDecodeError as e:
        raise TableError(f"{name}: not JSON ({e})") from e
    if not isinstance(data, dict):
        raise TableError(f"{name}: a JSON object was expected, got {type(data).__name__}")
    return data


def make(name: str, spec: Table, sources: list[Source]) -> str:
    """One table, a missing field refused with the table, the files and the field named."""
    try:
        return spec.make(sources)
    except (KeyError, IndexError, TypeError, ValueError) as e:
        files = ", ".join(n for n, _ in sources)
        raise TableError(f"table {name!r} from {files}: missing or malformed {e!r}") from e


def generate(results: Path = RESULTS, tables: dict[str, Table] | None = None) -> dict[str, str]:
    """Every table's markdown, from the files in `results`."""
    out = {}
    for name, spec in (TABLES if tables is None else tables).items():
        out[name] = make(name, spec, [(f, load(results, f)) for f in spec.files])
    return out


MARKER = re.compile(r"<!-- bench-tables: ([a-z0-9-]+) -->\n(.*?)<!-- /bench-tables -->", re.S)


def fill(readme: str, made: dict[str, str]) -> str:
    """The README with each marked block replaced by its table; a marker without a table, or a
    table without a marker, is refused."""
    names = MARKER.findall(readme)
    seen = [n for n, _ in names]
    unknown = sorted(set(seen) - set(made))
    missing = sorted(set(made) - set(seen))
    twice = sorted({n for n in seen if seen.count(n) > 1})
    if unknown or missing or twice:
        raise TableError(
            "README markers do not match the tables: "
            + "; ".join(
                f"{what}: {', '.join(ns)}"
                for what, ns in (("unknown", unknown), ("missing", missing), ("twice", twice))
                if ns
            )
        )
    return MARKER.sub(
        lambda m: (
            f"<!-- bench-tables: {m.group(1)} -->\n{_body(made[m.group(1)])}<!-- /bench-tables -->"
        ),
        readme,
    )


def _body(table: str) -> str:
    """A table as it stands between its markers."""
    return table


def differing(readme: str, made: dict[str, str]) -> list[str]:
    """The tables whose block in the README is not what the generator makes."""
    return [n for n, body in MARKER.findall(readme) if n not in made or _body(made[n]) != body]
