"""Forces of a session: springs, caps, and the merge of every client's pulls and script forces."""

from __future__ import annotations

import numpy as np
import pytest

import protocol as p
from protocol.forces import cap_forces, vector_norms
from server.session.forces import ForceBook, spring_force


def test_the_cap_scales_long_vectors_down_and_survives_huge_components() -> None:
    v, n = cap_forces([[3.0, 4.0, 0.0], [1e200, 0.0, 0.0], [0.0, 0.0, 0.0]], 1.0)
    assert n == 2
    np.testing.assert_allclose(v, [[0.6, 0.8, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert vector_norms([[1e300, 1e300, 0.0]])[0] == pytest.approx(1e300 * 2**0.5)
    with pytest.raises(ValueError, match="finite"):
        cap_forces([[np.nan, 0.0, 0.0]], 1.0)
    with pytest.raises(ValueError, match="positive"):
        cap_forces([[1.0, 0.0, 0.0]], 0.0)


def test_a_spring_pulls_toward_its_target_and_is_capped() -> None:
    pull = p.Pull(atom=0, target=(10.0, 0.0, 0.0), spring_k=2.0, max_force=15.0)
    np.testing.assert_allclose(spring_force(pull, [9.0, 0.0, 0.0]), [2.0, 0.0, 0.0])
    np.testing.assert_allclose(spring_force(pull, [0.0, 0.0, 0.0]), [15.0, 0.0, 0.0])
    constant = p.Pull(atom=0, force=(0.0, 3.0, 4.0), max_force=2.5)
    np.testing.assert_allclose(spring_force(constant, [5.0, 5.0, 5.0]), [0.0, 1.5, 2.0])


def test_a_spring_follows_the_nearest_image_of_an_atom_wrapped_across_the_box() -> None:
    # the display wraps an atom that left the box at x = -0.5 to x = 29.5 (box 30 A): the pull
    # toward x = 11 must still push it along +x, as it did before it crossed
    pull = p.Pull(atom=0, target=(11.0, 3.0, 3.0), spring_k=1.0, max_force=100.0)
    cube = np.diag([30.0, 30.0, 30.0])
    np.testing.assert_allclose(spring_force(pull, [29.5, 3.0, 3.0], cube), [11.5, 0.0, 0.0])
    np.testing.assert_allclose(spring_force(pull, [-0.5, 3.0, 3.0], cube), [11.5, 0.0, 0.0])
    assert spring_force(pull, [29.5, 3.0, 3.0])[0] == pytest.approx(-18.5)  # no box: as given
    # a triclinic box: the image one box vector away along the tilted axis
    tilted = np.array([[30.0, 0.0, 0.0], [10.0, 30.0, 0.0], [0.0, 0.0, 30.0]])
    np.testing.assert_allclose(
        spring_force(pull, [11.0 + 10.0, 3.0 + 30.0, 3.0], tilted), [0.0, 0.0, 0.0], atol=1e-9
    )
    book = ForceBook()
    book.pull("user", pull)
    _, forces = book.merged(np.array([[29.5, 3.0, 3.0]], np.float32), cube)
    np.testing.assert_allclose(forces, [[11.5, 0.0, 0.0]])


def test_every_clients_forces_are_merged_and_summed_per_atom() -> None:
    book = ForceBook(max_force=100.0)
    book.set_scripted("script", [2, 4, 4], [[1, 0, 0], [0, 1, 0], [0, 1, 0]])
    book.pull("user", p.Pull(atom=4, force=(0.0, 0.0, 5.0)))
    book.pull("user", p.Pull(atom=6, target=(1.0, 0.0, 0.0), spring_k=1.0))
    positions = np.zeros((8, 3), np.float32)
    idx, forces = book.merged(positions)
    assert idx.tolist() == [2, 4, 6]
    np.testing.assert_allclose(forces, [[1, 0, 0], [0, 2, 5], [1, 0, 0]])
    assert book.springs and book.atoms() == {2, 4, 6}
    assert [x.atom for x in book.pulling()] == [4, 6]


def test_a_leaving_client_takes_only_its_own_forces() -> None:
    book = ForceBook()
    book.set_scripted("script", [1], [[1, 0, 0]])
    book.pull("user", p.Pull(atom=3, force=(1.0, 0.0, 0.0)))
    assert book.drop_client("user")
    assert not book.drop_client("nobody")
    idx, _ = book.merged(None)
    assert idx.tolist() == [1]
    book.set_scripted("script", [], np.zeros((0, 3)))
    assert not book.active


def test_script_forces_are_capped_and_a_spring_needs_positions() -> None:
    book = ForceBook(max_force=10.0)
    book.set_scripted("s", [0], [[1e6, 0, 0]])
    book.pull("u", p.Pull(atom=1, target=(5.0, 0.0, 0.0)))
    idx, forces = book.merged(None)  # no frame yet: the spring waits for positions
    assert idx.tolist() == [0] and forces[0, 0] == pytest.approx(10.0)
    book.pull("u", p.Pull(atom=1, release=True))
    assert book.pulls == {}
