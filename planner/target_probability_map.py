"""Target probability maps (TPM, section 3.1): initialisation (eqs 9-16), probe update (eqs 17-18)
and forecast update (eqs 19-22), kept per UAV and batched across the swarm.

How several targets share one map (the paper is silent): the map is split into *layers*, one
per group of targets that move under the same forecast kernel (all unknown-position targets;
all known-position targets; known-speed targets of one speed; each known-velocity target). A
layer holds the expected number of its targets in each cell, so it sums to the number of its
targets still at large. Eq 18 is applied cell by cell to each layer, each layer is renormalised
to its count (eq 16), and the cell's target existence probability ``p_mn`` used by the rest of
the planner is ``1 - prod_layers (1 - layer_mn)``.

Arrays are ``(L, N, nx, ny)``: layer, UAV, cell. Each UAV owns its slice (its own beliefs).

Symbols: delta_0 -> ``cfg.delta_0_km``; delta_e -> ``cfg.delta_e_km_per_sqrt_s``; t_0 ->
``cfg.t0_s``; tau -> ``cfg.tpm_decay_tau``; Delta t -> ``cfg.step_s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from planner.config import PlannerConfig
from planner.grid import Grid
from planner.scenario import TargetSpec
from planner.sensor_model import detection_probability, likelihood_ratio, posterior

#: Quadrature sizes for the ring integrals and the cell-to-cell motion kernels.
RING_ANGLES = 128
CELL_SAMPLES = 16


# ----------------------------------------------------------------------------- initialisation


def _cell_gaussian_mass(
    centre_x: np.ndarray, centre_y: np.ndarray, sigma: float, grid: Grid
) -> np.ndarray:
    """Mass of isotropic Gaussians N(centre, sigma^2) in each cell, integrated exactly (eq 15).

    ``centre_x``/``centre_y`` are (A,) arrays; the result is (nx, ny), the average over the A
    Gaussians (the A points of a ring quadrature, or one point)."""
    edges_x = np.arange(grid.nx + 1) * grid.cell_km
    edges_y = np.arange(grid.ny + 1) * grid.cell_km
    cdf_x = ndtr((edges_x[None, :] - np.asarray(centre_x)[:, None]) / sigma)  # (A, nx+1)
    cdf_y = ndtr((edges_y[None, :] - np.asarray(centre_y)[:, None]) / sigma)
    mass_x = np.diff(cdf_x, axis=1)  # (A, nx)
    mass_y = np.diff(cdf_y, axis=1)
    return np.einsum("ai,aj->ij", mass_x, mass_y) / len(mass_x)


def uniform_prior(grid: Grid) -> np.ndarray:
    """Eq 9: unknown position, the same probability in every cell."""
    return np.full(grid.shape, 1.0 / grid.size)


def wiener_prior(target: TargetSpec, cfg: PlannerConfig, grid: Grid) -> np.ndarray:
    """Eq 11: known position, unknown velocity; N(x*, delta_0^2 + delta_e^2 t_0)."""
    sigma = np.sqrt(cfg.delta_0_km**2 + cfg.delta_e_km_per_sqrt_s**2 * cfg.t0_s)
    return _cell_gaussian_mass(np.array([target.x_km]), np.array([target.y_km]), sigma, grid)


def ring_prior(target: TargetSpec, cfg: PlannerConfig, grid: Grid) -> np.ndarray:
    """Eqs 12-13: known speed v, unknown heading; the Gaussian of eq 10 averaged over the circle
    of radius v t_0 around x* (angular quadrature, each Gaussian integrated over cells)."""
    radius = target.speed_mps / 1000.0 * cfg.t0_s
    theta = (np.arange(RING_ANGLES) + 0.5) * (2 * np.pi / RING_ANGLES)
    return _cell_gaussian_mass(
        target.x_km + radius * np.cos(theta),
        target.y_km + radius * np.sin(theta),
        cfg.delta_0_km,
        grid,
    )


def shifted_prior(target: TargetSpec, cfg: PlannerConfig, grid: Grid) -> np.ndarray:
    """Eq 14: known velocity; N(x* + v t_0 (cos theta, sin theta), delta_0^2)."""
    shift = target.speed_mps / 1000.0 * cfg.t0_s
    return _cell_gaussian_mass(
        np.array([target.x_km + shift * np.cos(target.heading_rad)]),
        np.array([target.y_km + shift * np.sin(target.heading_rad)]),
        cfg.delta_0_km,
        grid,
    )


def normalised(mass: np.ndarray) -> np.ndarray:
    """Eq 16: divide by the total so the map sums to one."""
    return mass / mass.sum()


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


class SquareStencil:
    """Convolution of N maps (N, nx, ny) with a 3x3 kernel of the square's symmetry
    (``has_square_symmetry``), edges reflected, in place: a 9-point stencil on an edge-padded
    copy, in the maps' dtype, with work buffers kept between calls (each step's forecast would
    otherwise allocate, and fault in, several map-sized temporaries)."""

    def __init__(self, shape: tuple[int, int, int], dtype: np.dtype) -> None:
        n, nx, ny = shape
        self.padded = np.empty((n, nx + 2, ny + 2), dtype=dtype)
        self.vertical = np.empty((n, nx, ny + 2), dtype=dtype)
        self.out = np.empty(shape, dtype=dtype)
        self.work = np.empty(shape, dtype=dtype)

    def apply(
        self, maps: np.ndarray, kernel: np.ndarray, box: tuple[int, int, int, int] | None = None
    ) -> None:
        """Replace ``maps`` by its convolution with ``kernel``. With ``box = (x0, x1, y0, y1)``
        the caller promises every cell outside ``[x0, x1) x [y0, y1)`` is zero: only the box
        grown by one cell (all the kernel can reach) is computed."""
        n, nx, ny = maps.shape
        x0, x1, y0, y1 = grow_box((0, nx, 0, ny) if box is None else box, nx, ny)
        a, b = x1 - x0, y1 - y0
        centre, edge, corner = float(kernel[1, 1]), float(kernel[0, 1]), float(kernel[0, 0])
        p = self.padded[:, : a + 2, : b + 2]
        vertical, out, work = (
            self.vertical[:, :a, : b + 2],
            self.out[:, :a, :b],
            self.work[:, :a, :b],
        )
        region = maps[:, x0:x1, y0:y1]
        p[:, 1:-1, 1:-1] = region
        # reflected at the area's edge; elsewhere the cells beyond the grown box are zero
        p[:, 0, 1:-1] = maps[:, 0, y0:y1] if x0 == 0 else 0.0
        p[:, -1, 1:-1] = maps[:, nx - 1, y0:y1] if x1 == nx else 0.0
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
        np.add(out, work, out=region)  # the sum lands in the maps: no copy back


def grow_box(box: tuple[int, int, int, int], nx: int, ny: int) -> tuple[int, int, int, int]:
    """``box`` (x0, x1, y0, y1) grown by one cell on every side (all a 3x3 kernel can reach),
    kept inside the ``nx x ny`` area."""
    x0, x1, y0, y1 = box
    return max(x0 - 1, 0), min(x1 + 1, nx), max(y0 - 1, 0), min(y1 + 1, ny)


def tighten_box(
    maps: np.ndarray, box: tuple[int, int, int, int], negligible: np.ndarray
) -> tuple[int, int, int, int]:
    """Shrink ``box`` (x0, x1, y0, y1) of maps (N, nx, ny) past border rows and columns whose
    values all lie below ``negligible`` (N,), zeroing them: a few strips per call, so the work
    stays proportional to the box's perimeter."""
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


# ----------------------------------------------------------------------------- layers


@dataclass(frozen=True)
class LayerSpec:
    """A group of targets that share a forecast kernel (one layer of the TPM)."""

    kind: str  # one of planner.scenario.TARGET_KINDS
    target_ids: tuple[int, ...]
    mean_value: float
    speed_mps: float = 0.0
    heading_rad: float = 0.0


def layer_specs(targets: tuple[TargetSpec, ...]) -> list[LayerSpec]:
    """Group the scenario's targets into layers that move alike."""
    groups: dict[tuple, list[TargetSpec]] = {}
    for t in targets:
        if t.kind in ("unknown_position", "known_position"):
            key: tuple = (t.kind,)
        elif t.kind == "known_speed":
            key = (t.kind, t.speed_mps)
        else:
            key = (t.kind, t.id)
        groups.setdefault(key, []).append(t)
    specs = []
    for members in groups.values():
        first = members[0]
        specs.append(
            LayerSpec(
                kind=first.kind,
                target_ids=tuple(m.id for m in members),
                mean_value=float(np.mean([m.value for m in members])),
                speed_mps=first.speed_mps,
                heading_rad=first.heading_rad,
            )
        )
    return specs


def initial_layers(
    targets: tuple[TargetSpec, ...], cfg: PlannerConfig
) -> tuple[list[LayerSpec], np.ndarray]:
    """Eqs 9-16 for every target, summed into layers: ``(specs, maps (L, nx, ny))``; each
    target contributes a normalised map, so layer l sums to its number of targets."""
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    prior_of = {
        "unknown_position": lambda t: uniform_prior(grid),
        "known_position": lambda t: wiener_prior(t, cfg, grid),
        "known_speed": lambda t: ring_prior(t, cfg, grid),
        "known_velocity": lambda t: shifted_prior(t, cfg, grid),
    }
    by_id = {t.id: t for t in targets}
    specs = layer_specs(targets)
    maps = np.zeros((len(specs), grid.nx, grid.ny))
    for index, spec in enumerate(specs):
        for tid in spec.target_ids:
            maps[index] += normalised(prior_of[spec.kind](by_id[tid]))
    return specs, maps


def existence_of_layers(maps: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Target existence probability ``p_mn = 1 - prod_layers (1 - layer_mn)`` of one UAV's
    stored layers ``maps`` (L, nx, ny) with their scale (L,) (see the module docstring)."""
    layers = maps.astype(np.float64) * np.asarray(scale)[:, None, None]
    return 1.0 - np.prod(1.0 - np.clip(layers, 0.0, 1.0), axis=0)


class TargetProbabilityMaps:
    """The TPMs of the whole swarm: layer l of UAV i's map is ``maps[l, i] * scale[l, i]``.

    The maps are stored in float32 with a per-(layer, UAV) scale, so eq 16's renormalisation is
    a change of ``scale`` (the forecast kernels conserve mass) rather than a pass over every
    cell; ``totals`` tracks each stored map's sum and is recomputed exactly every
    ``RESUM_PERIOD`` steps.
    """

    RESUM_PERIOD = 25
    #: Expected targets in a cell below which a known-speed layer's cell is set to zero, so its
    #: forecast only touches the box where the target can be (docs/parameters.md).
    NEGLIGIBLE = 1e-9

    def __init__(self, targets: tuple[TargetSpec, ...], cfg: PlannerConfig, n_uavs: int) -> None:
        self.cfg = cfg
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        self.specs, prior = initial_layers(targets, cfg)
        self.maps = np.repeat(prior[:, None, :, :], n_uavs, axis=1).astype(np.float32)
        # Targets of each layer still at large, as each UAV believes (L, N).
        self.counts = np.repeat(
            np.array([len(s.target_ids) for s in self.specs], float)[:, None], n_uavs, axis=1
        )
        self.totals = self.maps.sum(axis=(2, 3), dtype=np.float64)
        self.scale = np.ones_like(self.totals)
        self.renormalise()
        self.layer_of_target = {tid: l for l, s in enumerate(self.specs) for tid in s.target_ids}
        self.layer_values = np.array([s.mean_value for s in self.specs])
        self.steps = 0
        self._build_forecast()

    # -------------------------------------------------------------- forecast (eqs 19-22)

    def _build_forecast(self) -> None:
        cfg = self.cfg
        dt = cfg.step_s
        self.wiener_1d = wiener_kernel_1d(cfg.delta_e_km_per_sqrt_s * np.sqrt(dt) / cfg.cell_km)
        self.ring_kernels: dict[int, np.ndarray] = {}
        self.ring_symmetric: dict[int, bool] = {}
        self.ring_box: dict[int, tuple[int, int, int, int]] = {}
        self.stencil = SquareStencil(self.maps.shape[1:], self.maps.dtype)
        self.work = np.empty(self.maps.shape[1:], dtype=self.maps.dtype)  # one layer's maps
        self.wiener_work = np.empty_like(self.work)
        self.ratio_lookup = np.ones(self.maps.shape[1] * self.grid.size)  # drifted_ratio's
        self.shift_rate = np.zeros((len(self.specs), 2))  # cells per step
        self.wiener_layers = [l for l, s in enumerate(self.specs) if s.kind == "known_position"]
        self.drift_layers = np.array(
            [l for l, s in enumerate(self.specs) if s.kind == "known_velocity"], dtype=np.int64
        )
        self.shift_accum = np.zeros((len(self.specs), 2))
        for l, spec in enumerate(self.specs):
            step_cells = spec.speed_mps / 1000.0 * dt / cfg.cell_km
            if spec.kind == "known_speed":
                self.ring_kernels[l] = ring_kernel(step_cells)
                self.ring_symmetric[l] = has_square_symmetry(self.ring_kernels[l])
                if self.ring_symmetric[l]:
                    self.ring_box[l] = self._support_box(l)
            elif spec.kind == "known_velocity":
                self.shift_rate[l] = step_cells * np.array(
                    [np.cos(spec.heading_rad), np.sin(spec.heading_rad)]
                )

    def _negligible_stored(self) -> np.ndarray:
        """Per layer and UAV (L, N), the stored value below which a cell holds fewer than
        ``NEGLIGIBLE`` expected targets."""
        return np.divide(self.NEGLIGIBLE, self.scale, out=np.full(self.scale.shape, np.inf),
                         where=self.scale > 0).astype(np.float32)  # fmt: skip

    def _support_box(self, layer: int) -> tuple[int, int, int, int]:
        """Zero the negligible cells of a layer and return the box holding the rest."""
        maps = self.maps[layer]
        maps[maps < self._negligible_stored()[layer][:, None, None]] = 0.0
        xs = np.flatnonzero(maps.any(axis=(0, 2)))
        ys = np.flatnonzero(maps.any(axis=(0, 1)))
        if xs.size == 0:
            return 0, 1, 0, 1
        return int(xs[0]), int(xs[-1]) + 1, int(ys[0]), int(ys[-1]) + 1

    def forecast(self) -> None:
        """Propagate every UAV's map over one decision period (eq 19 with the kernels of eqs
        20-22); the ``reflect`` boundary keeps the mass of targets bouncing off the edge."""
        self._wiener_forecast(self.wiener_layers)
        self._move_layers()
        self.steps += 1
        if self.steps % self.RESUM_PERIOD == 0:
            self.totals = self.maps.sum(axis=(2, 3), dtype=np.float64)
            self.renormalise()

    def _wiener_forecast(self, layers: list[int]) -> None:
        """Eq 20 on ``layers``: separable, along x into a work buffer, then along y in place."""
        for l in layers:
            layer = self.maps[l]
            ndimage.convolve1d(
                layer, self.wiener_1d, axis=1, mode="reflect", output=self.wiener_work
            )
            ndimage.convolve1d(
                self.wiener_work, self.wiener_1d, axis=2, mode="reflect", output=layer
            )

    def _move_layers(self) -> None:
        """Eqs 21-22 on the known-speed and known-velocity layers."""
        negligible = None
        for l, spec in enumerate(self.specs):
            layer = self.maps[l]
            if spec.kind == "known_speed":
                if self.ring_symmetric[l]:
                    self.stencil.apply(layer, self.ring_kernels[l], self.ring_box[l])
                    grown = grow_box(self.ring_box[l], self.grid.nx, self.grid.ny)
                    if negligible is None:  # the scales do not change during the forecast
                        negligible = self._negligible_stored()
                    self.ring_box[l] = tighten_box(layer, grown, negligible[l])
                else:
                    self.maps[l] = convolve_reflect(layer, self.ring_kernels[l])
            elif spec.kind == "known_velocity":
                # Exact sub-cell bookkeeping: move whole cells once the drift reaches half a cell,
                # so the map is not blurred by repeated interpolation; the part of a cell left
                # (shift_accum) is where looks read the targets (drifted_ratio).
                self.shift_accum[l] += self.shift_rate[l]
                whole = np.rint(self.shift_accum[l]).astype(int)
                if whole.any():
                    self.shift_accum[l] -= whole
                    for axis, cells in ((1, int(whole[0])), (2, int(whole[1]))):
                        if cells:
                            shift_with_reflection(layer, cells, axis, out=self.work)
                            layer[...] = self.work
            # unknown_position targets are stationary; known_position: _wiener_forecast.

    # -------------------------------------------------------------- probe update (eqs 17-18)

    def apply_looks(
        self,
        receivers: np.ndarray,
        look_cells: list[np.ndarray],
        look_detected: list[np.ndarray],
        look_origin_cells: np.ndarray,
    ) -> None:
        """Apply looks to the receiving UAVs' maps with eq 18 (detection probability from eq 17).

        Look m goes to UAV ``receivers[m]``, covers ``look_cells[m]`` (K_m, 2) with bits
        ``look_detected[m]`` and was taken from ``look_origin_cells[m]``. A UAV may receive
        several looks: the likelihood ratios of all looks at one of its cells are multiplied
        and applied once, which equals applying eq 18 look by look.
        """
        if len(receivers) == 0:
            return
        cfg, grid = self.cfg, self.grid
        sizes = np.array([len(c) for c in look_cells])
        cells = np.concatenate(look_cells)
        detected = np.concatenate(look_detected).astype(bool)
        uav = np.repeat(np.asarray(receivers), sizes)
        origin = np.repeat(np.asarray(look_origin_cells), sizes, axis=0)
        distance = np.hypot(*((cells - origin) * grid.cell_km).T)
        ratio = likelihood_ratio(
            detected, detection_probability(distance, cfg), cfg.cell_false_alarm
        )
        keys, where = np.unique(uav * grid.size + grid.flat(cells), return_inverse=True)
        with np.errstate(divide="ignore"):
            log_ratio = np.bincount(where.ravel(), weights=np.log(ratio), minlength=len(keys))
        uav = keys // grid.size
        view = self.maps.reshape(len(self.specs), -1)  # (L, N * cells): keys index it directly
        scale = self.scale[:, uav]  # (L, P)
        stored_before = view[:, keys]
        cell_ratio = np.exp(log_ratio)
        ratio = np.broadcast_to(cell_ratio[None, :], stored_before.shape)
        drifting = self.drift_layers[(self.shift_accum[self.drift_layers] != 0).any(axis=1)]
        if drifting.size:  # known-velocity layers a part of a cell beside their targets
            ratio = ratio.copy()
            ratio[drifting] = drifted_ratio(
                keys, cell_ratio, self.shift_accum[drifting], grid, self.ratio_lookup
            )
        updated = posterior(stored_before * scale, ratio)
        if (self.scale > 0).all():  # the usual case: no layer is empty, no zero scale to skip
            stored = (updated / scale).astype(np.float32)
        else:
            stored = np.divide(updated, scale, out=np.zeros_like(updated), where=scale > 0)
            stored = stored.astype(np.float32)
        view[:, keys] = stored
        change = stored.astype(np.float64) - stored_before
        # keys are sorted, so each UAV's cells are one run: sum the runs
        first = np.flatnonzero(np.concatenate(([True], uav[1:] != uav[:-1])))
        self.totals[:, uav[first]] += np.add.reduceat(change, first, axis=1)

    def decay_unobserved(self, observed: np.ndarray) -> None:
        """Eq 18, first case: cells no UAV looked at this step are multiplied by tau.
        ``observed`` is (N, nx, ny) bool."""
        if self.cfg.tpm_decay_tau < 1.0:
            self.maps *= np.where(observed[None], 1.0, self.cfg.tpm_decay_tau).astype(np.float32)
            self.totals = self.maps.sum(axis=(2, 3), dtype=np.float64)

    def renormalise(self) -> None:
        """Eq 16: scale every layer of every UAV to its count of targets at large."""
        self.scale = np.divide(
            self.counts, self.totals, out=np.zeros_like(self.totals), where=self.totals > 0
        )

    # -------------------------------------------------------------- reading the maps

    def existence_at(self, uavs: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """Target existence probability p_mn as UAV ``uavs`` believes it, at ``cells`` (..., 2);
        ``uavs`` broadcasts against ``cells.shape[:-1]`` (e.g. (N, 1) with (N, K, 2)). Cells
        outside the area read 0."""
        grid = self.grid
        uavs = np.asarray(uavs)
        # one flat index into (L, N * cells): UAV and cell together
        index = uavs * grid.size + grid.clipped_flat(cells)
        layers = self.maps.reshape(len(self.specs), -1)[:, index] * self.scale[:, uavs]
        np.maximum(layers, 0.0, out=layers)  # clip to [0, 1]
        np.minimum(layers, 1.0, out=layers)
        existence = 1.0 - np.prod(1.0 - layers, axis=0)
        return np.where(grid.inside(cells), existence, 0.0)

    def values_at(self, uavs: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """Expected value of a target in each cell (the layers' masses weighting their mean values)
        for (UAV, cell) pairs: ``uavs`` (M,), ``cells`` (M, 2) inside the area."""
        flat = self.grid.flat(cells)
        view = self.maps.reshape(len(self.specs), -1, self.grid.size)
        masses = view[:, uavs, flat] * self.scale[:, uavs]  # (L, M)
        total = masses.sum(axis=0)
        weighted = self.layer_values @ masses
        return np.divide(weighted, total, out=np.zeros_like(weighted), where=total > 0)

    def existence_map(self, uav: int) -> np.ndarray:
        """The whole existence-probability map of one UAV (for figures and tests)."""
        return existence_of_layers(self.maps[:, uav], self.scale[:, uav])

    def layer_map(self, layer: int, uav: int) -> np.ndarray:
        """Expected number of layer ``layer``'s targets in each cell, as UAV ``uav`` believes."""
        return self.maps[layer, uav].astype(np.float64) * self.scale[layer, uav]

    def remove_target(
        self, uav: int, target_id: int, cell: np.ndarray, radius_cells: int = 2
    ) -> None:
        """A UAV learns that a target was serviced at ``cell``: its layer loses one target and the
        mass around the cell, and is renormalised."""
        l = self.layer_of_target.get(target_id)
        if l is None or self.counts[l, uav] <= 0:
            return
        self.counts[l, uav] -= 1
        x0, y0 = max(cell[0] - radius_cells, 0), max(cell[1] - radius_cells, 0)
        self.maps[l, uav, x0 : cell[0] + radius_cells + 1, y0 : cell[1] + radius_cells + 1] = 0.0
        if self.counts[l, uav] <= 0:
            self.maps[l, uav] = 0.0
        self.totals[l, uav] = self.maps[l, uav].sum(dtype=np.float64)
        self.renormalise()
