"""Tables of the benchmarks that run the server or its pipeline: latency_bench.py,
pipeline_bench.py, multi_session_bench.py, video_bench.py, batch_bench.py,
cpu_interactive_bench.py, cpu_demo_chromium.py, ws_parse_bench.py, flood_bench.py,
widget_bench.py, adapter_bench.py and trajectory_bench.py."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .markdown import Source, block, count, num, size, stem, table

STAGES = ("total", "queue", "render", "encode", "send", "decode")


def latency_steer(sources: list[Source]) -> str:
    """Steer-to-photon by stage, p50 / p95 / p99 ms, one row per file."""
    rows = []
    for name, res in sources:
        runs = [(stem(name, "latency_"), res["latency"])]
        runs += [  # `--jpeg-control`: each way of making the JPEG, taking turns
            (f"{stem(name, 'latency_')}, JPEG {lat['encoder']}", lat)
            for lat in res.get("latency_by_encoder", [])
        ]
        for label, lat in runs:
            w, h = lat["image"]
            row = [label, f"{lat['n_atoms']:,}", f"{size(w, h)} of {size(*res['size'])}"]
            row += [
                " / ".join(num(lat[stage][p], 1) for p in ("p50", "p95", "p99")) for stage in STAGES
            ]
            rows.append(row)
    header = ["run", "atoms", "image", *STAGES]
    return block(sources, table(header, "lrl" + "r" * len(STAGES), rows), "ms, p50 / p95 / p99")


SERVER_STAGES = ("steer", "wake", "plan", "to_thread", "thread", "back", "deliver")


def latency_stages(sources: list[Source]) -> str:
    """A steer's path inside the server (`--stages`), p50 / p95 ms, with each run's total."""
    rows = []
    for name, res in sources:
        stages = res.get("latency_stages")
        if stages is None:
            continue
        runs = res.get("latency_runs", [res["latency"]])
        totals = ", ".join(num(r["total"]["p50"], 2) for r in runs)
        row = [stem(name, "latency_"), totals, num(res["latency"]["render"]["p50"], 2)]
        row += [" / ".join(num(stages[s][q], 2) for q in ("p50", "p95")) for s in SERVER_STAGES]
        rows.append(row)
    header = ["run", "total p50 of each run", "render p50", *SERVER_STAGES]
    return block(sources, table(header, "lrr" + "r" * len(SERVER_STAGES), rows), "ms")


def latency_delivery(sources: list[Source]) -> str:
    """Frames delivered per viewer of a streamed system; rows with the upload overlap on and off
    (`--prefetch-control`) are each other's control."""
    rows = []
    for name, res in sources:
        for t in res["throughput"]:
            rt = t["render_timings_ms"]
            overlap = {True: "on", False: "off (control)"}.get(t.get("prefetch"), "not recorded")
            rows.append(
                [
                    stem(name, "latency_"),
                    count(t["n_atoms"]),
                    str(t["viewers"]),
                    ("own camera each" if t["own_camera"] else "shared")
                    + (f", JPEG {t['jpeg']}" if "jpeg" in t else ""),
                    overlap,
                    num(t["fps_per_viewer_mean"], 1),
                    num(t["sim_frames_per_s"], 1),
                    " / ".join(num(rt[k], 2) for k in ("upload", "grid", "raycast")),
                    num(t["encode_ms"], 1),
                ]
            )
    header = ["run", "atoms", "viewers", "view", "upload overlap", "fps per viewer"]
    header += ["frames taken/s", "render upload / grid / cast ms", "encode ms"]
    return block(sources, table(header, "lrrllrrrr", rows))


def pipeline(sources: list[Source]) -> str:
    """A session's live path with the next frame's upload overlapped, against it serial; and,
    where the run took it, staging as it was before (one copy thread, a 5 ms wait)."""
    ((_, res),) = sources
    rows = []
    before = any("serial_staging_before" in r for r in res["rows"])
    copied = any(r.get("copy_ms") for r in res["rows"])
    for r in res["rows"]:
        st = r["overlapped"]["median_stage_ms"]
        row = [
            count(r["atoms"]),
            size(*r["size"]),
            num(r["serial"]["fps"], 1),
            num(r["overlapped"]["fps"], 1),
            f"{r['overlapped_over_serial']:.3f}",
            " / ".join(num(st[k], 2) for k in ("upload", "grid", "raycast", "total")),
        ]
        copy = r.get("copy_ms")
        if copied:
            row.append(
                ""
                if copy is None
                else f"{num(copy['one_thread_ms'], 1)} / {num(copy['sliced_ms'], 1)} "
                f"({copy['threads']})"
            )
        if before:
            old = r.get("serial_staging_before")
            row.append(
                ""
                if old is None
                else f"{num(old['fps'], 1)} (upload {num(old['median_stage_ms']['upload'], 1)})"
            )
        rows.append(row)
    header = ["atoms", "image", "serial fps (control)", "overlapped fps", "ratio"]
    header += ["upload / grid / cast / frame ms"]
    if copied:
        header.append("frame into page-locked memory ms: one thread / sliced (threads)")
    if before:
        header.append("serial fps, staging as before (upload ms)")
    return block(sources, table(header, "rlrrrr" + "r" * (copied + before), rows))


def multi_session(sources: list[Source]) -> str:
    """Sessions on several devices against one session alone on one device (the control)."""
    rows = []
    for _, res in sources:
        each = res["sessions_one_device_each"]
        rows.append(
            [
                count(res["atoms"]),
                size(*res["size"]),
                num(res["one_session_one_device"]["fps"], 1),
                f"{num(res['one_session_all_devices']['fps'], 1)} ({res['spread_over_one']:.2f}x)",
                ", ".join(
                    f"{num(s['fps'], 1)} ({r:.2f})"
                    for s, r in zip(each, res["each_over_one"], strict=True)
                ),
            ]
        )
    header = ["atoms", "image", "one session, one device fps", "one session on all devices"]
    header += ["a session on each device, fps (over one alone)"]
    return block(sources, table(header, "rlrrr", rows))


ENCODINGS = ("jpeg", "h264", "h264-swscale")
"""The server's encodings (H.264 from the device's planes) and their controls; the files' x264
preset rows are a sweep (HISTORY.md, "Video")."""


def video_quality(sources: list[Source]) -> str:
    """Each encoding of the same 1080p frames: bit rate at 60 fps, encode time, PSNR against the
    raw render; JPEG is the control of the video stream. A row per system."""
    ((_, res),) = sources
    rows = []
    for s, by in res["quality"].items():
        row = [s]
        for e in ENCODINGS:
            q = by.get(e)
            row.append(
                ""
                if q is None
                else f"{num(q['mbit_per_s_at_60fps'], 1)} / {num(q['encode_ms_p50'], 1)} / "
                f"{num(q['psnr_db_mean'], 1)} ({num(q['psnr_db_min'], 1)})"
            )
        rows.append(row)
    note = "each encoding: Mbit/s / encode ms p50 / PSNR dB mean (min)"
    return block(sources, table(["system", *ENCODINGS], "l" + "r" * len(ENCODINGS), rows), note)


VIDEO_STAGES = ("up", "queued", "render", "encoder", "encode", "down", "decode")


def video_live(sources: list[Source]) -> str:
    """The live server, steer-to-photon p50 / p99 and its stages' p50; the JPEG rows are the
    video stream's control on the same link."""
    ((_, res),) = sources
    rows = []
    for r in res["live"]:
        st = r["stages_ms"]
        rows.append(
            [
                r["system"],
                r["link"],
                r["transport"],
                num(r["delivered_mbit_per_s"], 1),
                num(r["delivered_fps"], 0),
                num(r["steer_to_photon_ms_p50"], 0),
                num(r["steer_to_photon_ms_p99"], 0),
                *(num(st[k]["p50"], 1) for k in VIDEO_STAGES),
            ]
        )
    header = ["system", "link", "stream", "Mbit/s", "fps", "p50 ms", "p99 ms", *VIDEO_STAGES]
    note = f"the emulated link: {res['link']}"
    return block(sources, table(header, "lll" + "r" * 11, rows), note)


def _engine(r: dict[str, Any]) -> str:
    if r["engine"] == "ray":
        return f"Ray, {r['workers']} actor{'s' * (r['workers'] > 1)}"
    return str(r["engine"])


def batch(sources: list[Source]) -> str:
    """One movie job in-process (the control) and on Ray actors, in one run per machine; a row
    per machine, a column per engine."""
    engines: list[str] = []
    for _, res in sources:
        engines += [e for e in map(_engine, res["runs"]) if e not in engines]
    rows = []
    for name, res in sources:
        by = {_engine(r): r for r in res["runs"]}
        frames = {r["frames"] for r in res["runs"]}
        if len(frames) != 1:
            raise ValueError(f"frames differ between the engines of {name}: {sorted(frames)}")
        row = [stem(name, "batch_"), f"{frames.pop():,} at {size(*res['size'])}"]
        for e in engines:
            r = by.get(e)
            if r is None:
                row.append("")
                continue
            ratio = r.get("time_vs_in_process")
            cell = f"{num(r['wall_s'], 1)} / {num(r['frames_per_s'], 2)}"
            row.append(cell if ratio is None else f"{cell} ({ratio:.2f})")
        rows.append(row)
    note = "each engine: wall s / frames/s (time over in-process)"
    return block(sources, table(["run", "frames", *engines], "lr" + "r" * len(engines), rows), note)


def cpu_interactive(sources: list[Source]) -> str:
    """The demo on a machine without a GPU: each configuration in one run; `baseline` renders
    every image at the canvas's size (the control of the frame-time budget)."""
    ((_, res),) = sources
    rows = [
        [
            r["config"],
            num(r["fps"], 1),
            num(r["steer"]["median"], 0),
            num(r["pick"]["median"], 0),
            num(r["pull"]["median"], 0),
            num(r["pull_ack"]["median"], 0),
        ]
        for r in res["rows"]
    ]
    ratios = res["ratios_budget_over_baseline"]
    rows.append(
        ["budget / baseline"]
        + [f"{ratios[k]:.2f}" for k in ("fps", "steer", "pick", "pull")]
        + [""]
    )
    header = ["config", "fps while dragging", "steer-to-photon ms", "pick ms", "pull shown ms"]
    header += ["pull acked by the MD ms"]
    note = f"{res['system']}, canvas {size(*res['canvas'])}, medians"
    return block(sources, table(header, "lrrrrr", rows), note)


def ws_parse(sources: list[Source]) -> str:
    """The server's WebSocket parser fed one large frame whole (the control) and in fragments."""
    rows = []
    for name, res in sources:
        whole, frag = res["whole"], res["fragments"]
        rows.append(
            [
                stem(name, "ws_parse_"),
                f"{res['message_bytes']:,}",
                f"{num(whole['total_ms_median'], 1)} / {num(whole['longest_step_ms_median'], 1)}",
                f"{num(frag['total_ms_median'], 1)} / {num(frag['longest_step_ms_median'], 1)}",
                f"{res['ratio_total']:.1f}x",
            ]
        )
    header = ["host", "message bytes", "whole: loop ms / longest step"]
    header += ["fragments: loop ms / longest step", "ratio"]
    return block(sources, table(header, "lrrrr", rows))


def flood(sources: list[Source]) -> str:
    """A viewer's round trip while raw sockets flood the server; the no-flood row the control."""
    rows = []
    for name, res in sources:
        for key, case in res["cases"].items():
            row = [stem(name, "flood_"), key, f"{case['count']:,}"]
            row += [num(case[k], 2) for k in ("p50_ms", "p90_ms", "max_ms")]
            rows.append([*row, f"{case['p50_ratio']:.1f}x"])
    header = ["host", "flood", "round trips", "p50 ms", "p90 ms", "max ms", "p50 / no flood"]
    return block(sources, table(header, "llrrrrr", rows))


def cpu_demo_chromium(sources: list[Source]) -> str:
    """`scalesteer demo` as its dashboard in Chromium shows it on the CPU machine; each run of a
    file (the baseline checkout first, when it ran one) is a row."""
    runs: list[tuple[str, dict[str, Any]]] = []
    for name, res in sources:
        tag = f"--priority {res['priority']}" if res.get("priority") else "as loaded"
        for label, run in res["runs"].items():
            load = run["load_average_before"][0], run["load_average_after"][0]
            head = f"{stem(name, 'cpu_demo_chromium_')} {label} ({run['commit']}, {tag}, load"
            runs.append((f"{head} {num(load[0], 0)}-{num(load[1], 0)})", run))

    def pct(stats: dict[str, float], key: str = "p50") -> str:
        return num(stats[key], 0) if stats else "n/a"

    def lat(run: dict[str, Any], phase: str, kind: str) -> str:
        st = run["phases"][phase]["latency_ms"].get(kind)
        return f"{pct(st)} / {pct(st, 'p90')}" if st else "n/a"

    lines: list[tuple[str, Callable[[dict[str, Any]], str]]] = [
        (
            "images shown/s, simulation running",
            lambda r: num(r["phases"]["running"]["images_per_s"], 1),
        ),
        (
            "simulation frames among them/s",
            lambda r: num(r["phases"]["running"]["simulation_frames_shown_per_s"], 1),
        ),
        ("images shown/s, orbiting", lambda r: num(r["phases"]["orbit"]["images_per_s"], 1)),
        ("sigma steer-to-photon ms, p50 / p90", lambda r: lat(r, "steer", "render_params")),
        ("orbit (camera move to its image) ms, p50 / p90", lambda r: lat(r, "orbit", "view")),
        (
            "pixels of a running image (p50), transport",
            lambda r: f"{r['phases']['running']['pixels_rendered']['p50']:,.0f} {r['transport']}",
        ),
        (
            "render / encode / decode per running image ms (p50)",
            lambda r: " / ".join(
                num(r["phases"]["running"][k]["p50"], 1)
                for k in ("render_ms", "encode_ms", "decode_ms")
            ),
        ),
        (
            "simulation steps/s, running",
            lambda r: num(r["phases"]["running"]["sim_steps_per_s"], 0),
        ),
    ]
    header = ["run"] + [label for label, _ in lines]
    rows = [[head] + [get(run) for _, get in lines] for head, run in runs]
    return block(sources, table(header, "l" + "r" * len(lines), rows))


def widget(sources: list[Source]) -> str:
    """The notebook widget as the page measures it, beside its controls in the same run: the
    pictures the kernel forwarded and the dashboard on the same session."""
    rows = []
    for name, res in sources:
        runs = ", ".join(num(s, 2) for s in res["first_picture_runs_s"])
        load = " / ".join(num(x, 1) for x in res["load_average"])
        rows.append(
            [
                stem(name, "widget_"),
                count(res["atoms"]),
                f"{size(*res['size'])} {res['widget_format']}",
                load,
                f"{num(res['first_picture_s'], 2)} ({runs})",
                num(res["cold_s"], 1),
                num(res["widget_fps"], 2),
                num(res["forwarded_fps"], 2),
                f"{num(res['dashboard_fps'], 2)} ({res['dashboard_image_size']})",
            ]
        )
    header = ["run", "atoms", "view", "load avg start / end", "first picture s, median (runs)"]
    header += ["first picture with the server's start s", "widget drew/s"]
    header += ["kernel forwarded/s (control)", "dashboard drew/s (control)"]
    return block(sources, table(header, "lrlrrrrrr", rows))


def adapter(sources: list[Source]) -> str:
    """The OpenMM adapter's MD step rate beside a server that never reads, against the same
    reporter unconnected (the control, in the same run)."""
    ((_, res),) = sources
    rates = res["steps_per_s"]
    rows = [
        [label, num(rates[key]["best"], 1), num(rates[key]["median"], 1)]
        for label, key in (
            ("no server (control)", "unconnected"),
            ("a server that never reads", "never_reads"),
        )
    ]
    rows.append(
        ["never reads / no server", f"{res['ratio_best']:.2f}", f"{res['ratio_median']:.2f}"]
    )
    low, high = min(res["load_average"]), max(res["load_average"])
    note = (
        f"{res['n_atoms']:,} atoms, a report every {res['interval']} steps, {res['rounds']} "
        f"rounds of {res['steps_per_round']} steps, load average {low:.1f}-{high:.1f}; the "
        f"stuck adapter sent {res['frames_sent']} frames and replaced {res['frames_dropped']} "
        f"of {res['frames_reported']}"
    )
    return block(sources, table(["MD", "best steps/s", "median steps/s"], "lrr", rows), note)


def trajectory(sources: list[Source]) -> str:
    """Generated multi-GB trajectories: opening one and its first frame, a seek to any frame
    against reading in order (the control), through the server's isolated reader too, and the
    memory the reader keeps."""
    rows = []
    for _, res in sources:
        for f in res["files"]:
            rows.append(
                [
                    f["file"],
                    f"{f['bytes'] / (1 << 30):.2f}",
                    f"{f['frames']:,}",
                    num(f["open_cold_s"], 2),
                    num(f["first_frame_s"] * 1e3, 1),
                    num(f["seek_ms"], 2),
                    num(f["sequential_ms"], 2),
                    num(f["seek_per_sequential"], 2),
                    f"{num(f['isolated_open_s'], 1)} / {num(f['isolated_frame_ms'], 1)}",
                    num(f["rss_growth_mb"], 0),
                ]
            )
    header = ["file", "GiB", "frames", "open s (offsets built)", "first frame ms"]
    header += ["seek to any frame ms", "in order ms (control)", "seek / in order"]
    header += ["isolated reader: open s / frame ms", "memory growth MB"]
    return block(sources, table(header, "lrrrrrrrrr", rows))


def oneoff(sources: list[Source]) -> str:
    """One-off renders drawn whole (the control) and in bands, and a live render's wait behind
    each, in the same run."""
    rows = []
    for name, res in sources:
        for c in res["cases"]:
            row = [stem(name, "latency_"), count(c["n_atoms"]), size(*c["size"]), c["scale_space"]]
            row += [num(c[k], 1) for k in ("whole_alone_ms", "bands_alone_ms")]
            row += [f"{c['bands_over_whole_alone']:.2f}x"]
            row += [num(c[k], 1) for k in ("whole_live_wait_ms", "bands_live_wait_ms")]
            rows.append([*row, f"{c['live_wait_whole_over_bands']:.2f}x"])
    header = ["run", "atoms", "image", "density", "whole ms", "bands ms", "bands / whole"]
    header += ["live wait, whole ms", "live wait, bands ms", "wait whole / bands"]
    return block(sources, table(header, "lrllrrrrrr", rows))
