"""Refiner stage: each candidate's pose refined on its box's depth, with its own pallet type's boards and blocks.

Per candidate (`refine.py`): robust point-to-plane ICP from the network's pose; its pose replaces the
network's only when the depth is clean enough for ICP to be trusted (`refine_max_rms_m`) and it fits the
depth at least as well (`refine_margin`). Then ICP from starts around the pose so far; a trusted landing that
explains the box's depth better at a tight tolerance replaces it (`best_landing`).
"""
from __future__ import annotations

import logging
import time

import numpy as np

from .candidates import Candidates
from .deadline import Deadline, elapsed_ms
from .fit import fit_score
from .geometry import backproject_pixels
from .stage_geometry import PalletGeometry
from .refine import best_landing, refine_pose

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
    :param depth_range_m: (min, max) depth of a pixel used for refinement, metres (the pose inputs' range).
    """

    def __init__(self, geometries: tuple[PalletGeometry, ...], options, depth_range_m: tuple[float, float]) -> None:
        self.geometries = tuple(geometries)
        self.options = o = options
        self.depth_range_m = tuple(depth_range_m)
        on = bool(o.refine and o.refine_iterations > 0)
        self.refines_type = tuple(on and g.boxes_m is not None for g in self.geometries)
        for g in self.geometries:
            if o.refine and g.boxes_m is None:
                log.warning("pallet type %s has no pallet boxes_m in the bundle: its poses are not refined", g.name)

    @property
    def enabled(self) -> bool:
        """Whether any pallet type is refined."""
        return any(self.refines_type)

    def box_points(self, pixels: tuple[np.ndarray, np.ndarray], depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
        """A box's depth points for ICP: its candidate pixels (v, u), thinned by an even stride to at most
        `refine_points`, back-projected. :return: (m, 3) float32 camera frame, metres."""
        v, u = pixels
        if len(v) > self.options.refine_points:
            keep = np.linspace(0, len(v) - 1, self.options.refine_points).round().astype(np.int64)
            v, u = v[keep], u[keep]
        return backproject_pixels(u, v, depth_m[v, u], K)

    def refine(self, T_net: np.ndarray, obs_cam: np.ndarray, box_obs_cam: list[np.ndarray], type_index: np.ndarray,
               depth_m: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Refined poses of n candidates.

        :param T_net: (n, 4, 4) the network's poses. :param obs_cam: (n, N, 3) each candidate's sampled points
            (the fit score's), camera frame, metres. :param box_obs_cam: n (m_i, 3) depth points for ICP.
        :param type_index: (n,) pallet type of each candidate. :param depth_m: (H, W) metres. :param K: (3, 3).
        :return: T_cam_pallet (n, 4, 4), and the fit (inlier fraction, free-space violation, score) of each
            returned pose where it was computed on the way, NaN where not.
        """
        T = np.array(T_net, dtype=np.float64, copy=True)
        fit = np.full((len(T), 3), np.nan)
        for k in range(len(T)):
            if self.refines_type[int(type_index[k])]:
                T[k], fit[k] = self._refine_one(T[k], obs_cam[k], box_obs_cam[k], self.geometries[int(type_index[k])],
                                                depth_m, K)
        return T, fit

    def _refine_one(self, T_net: np.ndarray, obs_cam: np.ndarray, box_obs_cam: np.ndarray, g: PalletGeometry,
                    depth_m: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        o = self.options
        T, fit = T_net, np.full(3, np.nan)
        res = refine_pose(T_net, box_obs_cam, g.boxes_m, iterations=o.refine_iterations)
        # noisy depth pulls ICP off: its residual tells whether the depth is clean enough to trust it, and
        # then it must explain the depth at least as well as the network's pose
        if np.isfinite(res.rms_m) and res.rms_m < o.refine_max_rms_m:
            fit_icp = fit_score(res.T_cam_pallet, obs_cam, g.points_m, depth_m, K, o.fit_tol_m)
            fit_net = fit_score(T_net, obs_cam, g.points_m, depth_m, K, o.fit_tol_m)
            keep_icp = fit_icp.score >= fit_net.score + o.refine_margin
            T, fit = (res.T_cam_pallet, fit_array(fit_icp)) if keep_icp else (T_net, fit_array(fit_net))
        if o.refine_starts > 0:
            # the network's larger errors lie outside ICP's basin: ICP from starts around the pose, and a
            # trusted landing that explains the depth better at a tight tolerance replaces it
            T_best, j = best_landing(T, box_obs_cam, g.boxes_m, o.refine_starts, o.refine_start_points,
                                     lambda T_: fit_score(T_, box_obs_cam, g.points_m, depth_m, K,
                                                          o.refine_select_tol_m, g.boxes_m).score,
                                     o.refine_start_max_rms_m, o.refine_iterations)
            if j >= 0:
                T, fit = T_best, np.full(3, np.nan)
        return T, fit

    def __call__(self, cands: Candidates, depth_m: np.ndarray, K: np.ndarray, timings: dict[str, float],
                 deadline: Deadline | None = None) -> None:
        """The stage on the alive rows of `cands` of refined types: sets `T_cam_pallet` and `fit` where computed.
        With a deadline the rows go one at a time, highest score first; those left when it expires are
        rejected ("time_budget")."""
        t = time.perf_counter()
        rows = np.flatnonzero(cands.alive & np.asarray(self.refines_type, bool)[cands.type_index]) \
            if len(cands) else np.zeros(0, np.int64)
        chunks = [rows[k:k + 1] for k in range(len(rows))] if deadline is not None and deadline.budget_ms is not None \
            else [rows]
        for c, idx in enumerate(chunks):
            if len(idx) == 0:
                continue
            if deadline is not None and deadline.expired():
                cands.reject(np.concatenate(chunks[c:]), "time_budget",
                             "the frame's time budget was spent before this pallet was refined")
                break
            box_obs = [self.box_points(cands.pixels[i], depth_m, K) for i in idx]
            T, fit = self.refine(cands.T_net[idx], cands.points_cam[idx], box_obs, cands.type_index[idx], depth_m, K)
            cands.assign(idx, T_cam_pallet=T, fit=fit)
        timings["refine"] = elapsed_ms(t)
