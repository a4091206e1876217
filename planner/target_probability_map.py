"""Target probability maps (TPM, section 3.1): initialisation (eqs 9-16), probe update (eqs 17-18)
and forecast update (eqs 19-22), kept per UAV and batched across the swarm.

How several targets share one map (the paper is silent): the map is split into *layers*, one
per group of targets that move under the same forecast kernel (``planner.target_priors``: all
unknown-position targets; all known-position targets; known-speed targets of one speed; each
known-velocity target). The priors are ``planner.target_priors``'s, the motion kernels
``planner.motion_forecast``'s. A layer holds the expected number of its targets in each
cell, so it sums to the number of its targets still at large. Eq 18 is applied cell by cell
to each layer, each layer is renormalised to its count (eq 16), and the cell's target
existence probability ``p_mn`` used by the rest of the planner is
``1 - prod_layers (1 - layer_mn)``.

Arrays are ``(L, N, nx, ny)``: layer, UAV, cell. Each UAV owns its slice (its own beliefs).

Symbols: delta_0 -> ``cfg.delta_0_km``; delta_e -> ``cfg.delta_e_km_per_sqrt_s``; t_0 ->
``cfg.t0_s``; tau -> ``cfg.tpm_decay_tau``; Delta t -> ``cfg.step_s``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from planner.config import PlannerConfig
from planner.grid import Grid
from planner.motion_forecast import (
    SquareStencil,
    convolve_reflect,
    drifted_ratio,
    grow_boxes,
    has_square_symmetry,
    ring_kernel,
    shift_with_reflection,
    tighten_boxes,
    wiener_kernel_1d,
)
from planner.scenario import TargetSpec
from planner.sensor_model import detection_probability, likelihood_ratio, posterior
from planner.target_priors import initial_layers

#: Quadrature sizes for the ring integrals and the cell-to-cell motion kernels.
RING_ANGLES = 128
CELL_SAMPLES = 16



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
        # per known-speed layer, each UAV's box (N, 4: x0, x1, y0, y1) outside which its map is 0
        self.ring_box: dict[int, np.ndarray] = {}
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

    def _support_box(self, layer: int) -> np.ndarray:
        """Zero the negligible cells of a layer and return, per UAV, the box (N, 4: x0, x1,
        y0, y1) holding the rest of its map (each UAV's from its own map alone)."""
        maps = self.maps[layer]
        maps[maps < self._negligible_stored()[layer][:, None, None]] = 0.0
        boxes = np.tile(np.array([0, 1, 0, 1], dtype=np.int64), (len(maps), 1))
        for i, own in enumerate(maps):
            xs = np.flatnonzero(own.any(axis=1))
            ys = np.flatnonzero(own.any(axis=0))
            if xs.size:
                boxes[i] = xs[0], xs[-1] + 1, ys[0], ys[-1] + 1
        return boxes

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
        """Eq 20 on ``layers``: separable, along x into a work buffer, then along y in place,
        over the box of the cells that hold belief in any UAV's map grown by twice the kernel's
        reach (``wiener_box``; none: nothing to spread)."""
        for l in layers:
            layer = self.maps[l]
            box = wiener_box(layer, len(self.wiener_1d) // 2)
            if box is None:
                continue
            x0, x1, y0, y1 = box
            held = layer[:, x0:x1, y0:y1]
            work = self.wiener_work[:, : x1 - x0, : y1 - y0]
            ndimage.convolve1d(held, self.wiener_1d, axis=1, mode="reflect", output=work)
            ndimage.convolve1d(work, self.wiener_1d, axis=2, mode="reflect", output=held)

    def _move_layers(self) -> None:
        """Eqs 21-22 on the known-speed and known-velocity layers."""
        negligible = None
        for l, spec in enumerate(self.specs):
            layer = self.maps[l]
            if spec.kind == "known_speed":
                if self.ring_symmetric[l]:
                    # a few maps at a time over their boxes' union: a map is zero outside its
                    # own box, so each UAV's cells come out as they would from its own box
                    boxes = self.ring_box[l]
                    # the maps alike in their sums are compared: equal maps stencilled once
                    self.stencil.apply(
                        layer, self.ring_kernels[l], boxes=boxes, alike=self.totals[l]
                    )
                    grown = grow_boxes(boxes, self.grid.nx, self.grid.ny)
                    if negligible is None:  # the scales do not change during the forecast
                        negligible = self._negligible_stored()
                    self.ring_box[l] = tighten_boxes(layer, grown, negligible[l])
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


def wiener_box(layer: np.ndarray, reach: int) -> tuple[int, int, int, int] | None:
    """The box (x0, x1, y0, y1) of ``layer`` (N, nx, ny) over which a separable convolution of
    ``reach`` cells either side, edges reflected, gives every cell of the area what it gives
    over the whole area: the cells holding belief in any map grown by twice ``reach``, kept
    inside the area. A cell within ``reach`` of them reads only cells of the box (or, at the
    area's edge, the reflection the whole area makes too); every other cell is zero, over the
    whole area as inside the box, where what the box's own edge reflects is zero. None when
    no cell holds belief (the whole area stays zero). On 200 x 200 cells the known-position
    layer holds belief over about half the area in a 40-step run; paper-20uav's is all zero
    once its targets are engaged."""
    held = layer.any(axis=0)
    xs = np.flatnonzero(held.any(axis=1))
    if not xs.size:
        return None
    ys = np.flatnonzero(held.any(axis=0))
    nx, ny = held.shape
    grow = 2 * reach
    return (max(int(xs[0]) - grow, 0), min(int(xs[-1]) + 1 + grow, nx),
            max(int(ys[0]) - grow, 0), min(int(ys[-1]) + 1 + grow, ny))  # fmt: skip
