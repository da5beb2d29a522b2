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

    @property
    def num_slots(self) -> int:
        return self.num_colours * self.per_colour


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
    return ContactLayout(N, M, M - 1, M // 2, a, b, kind, by_kind, gather)
