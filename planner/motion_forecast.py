"""The forecast update's kernels and numerics (section 3.1, eqs 19-22): how each kind of target
moves from cell to cell in one decision step, and the convolutions and shifts that move a map.

Symbols: delta_e -> ``cfg.delta_e_km_per_sqrt_s``; Delta t -> ``cfg.step_s``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from planner.grid import Grid
from planner.target_priors import CELL_SAMPLES, RING_ANGLES

# ----------------------------------------------------------------------------- forecast kernels


def wiener_kernel_1d(sigma_cells: float) -> np.ndarray:
    """Cell-to-cell kernel of eq 20 along one axis: P(target moves o cells) for a target uniform
    in its cell displaced by N(0, sigma^2) (exact in the displacement, quadrature over the cell)."""
    if sigma_cells <= 0:
        return np.array([1.0])
    half = int(np.ceil(4 * sigma_cells)) + 1
    offsets = np.arange(-half, half + 1)
    u = (np.arange(CELL_SAMPLES) + 0.5) / CELL_SAMPLES
    upper = ndtr((offsets[None, :] + 1 - u[:, None]) / sigma_cells)
    lower = ndtr((offsets[None, :] - u[:, None]) / sigma_cells)
    kernel = (upper - lower).mean(axis=0)
    kernel = kernel[kernel > 1e-4 * kernel.max()]  # drop the far tails (symmetric)
    return kernel / kernel.sum()


def displacement_kernel(dx_cells: np.ndarray, dy_cells: np.ndarray) -> np.ndarray:
    """2-D cell-to-cell kernel of a set of equally likely displacements (cells): a target uniform
    in its cell moved by one of them lands in cell offset (a, b) with the kernel's probability."""
    u = (np.arange(CELL_SAMPLES) + 0.5) / CELL_SAMPLES
    ux, uy = np.meshgrid(u, u, indexing="ij")
    land_x = np.floor(ux.ravel()[:, None] + np.asarray(dx_cells)[None, :]).astype(int).ravel()
    land_y = np.floor(uy.ravel()[:, None] + np.asarray(dy_cells)[None, :]).astype(int).ravel()
    half = int(max(np.abs(land_x).max(), np.abs(land_y).max()))
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    np.add.at(kernel, (land_x + half, land_y + half), 1.0)
    return kernel / kernel.sum()


def ring_kernel(radius_cells: float) -> np.ndarray:
    """Eq 21 on the grid: displacement uniform on the circle of radius v Delta t."""
    theta = (np.arange(RING_ANGLES) + 0.5) * (2 * np.pi / RING_ANGLES)
    return displacement_kernel(radius_cells * np.cos(theta), radius_cells * np.sin(theta))


def has_square_symmetry(kernel: np.ndarray) -> bool:
    """A 3x3 kernel unchanged by the square's reflections: centre, edge and corner weights only."""
    k = kernel
    return (
        k.shape == (3, 3)
        and np.allclose(k, k.T)
        and np.allclose(k, k[::-1])
        and np.allclose(k, k[:, ::-1])
    )


#: bytes of maps a ``SquareStencil`` works through at a time: its passes over a few maps stay
#: in the core's cache (100 maps of 200 x 200 cells at once took 1.4 times as long)
STENCIL_CHUNK_BYTES = 1 << 20


#: cells of maps (maps x their boxes' union) from which a ``SquareStencil`` looks for equal
#: maps to stencil once: below, finding them (about 0.1 ms) costs more than it can save
DISTINCT_MIN_CELLS = 1 << 15


class SquareStencil:
    """Convolution of N maps (N, nx, ny) with a 3x3 kernel of the square's symmetry
    (``has_square_symmetry``), edges reflected, in place: a 9-point stencil on an edge-padded
    copy, in the maps' dtype, a few maps at a time (``STENCIL_CHUNK_BYTES``), with work buffers
    for that many kept between calls (each step's forecast would otherwise allocate, and fault
    in, several map-sized temporaries)."""

    def __init__(self, shape: tuple[int, int, int], dtype: np.dtype) -> None:
        n, nx, ny = shape
        self.chunk = min(n, max(1, STENCIL_CHUNK_BYTES // (nx * ny * np.dtype(dtype).itemsize)))
        m = self.chunk
        self.padded = np.empty((m, nx + 2, ny + 2), dtype=dtype)
        self.vertical = np.empty((m, nx, ny + 2), dtype=dtype)
        self.out = np.empty((m, nx, ny), dtype=dtype)
        self.work = np.empty((m, nx, ny), dtype=dtype)

    def apply(
        self,
        maps: np.ndarray,
        kernel: np.ndarray,
        box: tuple[int, int, int, int] | None = None,
        boxes: np.ndarray | None = None,
        alike: np.ndarray | None = None,
    ) -> None:
        """Replace ``maps`` by its convolution with ``kernel``. With ``box = (x0, x1, y0, y1)``
        the caller promises every cell outside ``[x0, x1) x [y0, y1)`` is zero: only the box
        grown by one cell (all the kernel can reach) is computed; with ``boxes`` (N, 4), one
        such box per map (the maps worked through together take their boxes' union). Each
        cell's value is the same whichever box holds it: the cells beyond are zero. With
        ``alike`` (N,) as well (each map's sum, say: maps that differ in it are different
        maps), the maps alike and equal are stencilled once (``distinct_maps``)."""
        whole = None if boxes is None else union_box(boxes)
        if alike is not None and len(maps) * box_cells(whole) >= DISTINCT_MIN_CELLS:
            regions = maps[:, whole[0] : whole[1], whole[2] : whole[3]]
            firsts, inverse = distinct_maps(regions, alike)
            if len(firsts) < len(maps):
                self._apply_distinct(maps, kernel, boxes, firsts, inverse)
                return
        for start in range(0, len(maps), self.chunk):
            part = slice(start, start + self.chunk)
            self._apply(maps, part, kernel, box if boxes is None else union_box(boxes[part]))

    def _apply_distinct(
        self,
        maps: np.ndarray,
        kernel: np.ndarray,
        boxes: np.ndarray,
        firsts: np.ndarray,
        inverse: np.ndarray,
    ) -> None:
        """``apply`` with ``boxes`` once to each distinct map (``distinct_maps``), its result
        copied to the maps equal to it: UAVs that have heard the same looks hold the same
        map (100 UAVs on 200 x 200 cells: 1 to 30 distinct maps of a layer)."""
        for start in range(0, len(firsts), self.chunk):
            rows = firsts[start : start + self.chunk]
            self._apply(maps, rows, kernel, union_box(boxes[rows]))
        copies = np.flatnonzero(firsts[inverse] != np.arange(len(maps)))
        # all a map's cells the kernel can reach: the union of the boxes grown by one
        x0, x1, y0, y1 = grow_box(union_box(boxes), *maps.shape[1:])
        maps[copies, x0:x1, y0:y1] = maps[firsts[inverse[copies]], x0:x1, y0:y1]

    def _apply(
        self,
        maps: np.ndarray,
        rows: slice | np.ndarray,
        kernel: np.ndarray,
        box: tuple[int, int, int, int] | None,
    ) -> None:
        """``apply`` to the maps ``rows`` (at most ``chunk`` of them)."""
        _, nx, ny = maps.shape
        x0, x1, y0, y1 = grow_box((0, nx, 0, ny) if box is None else box, nx, ny)
        region = maps[rows, x0:x1, y0:y1]  # a view for a slice of rows, else a copy
        n, a, b = region.shape
        centre, edge, corner = float(kernel[1, 1]), float(kernel[0, 1]), float(kernel[0, 0])
        p = self.padded[:n, : a + 2, : b + 2]
        vertical, out, work = (
            self.vertical[:n, :a, : b + 2],
            self.out[:n, :a, :b],
            self.work[:n, :a, :b],
        )
        p[:, 1:-1, 1:-1] = region
        # reflected at the area's edge; elsewhere the cells beyond the grown box are zero
        p[:, 0, 1:-1] = maps[rows, 0, y0:y1] if x0 == 0 else 0.0
        p[:, -1, 1:-1] = maps[rows, nx - 1, y0:y1] if x1 == nx else 0.0
        p[:, :, 0] = p[:, :, 1] if y0 == 0 else 0.0
        p[:, :, -1] = p[:, :, -2] if y1 == ny else 0.0
        np.add(p[:, :-2, :], p[:, 2:, :], out=vertical)  # above + below, padded sideways
        np.add(vertical[:, :, :-2], vertical[:, :, 2:], out=out)  # the four corners
        out *= corner
        np.add(vertical[:, :, 1:-1], p[:, 1:-1, :-2], out=work)  # the four edges
        work += p[:, 1:-1, 2:]
        work *= edge
        out += work
        np.multiply(p[:, 1:-1, 1:-1], centre, out=work)
        if isinstance(rows, slice):
            np.add(out, work, out=region)  # the sum lands in the maps: no copy back
        else:
            np.add(out, work, out=out)
            maps[rows, x0:x1, y0:y1] = out


def box_cells(box: tuple[int, int, int, int]) -> int:
    """The cells of ``box`` (x0, x1, y0, y1)."""
    return (box[1] - box[0]) * (box[3] - box[2])


def distinct_maps(regions: np.ndarray, alike: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The maps of ``regions`` (N, a, b) that differ: ``firsts`` (D,), the first map of each
    distinct content in order, and ``inverse`` (N,), each map's place in ``firsts``
    (``regions[i]`` equals ``regions[firsts[inverse[i]]]``, bit for bit). ``alike`` (N,): maps
    with different values of it are taken to differ; a map is compared (its bits) with the
    first of those alike only, and counted distinct when it is not that one's equal."""
    n = len(regions)
    _, first_alike, which = np.unique(alike, return_index=True, return_inverse=True)
    same_as = first_alike[which.ravel()]  # (N,) the first map alike, itself for the firsts
    others = np.flatnonzero(same_as != np.arange(n))
    if len(others):
        bits = regions.view(np.dtype(f"u{regions.itemsize}"))
        equal = (bits[others] == bits[same_as[others]]).all(axis=(1, 2))
        same_as[others[~equal]] = others[~equal]
    firsts, inverse = np.unique(same_as, return_inverse=True)
    return firsts, inverse.ravel()


def grow_box(box: tuple[int, int, int, int], nx: int, ny: int) -> tuple[int, int, int, int]:
    """``box`` (x0, x1, y0, y1) grown by one cell on every side (all a 3x3 kernel can reach),
    kept inside the ``nx x ny`` area."""
    x0, x1, y0, y1 = box
    return max(x0 - 1, 0), min(x1 + 1, nx), max(y0 - 1, 0), min(y1 + 1, ny)


def tighten_box(
    maps: np.ndarray, box: tuple[int, int, int, int], negligible: np.ndarray
) -> tuple[int, int, int, int]:
    """Shrink ``box`` (x0, x1, y0, y1) of maps (N, nx, ny) past border rows and columns whose
    values all lie below ``negligible`` (N,) in every map, zeroing them: a few strips per
    call (``tighten_boxes`` keeps a box per map)."""
    x0, x1, y0, y1 = box
    limit = negligible[:, None]
    for _ in range(2):
        if x1 - x0 > 1 and (maps[:, x0, y0:y1] < limit).all():
            maps[:, x0, y0:y1] = 0.0
            x0 += 1
        if x1 - x0 > 1 and (maps[:, x1 - 1, y0:y1] < limit).all():
            maps[:, x1 - 1, y0:y1] = 0.0
            x1 -= 1
        if y1 - y0 > 1 and (maps[:, x0:x1, y0] < limit).all():
            maps[:, x0:x1, y0] = 0.0
            y0 += 1
        if y1 - y0 > 1 and (maps[:, x0:x1, y1 - 1] < limit).all():
            maps[:, x0:x1, y1 - 1] = 0.0
            y1 -= 1
    return x0, x1, y0, y1


def union_box(boxes: np.ndarray) -> tuple[int, int, int, int]:
    """The smallest box (x0, x1, y0, y1) holding every box of ``boxes`` (N, 4)."""
    return (int(boxes[:, 0].min()), int(boxes[:, 1].max()), int(boxes[:, 2].min()),
            int(boxes[:, 3].max()))  # fmt: skip


def grow_boxes(boxes: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """``grow_box`` of every box of ``boxes`` (N, 4)."""
    grown = boxes + np.array([-1, 1, -1, 1])
    return np.clip(grown, 0, np.array([nx, nx, ny, ny]))


def tighten_boxes(maps: np.ndarray, boxes: np.ndarray, negligible: np.ndarray) -> np.ndarray:
    """Shrink each map's own box (``boxes`` (N, 4) of x0, x1, y0, y1 for maps (N, nx, ny),
    every cell outside a map's box zero) past border rows and columns whose values all lie
    below that map's ``negligible`` (N,), zeroing them: a few strips per call, so the work stays
    proportional to the boxes' perimeters. Map i's box and cells depend on map i alone: a
    UAV's TPM forecast is the same whether the swarm's maps are batched or it is alone
    (``planner.uav_node``). Returns the new boxes."""
    if len(maps) == 1:  # one UAV (its own node): the strips as slices, fewer numpy calls
        return np.array([tighten_box(maps, tuple(int(v) for v in boxes[0]), negligible)])
    x0, x1, y0, y1 = (boxes[:, k].copy() for k in range(4))
    uav = np.arange(len(maps))
    limit = negligible[:, None]

    def trim(rows: np.ndarray, wide: np.ndarray, at: np.ndarray, axis: int) -> np.ndarray:
        # rows: (N, len) the strip of each map (zero outside its box, so whole rows do)
        ok = wide & (rows < limit).all(axis=1)
        if ok.any():
            if axis == 1:
                maps[uav[ok], at[ok], :] = 0.0
            else:
                maps[uav[ok], :, at[ok]] = 0.0
        return ok

    for _ in range(2):
        x0 += trim(maps[uav, x0, :], x1 - x0 > 1, x0, 1)
        x1 -= trim(maps[uav, x1 - 1, :], x1 - x0 > 1, x1 - 1, 1)
        y0 += trim(maps[uav, :, y0], y1 - y0 > 1, y0, 2)
        y1 -= trim(maps[uav, :, y1 - 1], y1 - y0 > 1, y1 - 1, 2)
    return np.stack([x0, x1, y0, y1], axis=1)


def convolve_reflect(maps: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Convolve each (nx, ny) map of ``maps`` (..., nx, ny) with a 2-D kernel, edges reflected.
    The 3x3 kernels of eq 21 at the paper's speeds have the square's symmetry and take the
    stencil; any other kernel goes through ``scipy.ndimage.convolve``."""
    if has_square_symmetry(kernel) and maps.ndim == 3:
        out = maps.copy()
        SquareStencil(maps.shape, maps.dtype).apply(out, kernel)
        return out
    full = kernel.reshape((1,) * (maps.ndim - 2) + kernel.shape)
    return ndimage.convolve(maps, full, mode="reflect")


def shift_with_reflection(
    maps: np.ndarray, shift: int, axis: int, out: np.ndarray | None = None
) -> np.ndarray:
    """Move every map ``shift`` whole cells along ``axis``; mass pushed over the edge is folded
    back (targets reflect at the area's edge). Mass is conserved. The result goes to ``out``
    (which must not overlap ``maps``) when given, else to a new array."""
    if shift == 0:
        if out is None:
            return maps
        out[...] = maps
        return out
    n = maps.shape[axis]
    s = min(abs(shift), n)
    out = np.empty_like(maps) if out is None else out

    def along(part: slice) -> tuple[slice, ...]:
        index = [slice(None)] * maps.ndim
        index[axis] = part
        return tuple(index)

    if shift > 0:
        out[along(slice(s, n))] = maps[along(slice(0, n - s))]
        out[along(slice(0, s))] = 0.0
        fold_to = slice(n - 1, n - s - 1 if n - s - 1 >= 0 else None, -1)
        out[along(fold_to)] += maps[along(slice(n - s, n))]
    else:
        out[along(slice(0, n - s))] = maps[along(slice(s, n))]
        out[along(slice(n - s, n))] = 0.0
        out[along(slice(s - 1, None, -1))] += maps[along(slice(0, s))]
    return out


def drifted_ratio(
    keys: np.ndarray, ratio: np.ndarray, phase: np.ndarray, grid: Grid, lookup: np.ndarray
) -> np.ndarray:
    """Eq 18's likelihood ratio for layers kept shifted by whole cells while their targets
    drift by a part of one more (eq 22): the target believed in stored cell s is uniform over
    [s + phase, s + phase + 1) along each axis, so it overlaps cell s with share
    (1 - |phase|) and its neighbour towards the phase with share |phase|, and the ratio of a
    look for it is the share-weighted mean of those cells' ratios (``ratio`` at the sorted
    ``keys``, UAV * cells + cell; 1 at cells nobody looked at; a neighbour over the area's
    edge is the cell itself, where the reflected part lies). ``phase`` is (V, 2) in
    [-1/2, 1/2]; the result is (V, P). Reading ratios only at looked-at cells leaves out the
    stored cells just outside a footprint, where eq 17's ratio is close to 1. ``lookup`` is
    a scratch array of ones, one per UAV and cell, left as it was found."""
    uav, cell = np.divmod(keys, grid.size)
    x, y = np.divmod(cell, grid.ny)
    toward = np.sign(phase).astype(np.int64)  # (V, 2)
    share = np.abs(phase)
    near_x = np.clip(x[None] + toward[:, 0, None], 0, grid.nx - 1) * grid.ny  # (V, P)
    near_y = np.clip(y[None] + toward[:, 1, None], 0, grid.ny - 1)
    row, base = x * grid.ny, uav * grid.size
    lookup[keys] = ratio
    out = ((1.0 - share[:, 0]) * (1.0 - share[:, 1]))[:, None] * ratio[None]
    out += (share[:, 0] * (1.0 - share[:, 1]))[:, None] * lookup[base + near_x + y]
    out += ((1.0 - share[:, 0]) * share[:, 1])[:, None] * lookup[base + row + near_y]
    out += (share[:, 0] * share[:, 1])[:, None] * lookup[base + near_x + near_y]
    lookup[keys] = 1.0
    return out


