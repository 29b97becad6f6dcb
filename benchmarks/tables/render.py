"""Tables of the renderer's own benchmarks: render_bench.py (today's frame against its
controls, the densities, the sizes, the baselines, graph replay, passes per ray),
reach_accuracy.py, multi_device_bench.py, temporal_bench.py, layers_bench.py and
periodic_bench.py."""

from __future__ import annotations

import re

from .markdown import Results, Source, block, count, num, size, stem, table


def params(res: Results) -> str:
    """The render parameters a run was set to (the frames' and its controls')."""
    p = res["params"]
    return (
        f"sigma {p['sigma_A']:g} A, iso {p['iso_level']:g} ({p.get('level_scale', 'absolute')} "
        f"level), cutoff {p['cutoff_sigmas']:g} sigma, step {p['step_sigmas']:g} sigma"
    )


def _variant_case(v: Results, file_params: Results) -> str:
    mode = v.get("params", {}).get("mode", file_params.get("mode", "iso"))
    case = f"{count(v['n_atoms'])} atoms {size(v['width'], v['height'])}"
    return case if mode == "iso" else f"{case} {mode}"


def render_variants(sources: list[Source]) -> str:
    """Variants of one frame in one run: the first label of a file is today's code, the control
    every other variant is divided by (ratio in brackets)."""
    labels: list[str] = []
    cases: dict[str, dict[str, Results]] = {}
    for _, res in sources:
        for v in res["variants"]:
            if v["label"] not in labels:
                labels.append(v["label"])
            cases.setdefault(_variant_case(v, res["params"]), {})[v["label"]] = v
    first = labels[0]
    rows = []
    for case, by in cases.items():
        ref = by[first]
        st = ref["stages_ms"]
        row = [case, num(ref["median_ms"], 3), num(ref["fps"], 0)]
        row.append(f"{num(st['grid'])} / {num(st['raycast'])}")
        for label in labels[1:]:
            v = by.get(label)
            row.append(
                ""
                if v is None
                else f"{num(v['median_ms'], 3)} ({v['median_ms'] / ref['median_ms']:.2f})"
            )
        rows.append(row)
    header = ["case", f"{first} ms", "fps", "grid / cast ms", *labels[1:]]
    return block(
        sources, table(header, "lrrr" + "r" * (len(labels) - 1), rows), params(sources[0][1])
    )


def render_densities(sources: list[Source]) -> str:
    """The classical, geodesic and carved densities on the same frames; the classical one is the
    control of the ratios to it, and the geodesic density with its routes walked at every
    sample (`geodesic_routes`) the control of its grid (`geodesic_grid`: wherever the grid
    fits; `geodesic`: as the renderer chooses)."""
    ((_, res),) = sources
    rows = []
    for r in res["densities"]:
        drawn = r.get("geodesic_drawn_as", "geodesic")
        rows.append(
            [
                count(r["n_atoms"]),
                size(r["width"], r["height"]),
                num(r["classical"]["median_ms"], 3),
                num(r["geodesic"]["median_ms"], 2),
                "grid" if drawn == "geodesic_volume" else "routes",
                num(r["geodesic_over_classical_fps"], 3),
                num(r["geodesic_grid"]["median_ms"], 2) if "geodesic_grid" in r else "-",
                num(r["geodesic_routes"]["median_ms"], 2) if "geodesic_routes" in r else "-",
                num(r["geodesic_grid_over_routes_fps"], 2) if "geodesic_grid" in r else "-",
                num(r["carved"]["median_ms"], 3),
                num(r["carved_over_classical_fps"], 2),
                " / ".join(
                    num(r[f"{d}_bytes_per_atom"], 0) for d in ("classical", "geodesic", "carved")
                ),
            ]
        )
    header = [
        "atoms",
        "image",
        "classical ms",
        "geodesic ms",
        "drawn from",
        "geodesic fps / classical",
        "grid ms",
        "routes ms",
        "grid fps / routes",
        "carved ms",
        "carved fps / classical",
        "B/atom classical / geodesic / carved",
    ]
    return block(sources, table(header, "rlrrlrrrrrrr", rows), params(res))


def _graphs(res: Results) -> list[str]:
    """Graph replay against launching the frame's kernels one by one (its control)."""
    by = {(g["n_atoms"], g["width"], g["height"], g["graphs"]): g for g in res["graphs"]}
    rows = []
    for (n, w, h, replay), g in by.items():
        other = by.get((n, w, h, False))
        if replay and other:
            rows.append(
                [
                    f"{n:,}",
                    size(w, h),
                    num(g["median_ms"], 3),
                    num(other["median_ms"], 3),
                    f"{other['median_ms'] / g['median_ms']:.2f}x",
                ]
            )
    header = ["atoms", "image", "graph replay ms", "one by one ms", "ratio"]
    return table(header, "rlrrr", rows)


def render_passes(sources: list[Source]) -> str:
    """Density passes per ray (four samples each), iso against volume, and the share of a warp's
    pass slots that do work (a count, the same on any device)."""
    ((_, res),) = sources
    rows = []
    for r in res["passes"]:
        iso, vol = r["iso"], r["volume"]
        rows.append(
            [
                count(r["n_atoms"]),
                size(r["width"], r["height"]),
                num(iso["per_ray"]),
                num(iso["per_ray_reaching"]),
                num(iso["tile_use"]),
                num(vol["per_ray"]),
                num(vol["per_ray_reaching"]),
                num(vol["tile_use"]),
                num(r["volume_over_iso"]),
            ]
        )
    header = ["atoms", "image", "iso per ray", "iso per ray reaching", "iso tile use"]
    header += ["volume per ray", "volume per ray reaching", "volume tile use", "volume / iso"]
    return block(sources, table(header, "rl" + "r" * 7, rows), params(res))


def reach(sources: list[Source]) -> str:
    """The least reach that keeps the surface within the bound of the untruncated density (the
    control), per sigma and protein, and the shift at 3 and 4 sigmas; a column per sigma."""
    ((_, res),) = sources
    proteins = list(res["rows"][0]["least_k"])
    rows = [["bound A", *(f"{r['bound_A']:g}" for r in res["rows"])]]
    for p in proteins:
        rows.append(
            [
                f"least k, {p}",
                *(
                    "none tried" if r["least_k"][p] is None else f"{r['least_k'][p]:g}"
                    for r in res["rows"]
                ),
            ]
        )
    for k in ("3", "4"):
        rows.append(
            [
                f"shift A at {k} sigmas, {' / '.join(proteins)}",
                *(" / ".join(f"{r['shift_A'][p][k]:.3f}" for p in proteins) for r in res["rows"]),
            ]
        )
    header = ["sigma A", *(f"{r['sigma']:g}" for r in res["rows"])]
    return block(sources, table(header, "l" + "r" * len(res["rows"]), rows))


def _by_devices(run: Results) -> dict[int, float]:
    if "by_devices" in run:
        return {int(k): v["frame_ms"] for k, v in run["by_devices"].items()}
    return {1: run["one_device_ms"], len(run["per_device_ms"]): run["devices_ms"]}


def multi_device(sources: list[Source]) -> str:
    """One image across several devices against the same frames on one (the control), and
    where a run has it, the same devices each uploading whole frames (`whole_upload`)."""
    counts = sorted({n for _, res in sources for run in res["runs"] for n in _by_devices(run)})
    several = [n for n in counts if n > 1]
    rows = []
    for name, res in sources:
        for run in res["runs"]:
            by = _by_devices(run)
            one = by[1]
            row = [stem(name, "multi_device_"), count(run["atoms"]), size(*run["size"])]
            for n in counts:
                ms = by.get(n)
                row.append(
                    ""
                    if ms is None
                    else num(ms, 1)
                    if n == 1
                    else f"{num(ms, 1)} ({one / ms:.2f}x)"
                )
            whole = run.get("whole_upload", {})
            row.append(
                " / ".join(num(whole[str(n)]["frame_ms"], 1) for n in several if str(n) in whole)
            )
            rows.append(row)
    header = ["run", "atoms", "image", *(f"{n} device{'s' * (n > 1)} ms" for n in counts)]
    header.append("control: each device uploads all, ms")
    return block(sources, table(header, "lrl" + "r" * len(counts) + "l", rows))


def temporal(sources: list[Source]) -> str:
    """The temporal filter and its frame, against the frame with smoothing off (the control);
    a column per ring of W frames."""
    ((_, res),) = sources
    windows = [(w["window"], w["ring_bytes_per_atom"]) for w in res["sizes"][0]["windows"]]
    rows = []
    for s in res["sizes"]:
        if [(w["window"], w["ring_bytes_per_atom"]) for w in s["windows"]] != windows:
            raise ValueError(f"windows of {s['atoms']} atoms differ from the first size's")
        row = [count(s["atoms"]), num(s["baseline_frame_ms"], 2)]
        row += [
            f"{num(w['smooth_ms_classical'], 3)} / {num(w['smooth_ms_warped'], 3)}, "
            f"{num(w['frame_ms'], 2)} ({w['frame_ratio']:.2f})"
            for w in s["windows"]
        ]
        rows.append(row)
    header = ["atoms", "frame without smoothing ms"]
    header += [f"W {w} ({b} B/atom)" for w, b in windows]
    note = "each W: filter ms classical / warped, frame ms (over the frame without smoothing)"
    return block(sources, table(header, "r" * len(header), rows), note)


LAYER_ROWS = (
    ("protein_only", "protein only, plain renderer (the control)", None, ""),
    (
        "protein_layer",
        "solvated, one layer `protein`",
        "protein_layer_over_protein_only",
        "x protein only",
    ),
    ("protein_ligand", "+ ligand as a finer layer", "two_layers_over_one", "x one layer"),
    (
        "protein_licorice",
        "protein at half opacity + ligand as sticks",
        "licorice_pair_over_one",
        "x one layer",
    ),
)
"""Each case of the file, what it is, the ratio the file records for it and what that divides by."""


def layers(sources: list[Source]) -> str:
    """The layered frame of a solvated system against the protein alone in a plain renderer."""
    ((_, res),) = sources
    rows = []
    for key, label, ratio, against in LAYER_ROWS:
        r = res["results"][key]
        target = res["targets"].get(ratio) if ratio else None
        rows.append(
            [
                label,
                num(r["median_ms"]),
                num(r["fps"], 0),
                "" if ratio is None else f"{res['ratios'][ratio]:.2f}{against}",
                "" if target is None else f"<= {target:g}",
            ]
        )
    header = ["case", "median ms", "fps", "ratio", "target"]
    note = (
        f"{res['atoms']:,} atoms ({res['protein_atoms']:,} protein, {res['ligand_atoms']} "
        f"ligand), {size(*res['size'])}"
    )
    return block(sources, table(header, "lrrll", rows), note)


def periodic(sources: list[Source]) -> str:
    """The periodic steps of a frame per system size, a column per mode, beside copying the
    frame to the device (the control in the same run), with the time the topology's molecules
    took to build and the bytes per atom the device keeps; MDAnalysis' own transformations of
    adenylate kinase beside the kernels, where the run timed them, in the caption."""
    modes: list[str] = []
    for _, res in sources:
        for sz in res["sizes"]:
            modes += [m["mode"] for m in sz["modes"] if m["mode"] not in modes]
    rows = []
    notes = ["each mode: kernels ms / with copy and read-back ms (kernels / copy)"]
    for name, res in sources:
        for sz in res["sizes"]:
            by = {m["mode"]: m for m in sz["modes"]}
            row = [stem(name, "periodic_"), count(sz["atoms"]), num(sz["upload_ms"], 3)]
            row += [
                ""
                if mode not in by
                else f"{num(by[mode]['device_ms'], 2)} / {num(by[mode]['round_trip_ms'], 2)} "
                f"({num(by[mode]['device_per_upload'], 1)})"
                for mode in modes
            ]
            row += [num(sz["topology_ms"] / 1e3, 2), num(sz["device_bytes_per_atom"], 0)]
            rows.append(row)
        md = res.get("mdanalysis")
        if md:
            notes.append(
                f"{stem(name, 'periodic_')}: MDAnalysis unwrap + center_in_box + wrap of adk "
                f"({md['atoms']:,} atoms, the second control) {num(md['mdanalysis_ms'], 1)} ms "
                f"against {num(md['round_trip_ms'], 2)} ({num(md['mdanalysis_per_device'], 0)}x)"
            )
    header = ["run", "atoms", "frame copy ms (control)", *modes, "molecules built s"]
    header.append("device B/atom")
    return block(sources, table(header, "lrr" + "r" * (len(modes) + 2), rows), "; ".join(notes))


def periodic_live(sources: list[Source]) -> str:
    """Live frames through the GPU queue (molecules whole and centred, then drawn): plain
    frames (the control), displayed on the device and drawn from there, and displayed then
    drawn from a host copy (the second control, as before); what the steps add to a frame."""
    rows = []
    for name, res in sources:
        for live in res["live"]:
            rows.append(
                [
                    stem(name, "periodic_"), count(live["atoms"]), live["image"],
                    num(live["plain_ms"], 2), num(live["on_device_ms"], 2),
                    num(live["host_copy_ms"], 2), num(live["overhead_ms"], 2),
                    num(live["host_copy_overhead_ms"], 2),
                ]
            )  # fmt: skip
    header = [
        "run", "atoms", "image", "plain ms (control)", "on the device ms", "host copy ms",
        "added on the device ms", "added with a host copy ms",
    ]  # fmt: skip
    return block(sources, table(header, "lrl" + "r" * 5, rows))


def sort_last(sources: list[Source]) -> str:
    """Sort-last against one device on the same frames (the control): the frame, where it
    goes, each part's share of the atoms and of one device's bytes, and the image's distance
    from one device's; where a run also gathered the parts' atoms on the host (the control
    of the gather on the devices), both."""
    rows = []
    for _name, res in sources:
        parts = len(res["devices"])
        gpus = len(set(res["devices"]))
        where = f"{parts} on {gpus} devices" if gpus > 1 else f"{parts} on one device"
        for run in res["runs"]:
            one = run["one_device"]
            n = run["atoms"]
            gathers = [k for k in ("sort_last", "sort_last_host_gather") if k in run]
            for key in gathers:
                sl = run[key]
                gather = "host" if key.endswith("host_gather") or len(gathers) == 1 else "devices"
                stages = " / ".join(
                    num(sl[k], 1) for k in ("split_ms", "mean_ms", "queue_ms", "combine_ms")
                )
                held = ", ".join(f"{100.0 * a / n:.0f}" for a in sl["atoms_held"])
                mem = max(sl["bytes"]) / one["bytes"]
                diff = sl.get("image_vs_one_device", run["image_vs_one_device"])
                rows.append(
                    [
                        where,
                        gather,
                        count(n),
                        size(*run["size"]),
                        run["mode"],
                        num(one["frame_ms"], 2),
                        f"{num(sl['frame_ms'], 2)} ({one['frame_ms'] / sl['frame_ms']:.2f}x)",
                        stages,
                        held,
                        f"{mem:.2f}",
                        f"{diff['max_levels']} / {diff['mean_levels']:.3f}",
                    ]
                )
    header = [
        "parts on",
        "gathered on",
        "atoms",
        "image",
        "mode",
        "one device ms",
        "sort-last ms",
        "split / mean / queue / combine ms",
        "atoms held, % each",
        "device bytes, largest part / one device",
        "image vs one device, max / mean levels",
    ]
    return block(sources, table(header, "llrllrrllrl", rows))


def _kernel_name(activity: str) -> str:
    """`forward kernel _make__locals__iso_march_kernel_31bd5b71` -> `iso_march`."""
    name = activity.removeprefix("forward kernel ")
    for local in ("_make__locals__", "_bound_kernels__locals__"):
        name = name.removeprefix(local)
    name = re.sub(r"_[0-9a-f]{6,8}$", "", name)
    return name.removesuffix("_kernel").lstrip("_")


def render_kernels(sources: list[Source]) -> str:
    """Where a frame's device time goes: each profiled case's kernels timed one launch at a
    time (`render_bench.py --sections profile`), the largest five and the rest, each with its
    share of their sum; the frame's wall time from the same run's variants where it has the
    case (the classical density)."""
    (_, res) = sources[0]
    frames = {(v["n_atoms"], v["width"], v["height"]): v for v in res.get("variants", [])}
    rows = []
    for prof in res["profile"]:
        acts = sorted(prof["activities_ms"].items(), key=lambda kv: -kv[1])
        total = prof["sum_ms"]
        top = [f"{_kernel_name(k)} {v:.3f} ({100 * v / total:.0f} %)" for k, v in acts[:5]]
        rest = sum(v for _, v in acts[5:])
        top.append(f"{len(acts) - 5} more {rest:.3f} ({100 * rest / total:.0f} %)")
        frame = frames.get((prof["n_atoms"], prof["width"], prof["height"]))
        wall = num(frame["median_ms"], 3) if frame and prof["scale_space"] == "classical" else ""
        if prof["variant"] != "iso":
            wall = ""
        case = (
            f"{count(prof['n_atoms'])} atoms {size(prof['width'], prof['height'])} "
            f"{prof['scale_space']} {prof['variant']}"
        )
        rows.append([case, wall, num(total, 3), "; ".join(top)])
    header = [
        "case",
        "frame ms (wall)",
        "kernels' sum ms",
        "largest kernels, ms (share of the sum)",
    ]
    return block(sources, table(header, "lrrl", rows), params(res))
