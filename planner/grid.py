"""Mission grid, the eight headings and the candidate cells of a fixed-wing UAV
(section 2.1, Fig. 1).

The area is ``nx x ny`` square cells of side ``cell_km``; cell ``(ix, iy)`` spans
``[ix, ix+1) x [iy, iy+1)`` cells and its centre is at ``((ix + 0.5) L, (iy + 0.5) L)`` km, x east,
y north. A UAV sits at a cell centre and flies one cell per decision step along one of eight
headings; with a maximum turn of ``phi_max`` it can reach ``2 * floor(phi_max / 45) + 1`` cells
(three for the paper's 45 degrees): the grey cells of Fig. 1, constraint C_m of eq 5.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

#: Unit moves of the eight headings, counter-clockwise from east (heading index 0..7).
HEADING_STEPS = np.array(
    [(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)], dtype=np.int64
)
HEADING_ANGLES_RAD = np.arange(8) * (np.pi / 4)
HEADING_LENGTHS = np.hypot(HEADING_STEPS[:, 0], HEADING_STEPS[:, 1])


def heading_of_angle(angle_rad: float | np.ndarray) -> np.ndarray:
    """Nearest of the eight headings to a direction (radians, counter-clockwise from east)."""
    return np.rint(np.mod(angle_rad, 2 * np.pi) / (np.pi / 4)).astype(np.int64) % 8


def heading_change_deg(h_from: np.ndarray | int, h_to: np.ndarray | int) -> np.ndarray:
    """Absolute heading change between two heading indices, in degrees (0..180)."""
    diff = np.mod(np.asarray(h_to) - np.asarray(h_from), 8)
    return np.minimum(diff, 8 - diff) * 45.0


@dataclass(frozen=True)
class Grid:
    """Geometry of the discrete mission area."""

    nx: int = 100
    ny: int = 100
    cell_km: float = 1.0

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nx, self.ny)

    @property
    def size(self) -> int:
        return self.nx * self.ny

    def centre_km(self, cells: np.ndarray) -> np.ndarray:
        """Centres (..., 2) in km of integer cells (..., 2)."""
        return (np.asarray(cells, dtype=float) + 0.5) * self.cell_km

    def cell_of(self, xy_km: np.ndarray) -> np.ndarray:
        """Integer cell (..., 2) containing each point (..., 2) in km, clipped into the area."""
        cells = np.floor(np.asarray(xy_km, dtype=float) / self.cell_km).astype(np.int64)
        np.maximum(cells, 0, out=cells)
        np.minimum(cells, (self.nx - 1, self.ny - 1), out=cells)
        return cells

    def inside(self, cells: np.ndarray) -> np.ndarray:
        cells = np.asarray(cells)
        if cells.dtype == np.int64:  # read as unsigned, a negative coordinate is too large
            unsigned = cells.view(np.uint64)
            return (unsigned[..., 0] < self.nx) & (unsigned[..., 1] < self.ny)
        return (
            (cells[..., 0] >= 0)
            & (cells[..., 0] < self.nx)
            & (cells[..., 1] >= 0)
            & (cells[..., 1] < self.ny)
        )

    def flat(self, cells: np.ndarray) -> np.ndarray:
        cells = np.asarray(cells)
        return cells[..., 0] * self.ny + cells[..., 1]

    def clipped_flat(self, cells: np.ndarray) -> np.ndarray:
        """Flat index of the area's cell nearest to each of ``cells`` (..., 2) (each coordinate
        clipped into the area): a safe index for reads that ``inside`` then masks."""
        cells = np.asarray(cells)
        x = np.minimum(np.maximum(cells[..., 0], 0), self.nx - 1)
        y = np.minimum(np.maximum(cells[..., 1], 0), self.ny - 1)
        return x * self.ny + y

    @cached_property
    def centres_x_km(self) -> np.ndarray:
        return (np.arange(self.nx) + 0.5) * self.cell_km

    @cached_property
    def centres_y_km(self) -> np.ndarray:
        return (np.arange(self.ny) + 0.5) * self.cell_km

    def disc_offsets(self, radius_km: float) -> np.ndarray:
        """Integer offsets (K, 2) of the cells whose centres lie within ``radius_km`` of a
        centre."""
        r = int(np.floor(radius_km / self.cell_km + 1e-9))
        dx, dy = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
        keep = np.hypot(dx, dy) * self.cell_km <= radius_km + 1e-9
        return np.stack([dx[keep], dy[keep]], axis=1).astype(np.int64)


def corridor_offsets(
    footprint: np.ndarray, steps: int, discount: float
) -> tuple[np.ndarray, np.ndarray]:
    """The cells a UAV's footprint would sweep flying 2..``steps`` straight steps beyond a
    candidate cell, for each heading: ``(offsets (8, K, 2), weights (8, K))`` padded to a common
    K with weight 0. A cell's weight is ``discount ** (s - 1)`` for the first step s whose
    footprint holds it; the candidate's own footprint (s = 1) is left out."""
    per_heading = []
    for h in range(8):
        first_seen: dict[tuple[int, int], int] = {tuple(o): 1 for o in footprint}
        for s in range(2, steps + 1):
            for o in footprint + (s - 1) * HEADING_STEPS[h]:
                first_seen.setdefault((int(o[0]), int(o[1])), s)
        items = [(o, s) for o, s in first_seen.items() if s > 1]
        per_heading.append(items)
    k = max((len(items) for items in per_heading), default=0)
    offsets = np.zeros((8, k, 2), dtype=np.int64)
    weights = np.zeros((8, k))
    for h, items in enumerate(per_heading):
        for j, (o, s) in enumerate(items):
            offsets[h, j] = o
            weights[h, j] = discount ** (s - 1)
    return offsets, weights


def disc_overlap(
    radius_km: float, cell_km: float, samples: int = 32
) -> tuple[np.ndarray, np.ndarray]:
    """Cells overlapping a disc of ``radius_km`` around a cell centre: ``(offsets (K, 2),
    fractions (K,))``, the share of each cell's area inside the disc (midpoint quadrature), so
    that a target uniform in cell o lies within the radius with probability ``fractions[o]``."""
    offsets, fractions = disc_overlap_at(np.zeros((1, 2)), radius_km, cell_km, samples)
    inside = fractions[0] > 0
    return offsets[inside], fractions[0, inside]


def square_offsets(radius: int) -> np.ndarray:
    """(S, 2) int: the cell offsets within ``radius`` moves (Chebyshev distance), (0, 0)
    included, row by row."""
    span = np.arange(-radius, radius + 1)
    return np.stack(np.meshgrid(span, span, indexing="ij"), axis=-1).reshape(-1, 2)


def disc_overlap_at(
    points_km: np.ndarray, radius_km: float, cell_km: float, samples: int = 32
) -> tuple[np.ndarray, np.ndarray]:
    """``disc_overlap`` for discs around points anywhere in a cell: ``points_km`` (M, 2) are
    offsets from the centre of the cell each point lies in (at most half a cell). Returns the
    cell offsets (K, 2) of a window that holds every such disc and ``fractions`` (M, K)."""
    points = np.asarray(points_km, dtype=float).reshape(-1, 2)
    r = int(np.ceil(radius_km / cell_km + 0.5 + (np.abs(points).max(initial=0.0) > 0)))
    offsets = square_offsets(r)
    u = ((np.arange(samples) + 0.5) / samples - 0.5) * cell_km
    # (M, K, samples, samples) distances of the sample points of every window cell
    dx = offsets[None, :, 0, None] * cell_km + u[None, None, :] - points[:, None, 0, None]
    dy = offsets[None, :, 1, None] * cell_km + u[None, None, :] - points[:, None, 1, None]
    inside = np.hypot(dx[..., :, None], dy[..., None, :]) <= radius_km
    return offsets.astype(np.int64), inside.mean(axis=(2, 3))


@lru_cache(maxsize=8)
def steps_to_reach(max_turn_deg: float, reach_cells: int) -> np.ndarray:
    """Fewest turn-limited moves from a UAV at the origin with heading h to each cell offset:
    ``steps[h, dx + r, dy + r]`` (r = ``reach_cells``; a large number where the window does not
    hold a path). A point inside the turning circle needs a detour that the angle to it hides;
    this table, found once by breadth-first search over (heading, cell), gives the true count."""
    r = reach_cells
    side = 2 * r + 1
    turns = turn_options(max_turn_deg)
    unreached = np.iinfo(np.int64).max // 4
    steps = np.full((8, side, side), unreached, dtype=np.int64)
    for h0 in range(8):
        seen = np.zeros((8, side, side), dtype=bool)
        frontier = [(h0, r, r)]
        seen[h0, r, r] = True
        steps[h0, r, r] = 0
        depth = 0
        while frontier:
            depth += 1
            nxt = []
            for h, x, y in frontier:
                for t in turns:
                    h2 = (h + t) % 8
                    x2, y2 = x + HEADING_STEPS[h2][0], y + HEADING_STEPS[h2][1]
                    if 0 <= x2 < side and 0 <= y2 < side and not seen[h2, x2, y2]:
                        seen[h2, x2, y2] = True
                        steps[h0, x2, y2] = min(steps[h0, x2, y2], depth)
                        nxt.append((h2, x2, y2))
            frontier = nxt
    steps.setflags(write=False)  # shared by every planner of the process (cached)
    return steps


def turn_options(max_turn_deg: float) -> np.ndarray:
    """Heading changes allowed in one step, e.g. [-1, 0, 1] for 45 degrees (constraint C_m)."""
    k = int(np.floor(max_turn_deg / 45.0 + 1e-9))
    k = min(k, 4)
    options = list(range(-k, k + 1))
    if k == 4:
        options.remove(4)  # -4 and +4 are the same reversal
    return np.array(options, dtype=np.int64)


def candidate_moves(
    cells: np.ndarray, headings: np.ndarray, max_turn_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate next cells and headings for each UAV (the set Omega of eqs 35-37).

    Args:
        cells: (N, 2) current cells.
        headings: (N,) current heading indices.
        max_turn_deg: phi_max.

    Returns:
        ``(next_cells (N, C, 2), next_headings (N, C))``, C = number of allowed turns; cells may lie
        outside the area (the caller masks them).
    """
    turns = turn_options(max_turn_deg)
    next_headings = np.mod(np.asarray(headings)[:, None] + turns[None, :], 8)
    next_cells = np.asarray(cells)[:, None, :] + HEADING_STEPS[next_headings]
    return next_cells, next_headings
