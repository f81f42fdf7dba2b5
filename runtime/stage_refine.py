"""Refiner stage: the candidates' poses refined on their boxes' depth, each with its own pallet type's boards
and blocks, all candidates of a frame at once (`refine.refine_batch`).

Per candidate: robust point-to-plane ICP from the network's pose; its pose replaces the network's only when
the depth is clean enough for ICP to be trusted (`refine_max_rms_m`) and it fits the depth at least as well
(`refine_margin`). Then ICP from the type's starts around the pose so far; a trusted landing that explains
the box's depth better at a tight tolerance replaces it.
"""
from __future__ import annotations

import logging
import time

import numpy as np

from . import kernels
from .candidates import Candidates
from .deadline import Deadline, elapsed_ms
from .fit import fit_scores
from .geometry import backproject_pixels
from .refine import RefineGeometry, RefineOptions, refine_batch
from .stage_geometry import PalletGeometry

__all__ = ["RefinerStage", "fit_array"]

log = logging.getLogger(__name__)


def fit_array(fit) -> np.ndarray:
    """(3,) inlier fraction, free-space violation, score of a `FitScore`."""
    return np.array([fit.inlier_fraction, fit.free_space_violation, fit.score])


class RefinerStage:
    """ICP refinement of the candidates' poses.

    :param geometries: the pallet types (a candidate's `type_index` points into them); a type without
        `boxes_m` is not refined.
    :param options: `EstimatorOptions` (the `refine*` and `fit_tol_m` fields).
    :param threads: threads of the compiled kernels (the estimator's `threads`).

    :ivar budget_chunk: under a time budget, candidates are refined this many at a time, highest score first,
        and the budget is checked before each group (1: the tightest bound, at the cost of batching).
    """

    def __init__(self, geometries: tuple[PalletGeometry, ...], options, threads: int = 1) -> None:
        self.geometries = tuple(geometries)
        self.options = o = options
        on = bool(o.refine and o.refine_iterations > 0)
        for g in self.geometries:
            if o.refine and g.boxes_m is None:
                log.warning("pallet type %s has no pallet boxes_m in the bundle: its poses are not refined", g.name)
        # one RefineGeometry per type, built once: refine_batch refines the candidates of one object together
        self._refine_geometry = tuple(
            RefineGeometry(g.points_m, g.boxes_m, g.refine_starts[:o.refine_starts]) if on and g.boxes_m is not None
            else None for g in self.geometries)
        self.refine_options = RefineOptions(
            iterations=o.refine_iterations, max_rms_m=o.refine_max_rms_m, margin=o.refine_margin,
            fit_tol_m=o.fit_tol_m, start_points=o.refine_start_points, select_tol_m=o.refine_select_tol_m,
            start_max_rms_m=o.refine_start_max_rms_m, threads=max(int(threads), 1))
        self.budget_chunk = 2
        if on and not kernels.available():
            log.warning("the compiled kernels are not built (no C compiler when pallet6d was installed): "
                        "refinement runs in numpy, several times slower")
        elif on:
            for g in self._refine_geometry:         # the kernel's box grids now, not on the first frame
                if g is not None:
                    g.icp_grid()

    @property
    def refines_type(self) -> tuple[bool, ...]:
        """Per pallet type: whether its candidates are refined."""
        return tuple(g is not None for g in self._refine_geometry)

    def icp_grids(self, type_index) -> list:
        """Per pallet type index: the compiled ICP's `kernels.box_grid` of its boards (built at construction), or
        None where the type is not refined or the kernel cannot take its boxes."""
        geoms = [self._refine_geometry[int(j)] for j in type_index]
        return [None if g is None else g.icp_grid() for g in geoms]

    @property
    def enabled(self) -> bool:
        """Whether any pallet type is refined."""
        return any(self.refines_type)

    def box_points(self, pixels: tuple[np.ndarray, np.ndarray], depth_m: np.ndarray, K: np.ndarray,
                   max_points: int | None = None) -> np.ndarray:
        """A box's depth points for ICP: its candidate pixels (v, u), thinned by an even stride to at most
        `max_points` (default `refine_points`), back-projected. :return: (m, 3) float32 camera frame, metres."""
        v, u = pixels
        n = self.options.refine_points if max_points is None else int(max_points)
        if len(v) > n:
            keep = np.linspace(0, len(v) - 1, n).round().astype(np.int64)
            v, u = v[keep], u[keep]
        return backproject_pixels(u, v, depth_m[v, u], K)

    def fit(self, T_cam_pallet: np.ndarray, obs_cam: np.ndarray, type_index: np.ndarray, depth_m: np.ndarray,
            K: np.ndarray) -> np.ndarray:
        """The fit of n poses of refined types, as `refine` reports it for its own poses.

        :param T_cam_pallet: (n, 4, 4). :param obs_cam: (n, N, 3) each pose's sampled points, camera frame, metres.
        :param type_index: (n,) pallet type of each pose. :return: (n, 3) inlier fraction, free-space violation,
            score."""
        type_index = np.asarray(type_index, np.int64)
        out = np.full((len(type_index), 3), np.nan)
        o = self.refine_options
        for j in np.unique(type_index):
            g = self._refine_geometry[int(j)]
            if g is None:
                raise ValueError(f"fit: pallet type {int(j)} is not refined (no boxes_m, or refinement is off)")
            m = type_index == j
            out[m] = np.stack(fit_scores(T_cam_pallet[m], obs_cam[m], None, g.model_points_m, depth_m, K, o.fit_tol_m,
                                         points_in_boxes_m=g.in_boxes, point_index=g.point_index(o.fit_tol_m),
                                         compiled=o.compiled), 1)
        return out

    def refine(self, T_net: np.ndarray, obs_cam: np.ndarray, box_obs_cam: list[np.ndarray], type_index: np.ndarray,
               depth_m: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Refined poses of n candidates of refined types, all at once (`refine_batch`).

        :param T_net: (n, 4, 4) the network's poses. :param obs_cam: (n, N, 3) each candidate's sampled points
            (the fit score's), camera frame, metres. :param box_obs_cam: n (m_i, 3) depth points for ICP.
        :param type_index: (n,) pallet type of each candidate. :param depth_m: (H, W) metres. :param K: (3, 3).
        :return: T_cam_pallet (n, 4, 4), and the fit (inlier fraction, free-space violation, score) of each
            returned pose, (n, 3).
        """
        geometries = [self._refine_geometry[int(j)] for j in type_index]
        if any(g is None for g in geometries):
            raise ValueError("refine: a candidate's pallet type is not refined (no boxes_m, or refinement is off)")
        if len(geometries) == 0:
            return np.zeros((0, 4, 4)), np.zeros((0, 3))
        res = refine_batch(T_net, obs_cam, box_obs_cam, geometries, depth_m, K, self.refine_options)
        return res.T_cam_pallet, np.array([fit_array(f) for f in res.fits]).reshape(-1, 3)

    def __call__(self, cands: Candidates, depth_m: np.ndarray, K: np.ndarray, timings: dict[str, float],
                 deadline: Deadline | None = None) -> None:
        """The stage on the alive rows of `cands` of refined types: sets `T_cam_pallet` and `fit` where computed.
        Under a time budget the rows go `budget_chunk` at a time, highest score first; those left when it
        expires are rejected ("time_budget"). Rows refined already (their `fit` set, by the type choice) keep
        their pose."""
        t = time.perf_counter()
        rows = np.flatnonzero(cands.alive & np.asarray(self.refines_type, bool)[cands.type_index]
                              & np.isnan(cands.fit[:, 2]))
        step = self.budget_chunk if deadline is not None and deadline.budget_ms is not None else max(len(rows), 1)
        chunks = [rows[k:k + step] for k in range(0, len(rows), step)]
        for c, idx in enumerate(chunks):
            if deadline is not None and deadline.expired():
                cands.reject(np.concatenate(chunks[c:]), "time_budget",
                             "the frame's time budget was spent before this pallet was refined")
                break
            box_obs = [self.box_points(cands.pixels[i], depth_m, K) for i in idx]
            T, fit = self.refine(cands.T_net[idx], cands.points_cam[idx], box_obs, cands.type_index[idx], depth_m, K)
            cands.assign(idx, T_cam_pallet=T, fit=fit)
        timings["refine"] = timings.get("refine", 0.0) + elapsed_ms(t)
