"""Static contact layout: which body pair each contact slot holds, grouped into colours.

Every pair of bodies gets one persistent contact slot. Slots are grouped into
colours by a round-robin schedule (an edge colouring of the complete graph): no
body appears twice within a colour, so all slots of one colour can be solved at
once and the result equals solving them one after another (Gauss-Seidel). All
indices here are plain numpy constants.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

POLY_POLY, POLY_CIRCLE, CIRCLE_POLY, CIRCLE_CIRCLE, PADDING = range(5)


@dataclasses.dataclass(frozen=True, eq=False)
class ContactLayout:
    """Slot s = colour * K + k holds the pair (slot_a[s], slot_b[s]).

    The colours come from the circle method: the M padded bodies stand in a line,
    body 0 fixed and the others rotating one place per colour, and colour r pairs
    line[k] with line[M - 1 - k]. The solver visits only the colours that hold a
    contact point (contact_solver.schedule) and gathers each one's two sides by row.
    """

    num_bodies: int  # N = P + C
    num_padded: int  # M: N rounded up to even; body N (if M > N) is a static dummy
    num_colours: int  # M - 1
    per_colour: int  # K = M / 2 slots in each colour
    slot_a: np.ndarray  # (S,) global body index of side a (the dummy N for padding)
    slot_b: np.ndarray  # (S,) global body index of side b
    slot_kind: np.ndarray  # (S,) POLY_POLY / POLY_CIRCLE / CIRCLE_POLY / CIRCLE_CIRCLE / PADDING
    # The slots the narrow phase evaluates, per kind. Pairs of two always-static
    # polygons (SolverConfig.num_static) and pairs with the dummy are left out.
    by_kind: dict
    # For each slot, its row in the concatenation of the by_kind results (kind order) plus one empty row.
    gather: np.ndarray  # (S,)
    # The order the solver visits the slots in: colour c is solve_slots[c * K:(c + 1) * K]. The
    # identity unless always-static walls may repeat within a colour (see wall_grouped).
    solve_slots: np.ndarray  # (S,) a permutation of the slots
    walls_repeat: bool  # some body (always static) appears more than once in a colour

    @property
    def num_slots(self) -> int:
        return self.num_colours * self.per_colour

    @property
    def solve_sides(self) -> np.ndarray:
        """(C, 2K): the bodies of side a, then of side b, of each colour's slots in solve order."""
        C, K = self.num_colours, self.per_colour
        return np.concatenate([self.slot_a[self.solve_slots].reshape(C, K),
                               self.slot_b[self.solve_slots].reshape(C, K)], axis=1)

    @functools.cached_property
    def slot_order(self) -> np.ndarray:
        """(S,) the inverse of solve_slots: where each slot stands in solve order."""
        return np.argsort(self.solve_slots).astype(np.int32)

    @functools.cached_property
    def write_back(self) -> np.ndarray:
        """(C, M): after colour c is solved, body m's velocity is row write_back[c, m] of the body
        velocities followed by the colour's 2K solved ones: M + p if the body is at position p of
        solve_sides[c] (any one of them for a repeated static body: they all hold its unchanged
        velocity), else m (the body is not in the colour).

        A gather by this row is how the sweeps write a colour back: a scatter to the colour's 2K
        bodies compiled to a loop over them on the CPU, about 100 small kernels per colour.
        """
        M = self.num_padded
        rows = np.tile(np.arange(M, dtype=np.int32), (self.num_colours, 1))
        for c, sides in enumerate(self.solve_sides):
            rows[c, sides] = M + np.arange(len(sides), dtype=np.int32)
        return rows


def circle_method(m: int) -> tuple[np.ndarray, np.ndarray]:
    """(m - 1, m / 2) arrays a, b: round r pairs a[r, k] with b[r, k]; every pair appears once."""
    assert m % 2 == 0 and m >= 2
    others = np.arange(1, m)
    a, b = [], []
    for r in range(m - 1):
        line = np.concatenate([[0], np.roll(others, r)])
        a.append(line[: m // 2])
        b.append(line[m // 2 :][::-1])
    return np.array(a, dtype=np.int32), np.array(b, dtype=np.int32)


def wall_grouped(num_padded: int, static: list[int]) -> np.ndarray | None:
    """Colours in which the always-static bodies may repeat, so each one's pairs share few colours.

    Returns (C, K, 2) body pairs covering every pair of the num_padded bodies once, or None where
    this construction does not apply. Why: a body lying on the floor has a contact with body 0 in
    every step, and the round-robin puts each pair of body 0 in a colour of its own, so five boxes
    on the floor keep five colours live in every sweep. A static body's velocity never changes, so
    it may stand in many slots of one colour.

    Construction, with s static bodies and the D others split into q = D / s groups of s (s even,
    q odd): colour (w, i) pairs static body w with every body of group i, and pairs the other groups
    with each other along round i of a round-robin of the q groups (group pair (j, k) by the Latin
    matching t -> (t + w) mod s). Then s - 1 colours each hold one round-robin matching inside every
    group plus one of the static bodies with each other. Each static body's pairs then fill q colours
    instead of D.
    """
    M = num_padded
    static = list(static)
    s = len(static)
    dynamic = [i for i in range(M) if i not in static]
    D = len(dynamic)
    if s < 2 or s % 2 or D < s or D % s or (D // s) % 2 == 0:
        return None
    q = D // s
    groups = [dynamic[i * s:(i + 1) * s] for i in range(q)]
    rounds_a, rounds_b = circle_method(q + 1)  # q odd: q + 1 "teams"; team q is the bye
    bye = {int(x if y == q else y): r for r in range(q)
           for x, y in zip(rounds_a[r], rounds_b[r], strict=True) if q in (x, y)}
    colours = []
    for i in range(q):
        r = bye[i]
        group_pairs = [(j, k) for j, k in zip(rounds_a[r], rounds_b[r], strict=True) if q not in (j, k)]
        for w in range(s):
            colour = [(static[w], d) for d in groups[i]]
            colour += [(groups[j][t], groups[k][(t + w) % s]) for j, k in group_pairs for t in range(s)]
            colours.append(colour)
    inner_a, inner_b = circle_method(s)
    for r in range(s - 1):
        colour = [(g[inner_a[r][t]], g[inner_b[r][t]]) for g in groups for t in range(s // 2)]
        colour += [(static[inner_a[r][t]], static[inner_b[r][t]]) for t in range(s // 2)]
        colours.append(colour)
    return np.array(colours, dtype=np.int32)


def walls_whole(num_padded: int, static: list[int]) -> np.ndarray | None:
    """Colours in which each always-static body's pairs with the others fill one colour, or None.

    Applies where the D others are no more than K = num_padded / 2, which leaves at least K static
    bodies. Like wall_grouped, (C, K, 2) body pairs covering every pair once. Construction: the
    pairs among the others, as matchings (a round-robin of D bodies, or of D + 1 with a bye when D
    is odd), one colour each; with D odd, each matching's left-out body is paired with the last
    static body in that colour (each other body is left out once). Every other static body gets a
    colour of its own holding its pairs with all D others. The pairs of two static bodies (never
    solved) fill the free slots.
    """
    M = num_padded
    static = list(static)
    dynamic = [i for i in range(M) if i not in static]
    D, K = len(dynamic), M // 2
    if D == 0 or D > K:
        return None
    colours = []
    if D % 2:
        rounds_a, rounds_b = circle_method(D + 1)  # body D is the bye
        for ra, rb in zip(rounds_a, rounds_b, strict=True):
            colour = [(dynamic[x], dynamic[y]) for x, y in zip(ra, rb, strict=True) if D not in (x, y)]
            left_out = next(int(x if y == D else y) for x, y in zip(ra, rb, strict=True) if D in (x, y))
            colours.append(colour + [(static[-1], dynamic[left_out])])
        whole = static[:-1]
    else:
        if D > 1:
            rounds_a, rounds_b = circle_method(D)
            colours += [[(dynamic[x], dynamic[y]) for x, y in zip(ra, rb, strict=True)]
                        for ra, rb in zip(rounds_a, rounds_b, strict=True)]
        whole = static
    colours += [[(w, d) for d in dynamic] for w in whole]
    free = iter([(x, y) for i, x in enumerate(static) for y in static[i + 1:]])
    colours = [colour + [next(free) for _ in range(K - len(colour))] for colour in colours]
    assert next(free, None) is None and len(colours) == M - 1
    return np.array(colours, dtype=np.int32)


def _solve_order(a: np.ndarray, b: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """The slot of each pair of `colours` (C, K, 2), flattened: the permutation that visits them in that order."""
    slot = {(min(x, y), max(x, y)): i for i, (x, y) in enumerate(zip(a.tolist(), b.tolist(), strict=True))}
    order = np.array([slot[(min(x, y), max(x, y))] for x, y in colours.reshape(-1, 2).tolist()], dtype=np.int32)
    assert sorted(order.tolist()) == list(range(len(a))), "wall_grouped must cover every pair once"
    return order


@functools.cache
def contact_layout(num_polygons: int, num_circles: int, num_static: int = 0) -> ContactLayout:
    P, C = num_polygons, num_circles
    N = P + C
    M = max(2, N + (N % 2))
    a, b = (x.reshape(-1) for x in circle_method(M))
    kind = np.full(a.shape, PADDING, dtype=np.int32)
    real = (a < N) & (b < N) & ~((a < num_static) & (b < num_static))
    a_poly, b_poly = a < P, b < P
    kind[real & a_poly & b_poly] = POLY_POLY
    kind[real & a_poly & ~b_poly] = POLY_CIRCLE
    kind[real & ~a_poly & b_poly] = CIRCLE_POLY
    kind[real & ~a_poly & ~b_poly] = CIRCLE_CIRCLE
    by_kind = {k: np.nonzero(kind == k)[0] for k in (POLY_POLY, POLY_CIRCLE, CIRCLE_POLY, CIRCLE_CIRCLE)}
    order = np.concatenate(list(by_kind.values()))
    gather = np.full(a.shape, len(order), dtype=np.int32)
    gather[order] = np.arange(len(order), dtype=np.int32)
    # With always-static walls, colours where they repeat: the dummy body N (static too) joins them
    # where that makes the construction apply.
    grouped = None
    if num_static:
        walls = list(range(num_static))
        options = [walls + [N], walls] if M > N else [walls]
        grouped = next((g for g in (wall_grouped(M, st) for st in options) if g is not None), None)
        if grouped is None:
            grouped = walls_whole(M, walls + list(range(N, M)))
    solve = np.arange(len(a), dtype=np.int32) if grouped is None else _solve_order(a, b, grouped)
    return ContactLayout(N, M, M - 1, M // 2, a, b, kind, by_kind, gather, solve, grouped is not None)
