"""The part-bound trial's table: the trial against the rule of sizes and whole cells."""

from __future__ import annotations

from typing import Any

from .markdown import Source, block, count, num, size, table


def part_trial(sources: list[Source]) -> str:
    """Each case's frame with the renderer's trial (`parttrial.py`), the rule of sizes alone
    (the control) and whole cells alone, from runs of the same variants in one session: an
    iso run, the volume run, the geodesic density's run and the iso run again in the opposite
    order."""
    rows = []
    for _, res in sources:
        cases: dict[tuple[int, int, int], dict[str, Any]] = {}
        for v in res["variants"]:
            cases.setdefault((v["n_atoms"], v["width"], v["height"]), {})[v["label"]] = v
        for (n, w, h), by in cases.items():
            trial, rule, whole = by["trial"], by["rule of sizes"], by["whole cells"]
            params = trial["params"]
            mode = " ".join([params.get("mode", "iso"), params.get("scale_space", "")]).strip()
            rows.append(
                [
                    f"{count(n)} atoms {size(w, h)} {mode}",
                    num(rule["median_ms"], 3),
                    num(whole["median_ms"], 3),
                    num(trial["median_ms"], 3),
                    str(trial["parts"]),
                    f"{trial['median_ms'] / rule['median_ms']:.2f}",
                ]
            )
    header = [
        "case",
        "rule of sizes ms",
        "whole cells ms",
        "trial ms",
        "trial chose",
        "trial / rule",
    ]
    return block(sources, table(header, "lrrrlr", rows))
