"""The contact layout: every body pair in one slot, colours a sweep may solve at once."""

import itertools

import numpy as np
import pytest

from jax2d.pairs import PADDING, contact_layout

CAPACITIES = [(5, 2), (6, 3), (12, 4), (4, 0), (4, 4), (8, 2), (12, 12), (7, 0)]


def _pairs(layout) -> list[tuple[int, int]]:
    return [tuple(sorted(p)) for p in zip(layout.slot_a.tolist(), layout.slot_b.tolist(), strict=True)]


@pytest.mark.parametrize("num_static", [0, 4])
@pytest.mark.parametrize("capacity", CAPACITIES)
def test_every_pair_has_one_slot_and_a_colour_repeats_only_static_bodies(capacity, num_static: int) -> None:
    layout = contact_layout(*capacity, num_static)
    M, N = layout.num_padded, layout.num_bodies
    assert sorted(_pairs(layout)) == list(itertools.combinations(range(M), 2))
    assert sorted(layout.solve_slots.tolist()) == list(range(layout.num_slots))
    static = set(range(num_static)) | set(range(N, M))  # the walls and the dummy body never move
    for colour in layout.solve_sides:
        moving = [b for b in colour.tolist() if b not in static]
        assert len(moving) == len(set(moving)), f"a moving body twice in colour {colour}"
    assert not (layout.walls_repeat and num_static == 0)


@pytest.mark.parametrize("capacity", CAPACITIES)
def test_the_slot_of_a_pair_does_not_depend_on_num_static(capacity) -> None:
    """The state's contact slots (warm starts, touching, scene edits) mean the same pair whatever the solver
    config; only the order the sweeps visit them in changes, and wall-wall pairs are not collided."""
    plain, walls = contact_layout(*capacity, 0), contact_layout(*capacity, 4)
    assert _pairs(plain) == _pairs(walls)
    wall_wall = (plain.slot_a < 4) & (plain.slot_b < 4)
    assert (walls.slot_kind[wall_wall] == PADDING).all()
    assert (walls.slot_kind[~wall_wall] == plain.slot_kind[~wall_wall]).all()


def _colours_pairing(layout, body: int) -> set[int]:
    """The colours in which `body` is paired with a body that is neither a wall nor the dummy."""
    K, N = layout.per_colour, layout.num_bodies
    found = set()
    for c, sides in enumerate(layout.solve_sides.tolist()):
        for x, y in zip(sides[:K], sides[K:], strict=True):
            other = x if y == body else y if x == body else -1
            if 4 <= other < N:
                found.add(c)
    return found


@pytest.mark.parametrize(("capacity", "floor_colours"), [((12, 4), 3), ((5, 2), 1), ((12, 12), 5), ((6, 3), 1),
                                                         ((6, 2), 1)])
def test_wall_grouped_colours_put_the_floor_pairs_in_few_colours(capacity, floor_colours: int) -> None:
    """Why the layout exists: a body on the floor keeps the colour of its floor pair live in every sweep."""
    layout = contact_layout(*capacity, 4)
    assert layout.walls_repeat
    assert len(_colours_pairing(layout, 0)) == floor_colours
    plain = contact_layout(*capacity, 0)  # the round-robin: a colour for each of the floor's pairs
    assert len(_colours_pairing(plain, 0)) == plain.num_bodies - 4


def test_capacities_the_constructions_do_not_fit_keep_the_round_robin() -> None:
    # 10 bodies: 4 walls and 6 others (wall_grouped needs an odd number of groups of 4, walls_whole
    # at most 5 others)
    layout = contact_layout(6, 4, 4)
    assert not layout.walls_repeat
    assert layout.solve_slots.tolist() == list(range(layout.num_slots))


@pytest.mark.parametrize("num_static", [0, 4])
@pytest.mark.parametrize("capacity", CAPACITIES)
def test_write_back_puts_each_solved_velocity_at_its_body(capacity, num_static: int) -> None:
    """The sweeps write a colour back by gathering from (bodies, solved sides) with write_back: every body
    in the colour takes a solved row that belongs to it, every other body keeps its own."""
    layout = contact_layout(*capacity, num_static)
    M = layout.num_padded
    assert sorted(layout.slot_order[layout.solve_slots].tolist()) == list(range(layout.num_slots))
    assert (layout.slot_order[layout.solve_slots] == np.arange(layout.num_slots)).all()
    for sides, rows in zip(layout.solve_sides, layout.write_back, strict=True):
        taken = np.concatenate([np.arange(M), sides])[rows]  # the body each row came from
        assert (taken == np.arange(M)).all()
        assert set(np.nonzero(rows >= M)[0].tolist()) == set(sides.tolist())
