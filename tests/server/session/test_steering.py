"""Steering state without a server: deep patch merges, confirmed simulation parameters, acks."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

import protocol as p
from server.session.steering import (
    AckBook,
    Pending,
    apply_sim_params,
    merge_patch,
    sim_params_changes,
)


def test_a_nested_patch_changes_only_what_it_names() -> None:
    start = p.RenderParams(lighting=p.Lighting(specular=0.9), sigma_A=2.0)
    merged, changes = merge_patch(start, {"lighting": {"ambient": 0.5}})
    assert merged.lighting.specular == 0.9 and merged.lighting.ambient == 0.5
    assert merged.sigma_A == 2.0
    assert changes == {"lighting.ambient": 0.5}


def test_a_patch_that_repeats_the_current_values_changes_nothing() -> None:
    start = p.RenderParams(mode="volume")
    merged, changes = merge_patch(start, {"mode": "volume", "lighting": {"ambient": 0.25}})
    assert merged == start and changes == {}


def test_lists_and_tuples_are_replaced_whole() -> None:
    start = p.RenderParams(background=(0.1, 0.2, 0.3))
    merged, changes = merge_patch(start, {"background": (1.0, 1.0, 1.0), "transfer_function": []})
    assert merged.background == (1.0, 1.0, 1.0)
    assert changes == {"background": [1.0, 1.0, 1.0]}


def test_a_merge_that_breaks_a_constraint_is_refused() -> None:
    with pytest.raises(ValidationError) as err:
        merge_patch(p.RenderParams(), {"lighting": {"shininess": 0.0}})
    assert err.value.errors()[0]["loc"] == ("lighting", "shininess")


def test_a_patch_message_carries_only_the_fields_it_sets_and_keeps_their_limits() -> None:
    msg = p.decode(p.encode(p.SetRenderParams(params={"lighting": {"ambient": 0.5}})))
    assert isinstance(msg, p.SetRenderParams)
    assert msg.changes() == {"lighting": {"ambient": 0.5}}
    for bad in ({"sigma_A": 0.0}, {"sigma_A": float("nan")}, {"quality": 100.0}):
        with pytest.raises(ValidationError):
            p.SetRenderParams(params=bad)


def test_sim_params_merge_field_by_field_and_engine_key_by_key() -> None:
    current = p.SimParams(temperature_K=300.0, engine={"a": 1, "b": 2})
    change = p.SimParams(timestep_fs=1.0, engine={"b": 3})
    merged = apply_sim_params(current, change)
    assert merged.temperature_K == 300.0 and merged.timestep_fs == 1.0
    assert merged.engine == {"a": 1, "b": 3}
    assert sim_params_changes(change) == {"timestep_fs": 1.0, "engine": {"b": 3}}
    assert sim_params_changes(p.SimParams(temperature_K=310.0)) == {"temperature_K": 310.0}


def test_acks_are_matched_to_what_awaits_them_once() -> None:
    book = AckBook()
    a = book.expect(Pending("c1", 7, "control", 1))
    b = book.expect(Pending("c2", None, "pull", 2))
    free = book.next_seq()
    assert len({a, b, free}) == 3 and len(book) == 2
    assert book.take(free) is None
    taken = book.take(a)
    assert taken is not None and taken.client_seq == 7
    assert book.take(a) is None
    assert [x.kind for x in book.take_all()] == ["pull"] and len(book) == 0
