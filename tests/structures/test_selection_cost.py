"""The price of a selection, decided before it runs: its text (length, nesting), its parse
tree's depth, and its atom pairs, estimated from the frame against a brute-force count."""

from __future__ import annotations

import math

import numpy as np
import pytest

import protocol as p
from structures.selection import SelectionError, SelectionSkippedError, Selector, parse
from structures.selection_cost import (
    Density,
    SelectionLimits,
    depth_refusal,
    estimate,
    text_refusal,
)

pytest.importorskip("MDAnalysis")

LIMITS = SelectionLimits()


def backbone(n: int, spacing: float = 2.154, seed: int = 0) -> tuple[p.Topology, np.ndarray]:
    """`n` atoms of alanine backbone (N, CA, C, O) near the points of a grid `spacing` apart
    (2.154 A: 0.1 atoms per cubic angstrom, as dense as water)."""
    side = math.ceil(n ** (1 / 3))
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    pos = grid * spacing + np.random.default_rng(seed).normal(0, 0.3, (n, 3))
    topo = p.Topology(
        n_atoms=n,
        elements=[("N", "C", "C", "O")[i % 4] for i in range(n)],
        names=[("N", "CA", "C", "O")[i % 4] for i in range(n)],
        residue_ids=p.WireArray.from_numpy(np.arange(n) // 4 + 1, "<i4"),
        residue_names=["ALA"] * n,
        chain_ids=["A"] * n,
        bonds=p.WireArray.from_numpy(np.zeros((0, 2)), "<i4"),
    )
    return topo, pos.astype(np.float32)


def pairs_within(pos: np.ndarray, atoms: np.ndarray, cutoff: float) -> int:
    """Brute force: pairs (i in atoms, j any) closer than `cutoff`."""
    total = 0
    for chunk in np.array_split(atoms, max(1, len(atoms) // 256)):
        d = np.linalg.norm(pos[chunk][:, None, :] - pos[None, :, :], axis=-1)
        total += int((d < cutoff).sum())
    return total


def price(selector: Selector, text: str, pos: np.ndarray) -> int:
    found, _refusal = estimate(
        text,
        parse(text),
        selector.universe,
        Density(pos),
        SelectionLimits(max_pairs=10**15),
    )
    return found.pairs


def test_the_text_is_measured_before_it_is_parsed() -> None:
    limits = SelectionLimits(max_chars=40, max_depth=3)
    long = text_refusal("name " + "CA " * 20, limits)
    assert long is not None and long.limit == "selection_max_chars" and long.value == 40
    assert "65 characters" in long.reason and long.position == 40
    deep = text_refusal("not (not (not (not (name CA))))", limits)
    assert deep is not None and deep.limit == "selection_max_depth"
    assert deep.position == len("not (not (not (not ")  # the fourth parenthesis
    assert text_refusal("not (not (name CA))", limits) is None


def test_the_tree_depth_counts_prefixes_and_chains() -> None:
    limits = SelectionLimits(max_depth=4)
    assert depth_refusal("x", parse("not not not name CA"), limits) is None
    chain = "name A or name B or name C or name D or name E"
    refusal = depth_refusal(chain, parse(chain), limits)
    assert refusal is not None and refusal.limit == "selection_max_depth"
    prefixes = "not not not not not name CA"
    refusal = depth_refusal(prefixes, parse(prefixes), limits)
    assert refusal is not None and refusal.position == prefixes.index("not name")  # 5th


@pytest.mark.parametrize("cutoff", [3.0, 5.0, 8.0, 12.0])
def test_the_pair_estimate_follows_a_brute_force_count(cutoff: float) -> None:
    """Within a factor of two of the pairs MDAnalysis will check, on uniform matter and with
    the inner selection counted exactly."""
    topo, pos = backbone(8000)
    selector = Selector(topo)
    text = f"around {cutoff:g} index 100:399"
    exact = pairs_within(pos, np.arange(100, 400), cutoff)
    estimated = price(selector, text, pos) - selector.universe.atoms.n_atoms  # less one grid
    assert exact / 2 <= estimated <= 2 * exact, (estimated, exact)


def test_a_clump_is_priced_as_a_clump() -> None:
    """Atoms piled on one spot: every pair is near, and the estimate knows it."""
    topo, pos = backbone(4000)
    pos[:2000] = np.float32(5.0)
    selector = Selector(topo)
    estimated = price(selector, "around 1 index 0:99", pos)
    assert estimated >= 100 * 2000


def test_what_a_person_types_passes_and_the_attacks_do_not() -> None:
    topo, pos = backbone(40_000)
    selector = Selector(topo)
    for text in ("name CA", "around 5 index 0:99", "byres around 4 index 0:39",
                 "around 5 (index 0:9 and around 3 index 5)", "same resid as index 7"):  # fmt: skip
        selector.select(text, pos, None, LIMITS)
    for text, limit in [
        ("around 1000 index 0:4999", "selection_max_pairs"),
        ("around 5 (" * 20 + "name CA" + ")" * 20, "selection_max_pairs"),
        ("around 5 (" * 60 + "name CA" + ")" * 60, "selection_max_depth"),
        ("same x as all", "selection_max_pairs"),
    ]:
        with pytest.raises(SelectionError) as info:
            selector.select(text, pos, None, LIMITS)
        assert info.value.limit == limit, (text, info.value)
        assert f"({limit})" in info.value.reason


def test_the_costliest_term_is_named_with_its_position() -> None:
    topo, pos = backbone(20_000)
    text = "name CA and around 900 index 0:4999"
    with pytest.raises(SelectionError) as info:
        Selector(topo).select(text, pos, None, LIMITS)
    assert info.value.position == text.index("around")
    assert "most in `around` at character 13" in info.value.reason
    assert "4,000,000" in info.value.reason and info.value.value == 4_000_000


def test_the_layers_of_one_request_share_one_budget() -> None:
    topo, pos = backbone(20_000)
    texts = ["around 6 index 0:1999", "around 6 index 2000:3999", "name CA"]
    selector = Selector(topo)
    costs = [price(selector, t, pos) for t in texts[:2]]
    budget = SelectionLimits(max_pairs=int(costs[0] * 1.5))
    assert costs[1] > budget.max_pairs - costs[0]  # each fits alone; not both
    first, second, third = selector.evaluate(texts, pos, None, budget)
    assert isinstance(first, np.ndarray) and isinstance(third, np.ndarray)
    assert isinstance(second, SelectionError) and second.limit == "selection_max_pairs"
    assert "for the layers before it" in second.reason
    # all or nothing: nothing runs when one is refused
    found = Selector(topo).evaluate(texts, pos, None, budget, strict=True)
    assert isinstance(found[1], SelectionError) and found[1].limit == "selection_max_pairs"
    assert isinstance(found[0], SelectionSkippedError)
    assert isinstance(found[2], SelectionSkippedError)


def test_secondary_structure_of_a_huge_protein_is_refused() -> None:
    topo, pos = backbone(4 * 300)
    selector = Selector(topo)
    with pytest.raises(SelectionError) as info:
        selector.secondary(pos, SelectionLimits(max_pairs=200**2))
    assert info.value.limit == "selection_max_pairs" and "300 residues" in info.value.reason
    codes = selector.secondary(pos, SelectionLimits(max_pairs=300**2))
    assert codes.shape == (topo.n_atoms,)
