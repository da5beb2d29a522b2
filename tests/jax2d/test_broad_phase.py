"""The broad phase and per-step colouring for big scenes (jax2d.broad_phase, SolverConfig.broad_phase)."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import broad_phase, scene
from jax2d.narrow_phase import pair_filter
from jax2d.pairs import contact_layout
from tests.jax2d.scenes import pyramid, rollout

STEP = jax2d.jit(jax2d.step, static_argnames="config")
BROAD = jax2d.SolverConfig(broad_phase=True)
ALL_PAIRS = jax2d.SolverConfig(broad_phase=False)


def _colouring(state):
    """The broad phase's candidates and colouring for one scene, as numpy."""
    layout = contact_layout(state.num_polygons, state.num_circles)
    M, S = layout.num_padded, layout.num_slots
    b = jax.tree.map(lambda x: x[..., None], state.bodies)
    rows, _, _ = broad_phase.rows_for(layout)
    spec = jnp.full((1,), 0.04)
    may = pair_filter(layout, b, jnp.zeros((S, 1), bool), M)
    cand = broad_phase.candidates(layout, b, spec, may, broad_phase.PAD_ROWS)
    manifold = broad_phase.collide_candidates(cand, b, spec, rows + broad_phase.PAD_ROWS)
    live = np.asarray(jnp.any(manifold.valid, axis=1) & (cand.slot_kind != 4))  # (L, 1): one scene
    dyn = np.asarray(state.bodies.active & (state.bodies.inv_mass > 0))
    shareable = jnp.asarray(np.pad(~dyn, (0, M - len(dyn)), constant_values=True))[:, None]
    solved, placed = broad_phase.colour(cand, jnp.asarray(live), shareable, M)
    one = functools.partial(jax.tree.map, lambda x: np.asarray(x)[..., 0])
    solved = dataclasses.replace(solved, **{f: one(getattr(solved, f)) for f in (
        "slot_a", "slot_b", "slot_kind", "solve_slots", "slot_order", "solve_sides", "write_back")})
    return cand, live[:, 0], np.asarray(placed)[:, 0], solved, np.asarray(shareable)[:, 0]


def test_colouring_places_every_touching_pair_once_and_no_moving_body_twice_per_colour():
    state, _, _ = pyramid(6)
    cand, live, placed, solved, shareable = _colouring(state)
    assert live.sum() > 20 and np.array_equal(placed, live)
    order = np.asarray(solved.slot_order)
    K = solved.per_colour
    n = solved.num_colours * K
    # Each placed row has a position of its own; the other rows none (n: out of range, unpacked as 0).
    assert len(set(order[placed].tolist())) == placed.sum() and np.all(order[placed] < n)
    assert np.all(order[~placed] == n)
    solve = np.asarray(solved.solve_slots)
    assert np.array_equal(solve[order[placed]], np.nonzero(placed)[0])
    assert not live[solve[~np.isin(np.arange(n), order[placed])]].any()  # empty positions hold a dead row
    sides = np.asarray(solved.solve_sides)
    live_at = live[np.asarray(solved.solve_slots)].reshape(solved.num_colours, K)
    for c in range(solved.num_colours):
        bodies = np.concatenate([sides[c, :K][live_at[c]], sides[c, K:][live_at[c]]])
        moving = bodies[~shareable[bodies]]
        assert len(moving) == len(set(moving.tolist())), f"colour {c} repeats a moving body"
    # Far fewer colours than the all-pairs layout's sweeps visit (22 bodies: 21 colours, most live).
    used = int(np.max(np.where(placed, order // K, -1))) + 1
    assert used <= 10, used


def test_broad_phase_step_matches_all_pairs_on_a_small_pyramid():
    state, _, _ = pyramid(4)
    state, _ = rollout(state, jax2d.SimParams(), 60, config=ALL_PAIRS)
    none = (jnp.zeros(0), jnp.zeros(0))
    a = STEP(state, jax2d.SimParams(), *none, config=ALL_PAIRS)
    b = STEP(state, jax2d.SimParams(), *none, config=BROAD)
    # Same contacts (slots, keys) and, warm started, the same result up to the colour order.
    assert np.array_equal(np.asarray(a.contacts.active), np.asarray(b.contacts.active))
    assert np.array_equal(np.asarray(a.contacts.key), np.asarray(b.contacts.key))
    np.testing.assert_allclose(np.asarray(b.bodies.position), np.asarray(a.bodies.position), atol=1e-5)
    np.testing.assert_allclose(np.asarray(b.contacts.normal_impulse), np.asarray(a.contacts.normal_impulse),
                               atol=1e-3)


def test_overflow_is_counted_and_the_step_stays_finite():
    # 30 circles stacked on one spot: 435 close pairs against a capacity of 4 x 30 = 120 (plus the floor's).
    state = jax2d.empty_state(jax2d.Capacity(polygons=1, circles=30, joints=0, thrusters=0, max_vertices=4))
    state, _ = scene.add_rectangle(state, (0.0, -0.5), 40.0, 1.0, fixed=True)
    for i in range(30):
        state, _ = scene.add_circle(state, (0.001 * i, 0.5), 0.5)
    assert broad_phase.overflow(state) == (435 - 120, 0)  # the 120 kept pairs fit 32 colours
    spaced = jax2d.empty_state(jax2d.Capacity(polygons=1, circles=30, joints=0, thrusters=0, max_vertices=4))
    spaced, _ = scene.add_rectangle(spaced, (0.0, -0.5), 40.0, 1.0, fixed=True)
    for i in range(30):
        spaced, _ = scene.add_circle(spaced, (1.5 * i - 20.0, 0.5), 0.5)
    assert broad_phase.overflow(spaced) == (0, 0)
    out = STEP(state, jax2d.SimParams(), jnp.zeros(0), jnp.zeros(0), config=BROAD)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(out))


def test_a_scene_steps_the_same_alone_and_in_a_batch_with_the_broad_phase():
    """Candidates and colourings are per scene, so a scene's result does not depend on its batch companions
    (a shared colouring made them differ beyond rounding). Companions: the same pyramid moved sideways and
    one with its boxes shuffled, whose touching pairs and colours differ from the scene's."""
    state, boxes, _ = pyramid(5)
    pos = np.array(state.bodies.position)
    pos[boxes, 1] += 0.02 * np.arange(len(boxes))  # falling onto each other: impulses change every step
    state = dataclasses.replace(state, bodies=dataclasses.replace(state.bodies, position=jnp.asarray(pos)))
    moved = dataclasses.replace(state, bodies=dataclasses.replace(
        state.bodies, position=jnp.asarray(pos + np.array([3.0, 0.0], np.float32))))
    shuffled = pos.copy()
    shuffled[boxes] = pos[np.random.default_rng(1).permutation(boxes)]  # other pairs touch
    shuffled = dataclasses.replace(state, bodies=dataclasses.replace(state.bodies, position=jnp.asarray(shuffled)))
    batch = jax.tree.map(lambda *x: jnp.stack(x), shuffled, state, moved)
    none = (jnp.zeros(0), jnp.zeros(0))
    many = jax2d.jit(jax.vmap(lambda s: jax2d.step(s, jax2d.SimParams(), *none, config=BROAD)))
    alone, together = state, batch
    for _ in range(20):
        alone = STEP(alone, jax2d.SimParams(), *none, config=BROAD)
        together = many(together)
    mine = jax.tree.map(lambda x: x[1], together)
    print("\n[alone vs batch] max position difference", np.max(np.abs(np.asarray(mine.bodies.position)
                                                                   - np.asarray(alone.bodies.position))))
    assert np.array_equal(np.asarray(mine.contacts.key), np.asarray(alone.contacts.key))
    np.testing.assert_allclose(np.asarray(mine.bodies.position), np.asarray(alone.bodies.position), atol=2e-5)
    np.testing.assert_allclose(np.asarray(mine.bodies.angle), np.asarray(alone.bodies.angle), atol=2e-5)
    np.testing.assert_allclose(np.asarray(mine.contacts.normal_impulse), np.asarray(alone.contacts.normal_impulse),
                               atol=1e-3)


@pytest.mark.slow
def test_big_pyramid_stands_with_the_broad_phase():
    """210 boxes (rows of 20 down to 1) for 10 s: the broad phase is on by default above 100 bodies.
    Today's all-pairs figures (issue 28): drift 5 mm, top box sinks 33 mm."""
    base = 20
    state, boxes, rows = pyramid(base)
    assert broad_phase.uses_broad_phase(jax2d.SolverConfig().broad_phase, state.num_bodies)
    assert broad_phase.overflow(state) == (0, 0)
    start = np.asarray(state.bodies.position)[boxes]
    final, rec = rollout(state, jax2d.SimParams(), 600)
    pos = rec["position"][:, boxes]
    drift = np.max(np.abs(pos[..., 0] - start[:, 0]))
    top = boxes[rows == base - 1][0]
    top_drop = start[rows == base - 1][0, 1] - np.min(rec["position"][:, top, 1])
    sink = -np.min(pos[:, rows == 0, 1] - 0.5)
    print(f"\n[pyramid 210 boxes, broad phase, 10 s] drift {drift * 1000:.3f} mm; top box dropped "
          f"{top_drop * 1000:.3f} mm; deepest bottom-row sink {sink * 1000:.3f} mm")
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(final))
    assert drift < 0.01
    assert top_drop < 0.035
    assert sink < 0.006


@pytest.mark.slow
def test_55_box_pyramid_holds_the_same_with_the_broad_phase():
    """test_physics.test_pyramid_stays_standing's scene and thresholds, with the broad phase forced on."""
    state, boxes, rows = pyramid(10)
    start = np.asarray(state.bodies.position)[boxes]
    _, rec = rollout(state, jax2d.SimParams(), 600, config=BROAD)
    pos = rec["position"][:, boxes]
    drift = np.max(np.abs(pos[..., 0] - start[:, 0]))
    top = boxes[rows == 9][0]
    top_drop = start[rows == 9][0, 1] - np.min(rec["position"][:, top, 1])
    sink = -np.min(pos[:, rows == 0, 1] - 0.5)
    print(f"\n[pyramid 55 boxes, broad phase, 10 s] drift {drift * 1000:.3f} mm; top box dropped "
          f"{top_drop * 1000:.3f} mm; sink {sink * 1000:.3f} mm")
    assert drift < 0.01 and top_drop < 0.02 and sink < 0.005
