"""Tables of the geodesic density's own measures: side_walk_work.py (the routes a march walks,
what a sample's routes share) and the geodesic frame against the code before a change."""

from __future__ import annotations

from collections.abc import Callable

from .markdown import Results, Source, block, count, num, size, table
from .render import params


def side_walk(sources: list[Source]) -> str:
    """The share of a whole walk's routes (the control) each order of the side walk takes."""
    ((_, res),) = sources
    rows = []
    for r in res["rows"]:
        share = r["fraction_walked"]
        rows.append(
            [
                f"{r['sigma_A']:g}",
                f"{count(r['gated_samples'])} ({count(r['classically_gated_samples'])})",
                *(f"{100 * share[k]:.0f} %" for k in ("cells", "bands", "nearest")),
                _median_mean(r["gated_samples_per_crossing_ray"]),
                _median_mean(r["steps_from_gate_to_crossing"]),
            ]
        )
    header = [
        "sigma A",
        "samples gated (classically)",
        "cell rows",
        "bands, nearest first",
        "atom by atom, nearest",
        "gated samples a crossing ray takes",
        "steps from its first to the crossing",
    ]
    return block(sources, table(header, "rrrrrrr", rows))


def route_sharing(sources: list[Source]) -> str:
    """Per gated sample: the classical density's Gaussians (the control) against the route
    loop's table entries and what they share (distinct bonds, their ends, atom-node pairs)."""
    ((_, res),) = sources
    rows = []
    for r in res["rows"]:
        share = r["sharing"]
        atoms = share["atoms"]["mean"]
        rows.append(
            [
                f"{r['sigma_A']:g}",
                f"{atoms:.0f}",
                *(
                    f"{share[k]['mean']:,.0f} ({share[k]['mean'] / atoms:.1f})"
                    for k in ("table_entries", "bonds", "nodes", "atom_nodes")
                ),
                f"{share['table_entries']['mean'] / share['bonds']['mean']:.1f}",
            ]
        )
    header = [
        "sigma A",
        "Gaussians (atoms within reach)",
        "(atom, bond) entries walked",
        "distinct bonds",
        "distinct bond ends",
        "(atom, bond end) pairs",
        "entries per distinct bond",
    ]
    return block(sources, table(header, "rrrrrrr", rows))


def _median_mean(spread: dict[str, float]) -> str:
    return f"{spread['median']:g} (mean {spread['mean']:.1f}, p90 {spread['p90']:g})"


def _against_base(column: str, key: str) -> Callable[[list[Source]], str]:
    """A table of a geodesic frame against the same code before a change (the control, its
    own checkout in the same session), each the mean of two runs: `key`_ms and
    `key`_over_base in each row."""

    def make(sources: list[Source]) -> str:
        ((_, res),) = sources
        rows = [
            [
                count(r["n_atoms"]),
                size(r["width"], r["height"]),
                num(r["base_ms"], 2),
                num(r[f"{key}_ms"], 2),
                f"{r[f'{key}_over_base']:.2f}",
            ]
            for r in res["rows"]
        ]
        header = ["atoms", "image", "before ms", column, "ratio"]
        return block(sources, table(header, "lrrrr", rows), params(res))

    return make


geodesic_gate = _against_base("with the gate ms", "gate")
geodesic_route_major = _against_base("routes with their geometry ms", "new")
geodesic_route_once = _against_base("each route read once a pass ms", "new")


def _drawn(row: Results) -> str:
    return "grid" if row["geodesic_drawn_as"] == "geodesic_volume" else "routes"


def _by_case(res: Results) -> dict[tuple[int, int, int], Results]:
    return {(r["n_atoms"], r["width"], r["height"]): r for r in res["densities"]}


def geodesic_fast_fill(sources: list[Source]) -> str:
    """The geodesic frame today and with its grid's kernels compiled with precise square
    roots, divisions and exponentials (the code before, its own checkout in the same device
    session, the same frames: the control), each with its own run's classical frame."""
    (_, today), (_, before) = sources
    was = _by_case(before)
    rows = []
    for r in today["densities"]:
        b = was[(r["n_atoms"], r["width"], r["height"])]
        ms, base = r["geodesic"]["median_ms"], b["geodesic"]["median_ms"]
        rows.append(
            [
                count(r["n_atoms"]),
                size(r["width"], r["height"]),
                f"{num(base, 2)} ({_drawn(b)})",
                f"{num(ms, 2)} ({_drawn(r)})",
                f"{base / ms:.2f}",
                f"{b['classical']['median_ms'] / base:.2f}",
                f"{r['classical']['median_ms'] / ms:.2f}",
            ]
        )
    header = [
        "atoms",
        "image",
        "precise ms (drawn from)",
        "today ms (drawn from)",
        "frame rate / precise",
        "geodesic / classical frame rate, precise",
        "today",
    ]
    return block(sources, table(header, "rlrrrrr", rows), params(today))


def geodesic_line_weights(sources: list[Source]) -> str:
    """The geodesic frame with the routes weighed against the straight line and each bond's
    length made once a frame, against the code before (the running least, lengths at every
    point: its own checkout, the same device session, the same frames), in two sessions (the
    first pair of files, then the second); ratios are frame rates, each against its own
    session's control, and against its own run's classical frame."""
    (_, today), (_, before), (_, again), (_, before_again) = sources
    was, now2, was2 = _by_case(before), _by_case(again), _by_case(before_again)
    rows = []
    for r in today["densities"]:
        key = (r["n_atoms"], r["width"], r["height"])
        b = was[key]
        ms, base = r["geodesic"]["median_ms"], b["geodesic"]["median_ms"]
        second = "-"
        if key in now2 and key in was2:
            pair = was2[key]["geodesic"]["median_ms"], now2[key]["geodesic"]["median_ms"]
            second = f"{pair[0] / pair[1]:.2f}"
        routes = r["geodesic_routes"]["median_ms"], b["geodesic_routes"]["median_ms"]
        rows.append(
            [
                count(r["n_atoms"]),
                size(r["width"], r["height"]),
                f"{num(base, 2)} ({_drawn(b)})",
                f"{num(ms, 2)} ({_drawn(r)})",
                f"{base / ms:.2f}",
                second,
                f"{routes[1] / routes[0]:.2f}",
                f"{r['classical']['median_ms'] / ms:.2f}",
            ]
        )
    header = [
        "atoms",
        "image",
        "before ms (drawn from)",
        "today ms (drawn from)",
        "frame rate / before",
        "again",
        "routes per sample: frame rate / before",
        "geodesic / classical frame rate",
    ]
    return block(sources, table(header, "rlrrrrrr", rows), params(today))


def geodesic_fill(sources: list[Source]) -> str:
    """The geodesic density as the renderer drew it after the twelfth round and in the code
    before two changes (each its own checkout, the same device session, the same frames): the
    first file that round's run, the second the code before the fill took bricks, the third the
    bricks without the mean's queues. Ratios are frame rates against the code before (the
    control) and against that round's classical frame of the same run."""
    (_, today), (_, before), (_, bricks) = sources
    was, mid = _by_case(before), _by_case(bricks)
    rows = []
    for r in today["densities"]:
        key = (r["n_atoms"], r["width"], r["height"])
        b, m = was[key], mid[key]
        ms = r["geodesic"]["median_ms"]
        rows.append(
            [
                count(r["n_atoms"]),
                size(r["width"], r["height"]),
                f"{num(b['geodesic']['median_ms'], 2)} ({_drawn(b)})",
                num(m["geodesic"]["median_ms"], 2),
                f"{num(ms, 2)} ({_drawn(r)})",
                f"{b['geodesic']['median_ms'] / ms:.2f}",
                f"{r['classical']['median_ms'] / ms:.2f}",
            ]
        )
    header = [
        "atoms",
        "image",
        "before ms (drawn from)",
        "bricks ms",
        "bricks and queues ms (drawn from)",
        "frame rate / before",
        "geodesic / classical frame rate",
    ]
    return block(sources, table(header, "rlrrrrr", rows), params(today))


def visible_bricks(sources: list[Source]) -> str:
    """The grid's walked bricks (the control: every one the fill walks) and those within the
    spline's and the prefilter's reach of an iso image's hits."""
    ((_, res),) = sources
    rows = [
        [
            count(r["n_atoms"]),
            size(r["width"], r["height"]),
            count(r["bricks_walked"]),
            count(r["bricks_reached"]),
            f"{100.0 * r['reached_share']:.0f} %",
        ]
        for r in res["rows"]
    ]
    header = ["atoms", "image", "bricks walked", "within reach of a hit", "share"]
    reach = res["rows"][0]["reach_A"]
    note = f"sigma {res['rows'][0]['sigma_A']:g} A, reach {reach:.2f} A"
    return block(sources, table(header, "rlrrr", rows), note)


def geodesic_route_math(sources: list[Source]) -> str:
    """The geodesic frame with each route's distance across as |e - u v|^2 and its smooth
    clamp's two halves' t taken out (the code shipped, "today"), against the code before (its
    own checkout, the same device session, the same frames, both again at the session's end).
    An earlier session of the same day timed the expansion |e|^2 + u (u l^2 - 2 e.v) (the
    next five files: itself, its control, the distance across alone, both again), given as its
    frame rate against its own control. Ratios are frame rates and grid-stage rates against
    the control; the classical frames come from the files after those (one H200; the first
    that holds the case)."""
    (_, today), (_, before), (_, again), (_, before_again) = sources[:4]
    (_, exp), (_, exp_before), (_, across) = sources[4:7]
    was, now2, was2 = (_by_variant(r) for r in (before, again, before_again))
    e_now, e_was, mid = (_by_variant(r) for r in (exp, exp_before, across))
    flat: dict[tuple[int, int, int], Results] = {}
    for _, res in sources[9:]:
        for key, v in _by_variant(res).items():
            flat.setdefault(key, v)
    rows = []
    for v in today["variants"]:
        key = (v["n_atoms"], v["width"], v["height"])
        b, ms = was[key], v["median_ms"]
        rows.append(
            [
                count(v["n_atoms"]),
                size(v["width"], v["height"]),
                num(b["median_ms"], 2),
                num(ms, 2),
                f"{b['median_ms'] / ms:.2f}",
                f"{was2[key]['median_ms'] / now2[key]['median_ms']:.2f}",
                f"{b['stages_ms']['grid'] / v['stages_ms']['grid']:.2f}",
                f"{e_was[key]['median_ms'] / e_now[key]['median_ms']:.2f}",
                f"{e_was[key]['median_ms'] / mid[key]['median_ms']:.2f}",
                f"{flat[key]['median_ms'] / ms:.2f}",
            ]
        )
    header = [
        "atoms",
        "image",
        "before ms",
        "today ms",
        "frame rate / before",
        "again",
        "grid stage / before",
        "the expansion / before (earlier run)",
        "distance across alone / before (earlier run)",
        "geodesic / classical frame rate",
    ]
    return block(sources, table(header, "rlrrrrrrrr", rows), params(today))


def _by_variant(res: Results) -> dict[tuple[int, int, int], Results]:
    return {(v["n_atoms"], v["width"], v["height"]): v for v in res["variants"]}
