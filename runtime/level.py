"""Pallet poses on a calibrated camera's floor: levelled, set on the floor, refined in yaw and position.

Pallets stand level on floors, rack beams and truck beds. An estimate's tilt (a degree or two on stereo depth) moves
each fork pocket by centimetres, and noisy stereo depth pins down 3 or 4 degrees of freedom far better than 6. With
the camera's calibration (`T_vehicle_cam`; vehicle frame: z up, the floor at z = 0), `level_poses`:

1. levels a pose whose z axis leans at most `max_tilt_deg` from the vertical: its z axis becomes the vertical, its
   x axis the horizontal direction nearest to the estimated one, its bounding-box centre stays;
2. sets it on the floor when its underside is then within `floor_snap_m` of z = 0;
3. refines it by point-to-plane ICP (`refine._icp`) on its detection box's depth with roll and pitch held (and the
   height, on the floor): yaw and position only. All poses of one pallet type in one pass. The network's yaw is
   often 30-90 degrees off on the forklift's oblique and close views, outside ICP's reach: the ICP also starts from
   the best few of a grid of turns and slides of the pose (`search_*`), each scored by how well it explains the
   depth along the viewing rays (`ray_scores`); after step 4 the landing that scores best wins;
4. moves it along the viewing rays by the median of its points' depth residuals against the posed pallet along each
   point's own ray (the model's first surface on that ray). Stereo and ToF depth is noisy along the ray: matched to
   their closest surface, the points behind a board's front go to its sides, back or the blocks beside it while those
   in front pull the face forward, so ICP lands nearer than the pallet (by about 2.5 cm at 3-7 m on D435-like depth);
   the ray residuals are symmetric about the true surface.

`climb_poses` then lets a pose the fit check accepted climb a soft version of the ray score by small turns and slides
(and lifts, off the floor; `LevelParams.climb_*`): ICP started a few centimetres or degrees off can stop on one of a
pallet's repeated boards, which the forks' 2 cm / 1 degree cannot afford; the ray score ranks the true pose first.

A pose tilted further (on its side, upside down) is left as it is. A pose that is level already (levelled by the
estimator with this calibration) is not refined again.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .geometry import check_K, invert_T
from .pallet_geometry import asymmetric
from .structure import cast_rays_boxes

__all__ = ["LevelParams", "climb_poses", "level_in_camera", "level_poses", "ray_scores", "up_in_camera"]

# 1 sigma of the held degrees of freedom (radians, metres): held, not frozen; the free ones keep the refiner's own
_HELD = 1e-3
_FREE_ROT_RAD, _FREE_TRANS_M = 0.1, 0.1
_DEPTH_RANGE_M = (0.1, 20.0)
_CORR_START_M, _CORR_END_M = 0.08, 0.015
_MIN_INLIERS = 30
_LEVEL_TOL_DEG = 1e-4            # a pose this close to level was levelled already (float rounding: ~1e-6)
_RAY_ROUNDS = 2                  # the along-ray correction twice: the points within the window change with the pose


@dataclass(frozen=True)
class LevelParams:
    """:ivar max_tilt_deg: a pose tilted at most this much from the vertical is levelled; 0: none is. The
        structure check's own bound (`StructureParams.max_tilt_deg`, 25 degrees), so that with the defaults every
        pose it accepts in a calibrated view stands level: the network's tilt is 10 degrees or more off on some near
        and half-hidden pallets. Calibrated forklift-approach validation frames (seed 8015) 39.6 -> 40.4 % within
        5 cm (20 degrees: the same), EPAL pocket targets of a validation seed 86.7 / 79.2 -> 87.5 / 80.0 % (exact /
        D435-like depth) against 8 degrees (`docs/experiments/forklift.md`).
    :ivar floor_snap_m: a levelled pallet whose underside is within this of the floor is set on it; 0: never.
    :ivar refine_points: a levelled pose is refined on at most this many depth points of its box; 0: not refined.
    :ivar refine_iterations: its ICP steps (from the pose and from each search start); the correspondence distance
        shrinks from 8 to 1.5 cm over them. With a search on a 30-degree grid, on EPAL forklift views (40 validation
        frames, pockets within 2 cm and 1 degree, exact / D435-like depth) 72.5 / 45.0 % with 5 steps, 72.5 / 47.5 %
        with 10, and on the all-type forklift views (ground-truth boxes and types, D435-like depth) 119 / 127 of 211
        pallets within 5 cm: a start half a grid step off in yaw needs the steps (`docs/experiments/forklift.md`).
    :ivar ray_window_m: after the ICP, the pose moves along the viewing rays by the median depth residual of the
        points within this of the posed surface along their rays (step 4 of the module docstring); 0: it does not.
        Forklift views of all types, D435-like depth, ground-truth boxes and types, 40 validation frames: positions
        within 5 cm 72 -> 99 / 105 / 105 of 211 pallets at 0.1 / 0.2 / 0.3 m; exact depth 145 -> 146
        (`docs/experiments/forklift.md`).
    :ivar search_yaw_step_deg: before the ICP, a search over yaw and position (step 3 of the module docstring):
        turns by this step over a full turn (half a turn for a pallet that looks the same turned half way round);
        0: no search (the ICP from the pose alone).
    :ivar search_shifts_m: and slides of the centre by these along the pose's x and y (every pair).
    :ivar search_keep: the ICP also runs from this many of the best-scoring turns and slides.
    :ivar search_points: the turns and slides are scored on at most this many of the points (an even subset).
    :ivar search_window_m: a point within this of the posed surface along its ray supports a pose; one seen
        beyond it by as much contradicts it (`ray_scores`).
    :ivar floor_from_depth: the estimator levels on the frame's own floor where its depth shows it near the
        calibrated one and spread over at least 0.5 m each way (`floor.refine_floor`: within 2 degrees and 5 cm),
        else on the calibration's. A calibration a degree off puts a pallet 5 m ahead 9 cm off the floor it stands
        on: on the calibrated forklift-approach validation frames, within 5 cm, a calibration pitched 1 degree,
        rolled 1 degree or 3 cm high keeps 37.2 / 37.2 / 38.5 % with this (an older runtime kept 32.6-34.0 % on
        the calibration's floor). With an exact calibration the fitted floor's own error costs: 39.4 -> 39.2 %,
        EPAL pockets 86.7 / 85.0 -> 85.0 / 78.3 % (exact / D435-like depth). Off by default: for a camera whose
        calibration drifts or a truck that pitches with its load (docs/experiments/forklift.md).
    :ivar climb_step_deg, climb_step_m: an accepted levelled pose climbs the soft ray score (`climb_poses`;
        `ray_scores(soft=True)` on all its points, window `climb_window_m`): it moves to the best of its 26
        neighbours (turned by +-step, slid by +-step along its x and y, and every combination; a pallet not set on
        the floor also raised and lowered by +-step, as nothing else holds its height) while that scores
        higher, else halves both steps, until the turn's step is below `climb_min_step_deg` or `climb_max_moves`
        moves were made, never further than `climb_max_turn_deg` and `climb_max_shift_m` from the pose the fit
        check judged, and only for pallets within `climb_max_range_m` of the camera (farther, stereo depth noise of
        several centimetres moves the score's peak as much as it corrects: forklift-approach test pallets at 5-7 m
        lost as many as they gained). EPAL forklift targets within 2 cm and 1 degree, exact / D435-like depth:
        76.7 / 73.3 -> 83.3 / 83.3 % (`docs/experiments/forklift.md`); the targets off the floor climbing in
        height too, every one posed is within 0.7 cm of its height instead of 2.2 cm, and 86.7 / 85.0 -> 88.3 /
        86.7 %. `climb_step_deg` 0: no climb.
    :ivar climb_points: the climb scores its moves on at most this many of the box's depth points (an even
        subset); 0: on the levelling's `refine_points`. A yaw a degree off moves a near pallet's face by about 1 cm
        from end to end, which the scores of 600 points hardly tell apart: on the EPAL forklift views of a
        validation seed 2000 points put 2 more of 120 targets within 2 cm and 1 degree, exact and D435-like depth
        (5000: the same on exact depth, 2 fewer on D435-like).
    """

    max_tilt_deg: float = 25.0
    floor_snap_m: float = 0.04
    refine_points: int = 600
    refine_iterations: int = 10
    ray_window_m: float = 0.2
    search_yaw_step_deg: float = 15.0
    search_shifts_m: tuple = (-0.2, -0.1, 0.0, 0.1, 0.2)
    search_keep: int = 3
    search_points: int = 150
    search_window_m: float = 0.05
    climb_step_deg: float = 2.0
    climb_step_m: float = 0.04
    climb_min_step_deg: float = 0.25
    climb_window_m: float = 0.05
    climb_max_moves: int = 20
    climb_max_turn_deg: float = 6.0
    climb_max_shift_m: float = 0.1
    climb_max_range_m: float = 4.5
    climb_points: int = 2000
    floor_from_depth: bool = False

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_tilt_deg < 90.0:
            raise ValueError(f"max_tilt_deg must be in [0, 90), got {self.max_tilt_deg}")
        if not self.floor_snap_m >= 0:
            raise ValueError(f"floor_snap_m must be >= 0, got {self.floor_snap_m}")
        if not 0.0 <= self.ray_window_m <= 1.0:
            raise ValueError(f"ray_window_m must be in [0, 1], got {self.ray_window_m}")
        if not 0.0 <= self.search_yaw_step_deg <= 180.0:
            raise ValueError(f"search_yaw_step_deg must be in [0, 180], got {self.search_yaw_step_deg}")
        sh = np.asarray(self.search_shifts_m, dtype=np.float64)
        if sh.ndim != 1 or len(sh) == 0 or not np.all(np.abs(sh) <= 1.0):
            raise ValueError(f"search_shifts_m must be a non-empty sequence of shifts within 1 m, got "
                             f"{self.search_shifts_m}")
        if int(self.search_keep) < 1 or int(self.search_points) < 1 or not 0.0 < self.search_window_m <= 1.0:
            raise ValueError(f"need search_keep >= 1, search_points >= 1 and search_window_m in (0, 1], got "
                             f"{self.search_keep}, {self.search_points}, {self.search_window_m}")
        if not (self.climb_step_deg >= 0 and self.climb_step_m >= 0 and self.climb_min_step_deg > 0
                and 0.0 < self.climb_window_m <= 1.0 and int(self.climb_max_moves) >= 0
                and self.climb_max_turn_deg >= 0 and self.climb_max_shift_m >= 0 and self.climb_max_range_m >= 0):
            raise ValueError(f"need climb_step_deg >= 0, climb_step_m >= 0, climb_min_step_deg > 0, "
                             f"climb_window_m in (0, 1], climb_max_moves, climb_max_turn_deg, climb_max_shift_m and "
                             f"climb_max_range_m >= 0, got {self.climb_step_deg}, {self.climb_step_m}, "
                             f"{self.climb_min_step_deg}, {self.climb_window_m}, {self.climb_max_moves}, "
                             f"{self.climb_max_turn_deg}, {self.climb_max_shift_m}, {self.climb_max_range_m}")
        if int(self.refine_points) < 0 or int(self.refine_iterations) < 1 or int(self.climb_points) < 0:
            raise ValueError(f"refine_points and climb_points must be >= 0 and refine_iterations >= 1, got "
                             f"{self.refine_points}, {self.climb_points}, {self.refine_iterations}")


def up_in_camera(T_vehicle_cam: np.ndarray) -> np.ndarray:
    """(3,) the vehicle's up direction in the camera frame."""
    return np.asarray(T_vehicle_cam, dtype=np.float64)[2, :3].copy()


def _level(R: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations with their z axis set to the vertical and their x axis projected to the horizontal."""
    x = np.zeros((len(R), 3))
    x[:, :2] = R[:, :2, 0]
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    out = np.zeros_like(R)
    out[:, :, 0] = x
    out[:, 0, 1], out[:, 1, 1] = -x[:, 1], x[:, 0]                     # z x x with z vertical
    out[:, 2, 2] = 1.0
    return out


def level_in_camera(T_cam_pallet: np.ndarray, T_vehicle_cam: np.ndarray, geometries: list, params: LevelParams,
                    pts_cam: list, threads: int = 1, grids: list | None = None) -> np.ndarray:
    """`level_poses` of n posed pallets, each refined on its own type's boards and depth points, as camera poses.

    :param geometries: n pallet types (`size_m` and `boxes_m` of each, e.g. `stage_geometry.PalletGeometry`).
    :param pts_cam: n arrays (m_i, 3), each pose's depth points, camera frame, metres.
    :param grids: see `level_poses`.
    :return: (n, 4, 4) T_cam_pallet.
    """
    T_vp = level_poses(T_cam_pallet, T_vehicle_cam, np.array([g.size_m[2] for g in geometries]), params,
                       [g.boxes_m for g in geometries], pts_cam=pts_cam, threads=threads, grids=grids)
    return invert_T(T_vehicle_cam) @ T_vp


def level_poses(T_cam_pallet: np.ndarray, T_vehicle_cam: np.ndarray, height_m: np.ndarray,
                params: LevelParams = LevelParams(), boxes_m: list | None = None, depth_m: np.ndarray | None = None,
                K: np.ndarray | None = None, boxes_xyxy: np.ndarray | None = None,
                pts_cam: list | None = None, threads: int = 1, grids: list | None = None) -> np.ndarray:
    """`T_vehicle_pallet` of n posed pallets, levelled, set on the floor and refined (see the module docstring).

    :param T_cam_pallet: (n, 4, 4) the estimated poses. :param T_vehicle_cam: (4, 4) from the calibration.
    :param height_m: (n,) each pallet type's height, metres.
    :param boxes_m: n arrays (k, 2, 3), each pose's type's boards and blocks (poses sharing the same array are
        refined together), or None; with `depth_m`, `K` and `boxes_xyxy` ((n, 4) detection boxes, pixels) the
        levelled poses are refined (`params.refine_points` > 0).
    :param pts_cam: n arrays (m_i, 3), each pose's depth points (camera frame, metres) when the caller has them
        already (the estimator's refiner): used instead of reading `depth_m` in `boxes_xyxy`.
    :param threads: the compiled ICP and the search's scores share their work among this many threads (the same
        poses).
    :param grids: n `kernels.box_grid`s of `boxes_m` (or None each), for the compiled ICP: fewer boxes measured per
        point, the same poses. None: none.
    :return: (n, 4, 4) vehicle frame.
    """
    T_vc = np.asarray(T_vehicle_cam, dtype=np.float64)
    T_vp = T_vc @ np.asarray(T_cam_pallet, dtype=np.float64).reshape(-1, 4, 4)
    n = len(T_vp)
    height_m = np.broadcast_to(np.asarray(height_m, dtype=np.float64), (n,))
    tilt = np.degrees(np.arccos(np.clip(T_vp[:, 2, 2], -1.0, 1.0)))
    todo = np.flatnonzero(tilt <= params.max_tilt_deg) if params.max_tilt_deg > 0 else np.zeros(0, dtype=np.int64)
    if len(todo) == 0:
        return T_vp
    already = tilt[todo] <= _LEVEL_TOL_DEG
    out = T_vp.copy()
    out[todo, :3, :3] = _level(T_vp[todo, :3, :3])
    half_h = height_m / 2
    on_floor = np.zeros(n, dtype=bool)
    if params.floor_snap_m > 0:
        on_floor[todo] = np.abs(out[todo, 2, 3] - half_h[todo]) <= params.floor_snap_m
        out[on_floor, 2, 3] = half_h[on_floor]
    refine = todo[~already]
    if params.refine_points > 0 and len(refine) and boxes_m is not None:
        if pts_cam is not None:
            pts = [_even_subset(np.asarray(pts_cam[i], dtype=np.float64).reshape(-1, 3), int(params.refine_points))
                   for i in refine]
        elif depth_m is not None and K is not None and boxes_xyxy is not None:
            from .refine import box_points          # here: refine -> results -> forklift -> this module
            K = check_K(K)
            boxes_xyxy = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
            pts = [box_points(depth_m, K, boxes_xyxy[i], int(params.refine_points), _DEPTH_RANGE_M) for i in refine]
        else:
            return out
        out[refine] = _refine(out[refine], on_floor[refine], T_vc, [boxes_m[i] for i in refine], pts, params,
                              threads, None if grids is None else [grids[i] for i in refine])
        out[refine, :3, :3] = _level(out[refine, :3, :3])             # what the held tilt let through (< 0.1 deg)
        snap = refine[on_floor[refine]]
        out[snap, 2, 3] = half_h[snap]
    return out


def _even_subset(pts: np.ndarray, n: int) -> np.ndarray:
    """At most n of the (m, 3) points, an even stride over them (all when m <= n)."""
    if len(pts) <= n:
        return pts
    return pts[np.linspace(0, len(pts) - 1, n).round().astype(np.int64)]


def _refine(T_vp: np.ndarray, on_floor: np.ndarray, T_vc: np.ndarray, boxes_m: list, pts: list,
            params: LevelParams, threads: int = 1, grids: list | None = None) -> np.ndarray:
    """ICP with the tilt held, one pass per pallet type; poses without depth points stay."""
    from .refine import _icp          # here: refine -> results -> forklift -> this module

    out = T_vp.copy()
    T_cv = invert_T(T_vc)
    groups: dict[int, list[int]] = {}
    for i, b in enumerate(boxes_m):
        if b is not None and len(pts[i]):
            groups.setdefault(id(b), []).append(i)
    for idx in groups.values():
        counts = np.array([len(pts[i]) for i in idx])
        padded = np.zeros((len(idx), counts.max(), 3))
        for k, i in enumerate(idx):
            padded[k, :counts[k]] = pts[i]
        P = len(idx)
        T0, H = T_vp[idx], 1
        if params.search_yaw_step_deg > 0:
            T0, H = _search_starts(T_vp[idx], T_cv, [pts[i] for i in idx], boxes_m[idx[0]], params, threads)
        padded_h, counts_h, floor_h = np.repeat(padded, H, 0), np.repeat(counts, H), np.repeat(on_floor[idx], H)
        rot = np.tile([_HELD, _HELD, _FREE_ROT_RAD], (P * H, 1))
        trans = np.tile([_FREE_TRANS_M, _FREE_TRANS_M, _FREE_TRANS_M], (P * H, 1))
        trans[floor_h, 2] = _HELD                                    # pallet frame z: the vertical once levelled
        run = _icp(T_cv @ T0, padded_h, counts_h, boxes_m[idx[0]], int(params.refine_iterations), _CORR_START_M,
                   _CORR_END_M, rot, trans, _MIN_INLIERS, 1e-4, None, 0.0, threads=threads,
                   grid=None if grids is None else grids[idx[0]])
        T_cp = run.T_cam_pallet
        if params.ray_window_m > 0:
            for _ in range(_RAY_ROUNDS):
                T_cp = _along_rays(T_cp, padded_h, counts_h, boxes_m[idx[0]], params.ray_window_m, T_vc, floor_h,
                                   threads=threads)
        if H > 1:
            # the best landing of each pose (ties: the pose's own), scored after the move along the rays: a 2-3 cm
            # pull towards the camera (noisy depth) would otherwise weigh in the 5 cm window
            T_cp = T_cp.reshape(P, H, 4, 4)
            for k, i in enumerate(idx):
                sc = ray_scores(T_cp[k], pts[i], boxes_m[idx[0]], params.search_window_m)
                T_cp[k, 0] = T_cp[k, int(np.argmax(sc))]
            T_cp = T_cp[:, 0]
        out[idx] = T_vc @ T_cp
    return out


def _search_starts(T_vp: np.ndarray, T_cv: np.ndarray, pts: list, boxes_m: np.ndarray,
                   params: LevelParams, threads: int = 1) -> tuple[np.ndarray, int]:
    """ICP starts of P levelled poses: each pose, then its `search_keep` best turns and slides (step 3 of the
    module docstring). :param T_vp: (P, 4, 4) vehicle frame. :param pts: P arrays (m_i, 3), camera frame, each
    pose's points for the scores. :return: ((P * H, 4, 4) vehicle frame, pose i's starts at rows i * H .. i * H +
    H - 1; H)."""
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])                   # a pallet that looks the same turned half way round
    span = 180.0 if not asymmetric(turn[None], boxes_m) else 360.0  # needs half the turns
    yaws = np.deg2rad(np.arange(0.0, span - 1e-9, params.search_yaw_step_deg))
    sx, sy = np.meshgrid(np.asarray(params.search_shifts_m, dtype=np.float64),
                         np.asarray(params.search_shifts_m, dtype=np.float64), indexing="ij")
    a = np.repeat(yaws, sx.size)
    grid = np.tile(np.eye(4), (len(a), 1, 1))                    # pallet frame: slid, then turned about the new centre
    grid[:, 0, 0], grid[:, 0, 1], grid[:, 1, 0], grid[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    grid[:, 0, 3], grid[:, 1, 3] = np.tile(sx.ravel(), len(yaws)), np.tile(sy.ravel(), len(yaws))
    keep = min(int(params.search_keep), len(grid))
    out = np.repeat(T_vp[:, None], keep + 1, axis=1)
    for i in range(len(T_vp)):
        p = _even_subset(np.asarray(pts[i], dtype=np.float64).reshape(-1, 3), int(params.search_points))
        cand = T_vp[i] @ grid
        sc = ray_scores(T_cv @ cand, p, boxes_m, params.search_window_m, threads=threads)
        out[i, 1:] = cand[np.argsort(-sc, kind="stable")[:keep]]
    return out.reshape(-1, 4, 4), keep + 1


def _neighbours(step_rad: float, step_m: float, lift: bool = False) -> np.ndarray:
    """(26, 4, 4) pallet-frame moves: turned about z by -step, 0 or +step, slid along x and y by -step, 0 or +step,
    every combination but none at all; `lift`: (28, 4, 4), also raised and lowered by step alone."""
    a, sx, sy = (g.ravel() for g in np.meshgrid([-step_rad, 0.0, step_rad], [-step_m, 0.0, step_m],
                                                 [-step_m, 0.0, step_m], indexing="ij"))
    keep = (a != 0) | (sx != 0) | (sy != 0)
    a, sx, sy = a[keep], sx[keep], sy[keep]
    g = np.tile(np.eye(4), (len(a), 1, 1))
    g[:, 0, 0], g[:, 0, 1], g[:, 1, 0], g[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    g[:, 0, 3], g[:, 1, 3] = sx, sy
    if not lift:
        return g
    up_down = np.tile(np.eye(4), (2, 1, 1))
    up_down[:, 2, 3] = (-step_m, step_m)
    return np.concatenate([g, up_down])


def climb_poses(T_cam_pallet: np.ndarray, pts_cam: list, boxes_m: list, params: LevelParams = LevelParams(),
                threads: int = 1, lift: np.ndarray | None = None) -> np.ndarray:
    """n levelled poses after the climb of the soft ray score (`LevelParams.climb_*`; the module docstring). The
    estimator climbs the poses its fit check accepted: the climb makes a pose explain the depth better, and so must
    not decide whether it is a pallet; it stays within a few degrees and centimetres of the pose that was judged.

    :param T_cam_pallet: (n, 4, 4), each level (its z axis the vehicle's up). :param pts_cam: n arrays (m_i, 3),
        each pose's depth points (camera frame, metres). :param boxes_m: n arrays (k, 2, 3), each pose's type's
        boards and blocks, or None (that pose stays). :param threads: the scores' threads (the same poses).
    :param lift: (n,) bool: the poses that also climb up and down (pallets not set on the floor: on a rack, a stack
        or a truck bed, nothing holds their height); None: none.
    :return: (n, 4, 4) camera frame; the poses as given when `params.climb_step_deg` is 0.
    """
    T = np.array(T_cam_pallet, dtype=np.float64).reshape(-1, 4, 4)
    if params.climb_step_deg <= 0:
        return T
    lift = np.zeros(len(T), bool) if lift is None else np.asarray(lift, bool)
    for i in range(len(T)):
        if boxes_m[i] is not None and np.linalg.norm(T[i, :3, 3]) <= params.climb_max_range_m:
            T[i] = _climb_one(T[i], pts_cam[i], boxes_m[i], params, threads, bool(lift[i]))
    return T


def _climb_one(T_cam_pallet: np.ndarray, pts: np.ndarray, boxes_m: np.ndarray, params: LevelParams,
               threads: int = 1, lift: bool = False) -> np.ndarray:
    """One levelled pose's climb of the soft ray score (`LevelParams.climb_*`). :param T_cam_pallet: (4, 4).
    :param pts: (m, 3) its depth points, camera frame, metres. :return: (4, 4) the pose climbed (the same pose
    when no neighbour scores higher, or without points)."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return T_cam_pallet
    T0 = T = np.asarray(T_cam_pallet, dtype=np.float64)
    best = ray_scores(T[None], p, boxes_m, params.climb_window_m, threads=threads, soft=True)[0]
    step_deg, step_m = float(params.climb_step_deg), float(params.climb_step_m)
    cos_max = np.cos(np.deg2rad(params.climb_max_turn_deg))
    moves = 0
    while step_deg >= params.climb_min_step_deg and moves < int(params.climb_max_moves):
        cand = T @ _neighbours(np.deg2rad(step_deg), step_m, lift)
        sc = ray_scores(cand, p, boxes_m, params.climb_window_m, threads=threads, soft=True)
        far = (np.trace(T0[:3, :3].T @ cand[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0 < cos_max - 1e-12
        far |= np.linalg.norm(cand[:, :3, 3] - T0[:3, 3], axis=1) > params.climb_max_shift_m + 1e-12
        sc[far] = -np.inf
        k = int(np.argmax(sc))
        if sc[k] > best + 1e-12:
            T, best, moves = cand[k], sc[k], moves + 1
        else:
            step_deg, step_m = step_deg / 2, step_m / 2
    return T


def ray_scores(T_cam_pallet: np.ndarray, pts_cam: np.ndarray, boxes_m: np.ndarray, window_m: float,
               compiled: bool = True, threads: int = 1, soft: bool = False) -> np.ndarray:
    """How well each of P poses explains the same observed points along their viewing rays.

    A point's residual is its depth beyond the posed model's first surface on the point's own ray (the projective
    association of depth-camera trackers); the score is the fraction of points within `window_m` of the surface
    minus the fraction seen beyond it by `window_m` or more (the camera sees through where the model is solid).
    Points whose rays miss the model count neither way. `soft`: the mean of 1 - (residual / window_m)^2 over the
    points within the window instead, with no penalty beyond: it peaks at the pose that explains the depth best
    instead of being flat while the points stay within the window, and zero-mean noise along the rays pushes it
    neither nearer nor farther (a penalty on one side would push the pose away from the camera). In the compiled
    kernel, on `threads` threads, when `compiled` and the package has it (the same scores), else in numpy.

    :param T_cam_pallet: (P, 4, 4). :param pts_cam: (m, 3) camera frame, metres. :param boxes_m: (k, 2, 3) the
        pallet's boards and blocks. :return: (P,) scores in [-1, 1]; 0 for no points.
    """
    T = np.asarray(T_cam_pallet, dtype=np.float64).reshape(-1, 4, 4)
    p = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(len(T))
    if compiled and kernels.available() and len(boxes_m) <= kernels.MAX_BOXES:
        return kernels.ray_scores(T, p, boxes_m, window_m, threads, soft)
    R_pc = np.swapaxes(T[:, :3, :3], 1, 2)
    origin = -(R_pc @ T[:, :3, 3, None])[..., 0]
    s, _ = cast_rays_boxes(origin, np.einsum("nij,mj->nmi", R_pc, p), boxes_m)      # 1 = at the point
    with np.errstate(invalid="ignore"):
        res = (1.0 - s) * np.linalg.norm(p, axis=1)[None]
    hit = np.isfinite(res)
    inside = hit & (np.abs(res) < window_m)
    if soft:
        return np.sum(np.where(inside, 1.0 - (np.where(inside, res, 0.0) / window_m) ** 2, 0.0), 1) / len(p)
    return (np.sum(inside, 1) - np.sum(hit & (res >= window_m), 1)) / len(p)


def _row_medians(values: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(P,) the median of each row's `count[i]` finite values (the rest of the row is +inf), as np.median takes it."""
    v = np.sort(values, axis=1)
    rows = np.arange(len(v))
    return 0.5 * (v[rows, (count - 1) // 2] + v[rows, count // 2])


def _along_rays(T_cam_pallet: np.ndarray, pts: np.ndarray, n_pts: np.ndarray, boxes_m: np.ndarray, window_m: float,
                T_vc: np.ndarray, on_floor: np.ndarray, compiled: bool = True, threads: int = 1) -> np.ndarray:
    """Step 4 of the module docstring, once, for P poses of one pallet type.

    :param T_cam_pallet: (P, 4, 4). :param pts: (P, N, 3) camera frame, metres; pose i uses its first `n_pts[i]` rows.
    :param boxes_m: (k, 2, 3) the type's boards and blocks. :param on_floor: (P,) bool: move those horizontally only
        (in the vehicle frame), keeping them on the floor. :param compiled: the rays in the compiled kernel (on
        `threads` threads) when the package has it (`kernels.along_rays`, the same moves), else in numpy.
    :return: (P, 4, 4) the poses moved; a pose with fewer than `_MIN_INLIERS` points within the window stays.
    """
    P, N = pts.shape[:2]
    n_pts = np.minimum(np.asarray(n_pts, dtype=np.int64), N)
    if compiled and kernels.available() and len(boxes_m) <= kernels.MAX_BOXES:
        count, shift_m, ray = kernels.along_rays(T_cam_pallet, pts, n_pts, boxes_m, window_m, threads)
    else:
        count, shift_m, ray = _along_rays_numpy(T_cam_pallet, pts, n_pts, boxes_m, window_m)
    moved = np.flatnonzero(count >= _MIN_INLIERS)              # fewer points within the window: the pose stays
    out = T_cam_pallet.copy()
    if len(moved) == 0:
        return out
    shift_m, ray = shift_m[moved], ray[moved]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)          # the points' mean viewing direction
    move = shift_m[:, None] * ray
    up = T_vc[2, :3]                                                                # vehicle up, camera frame
    floor = on_floor[moved]
    # on the floor: horizontally, by as much as moves the surface by shift_m along the ray; seen steeply from above
    # (rays more than 45 degrees down) the depth is the deck's height, which a horizontal move cannot explain
    flat = ray - (ray @ up)[:, None] * up
    flat2 = np.einsum("ij,ij->i", flat, flat)
    steep = floor & (flat2 < 0.5)
    with np.errstate(invalid="ignore", divide="ignore"):
        move[floor] = (shift_m[floor] / flat2[floor])[:, None] * flat[floor]
    move[steep] = 0.0
    out[moved, :3, 3] += move
    return out


def _along_rays_numpy(T_cam_pallet: np.ndarray, pts: np.ndarray, n_pts: np.ndarray, boxes_m: np.ndarray,
                      window_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`kernels.along_rays` in numpy (its specification): of each pose's points, those whose depth lies within
    `window_m` of the posed boxes' first surface along their rays: (P,) how many, (P,) the median of their residuals
    (0 for none), (P, 3) the sum of their unit viewing directions."""
    P, N = pts.shape[:2]
    R_pc = np.swapaxes(T_cam_pallet[:, :3, :3], 1, 2)                               # camera -> pallet
    origin = -(R_pc @ T_cam_pallet[:, :3, 3, None])[..., 0]                         # the camera, pallet frame
    s = np.full((P, N), np.inf)
    for i in range(P):
        # one pose at a time: the (boxes, points) arrays of a pose stay in cache (16 poses at once: 3x slower)
        p = pts[i, :n_pts[i]]
        s[i, :n_pts[i]] = cast_rays_boxes(origin[i:i + 1], (p @ R_pc[i].T)[None], boxes_m)[0][0]   # 1: at the point
    rng_m = np.linalg.norm(pts, axis=2)
    with np.errstate(invalid="ignore"):
        res = (1.0 - s) * rng_m                                  # > 0: the point lies beyond the pallet's surface
    ok = np.isfinite(res) & (np.abs(res) < window_m) & (np.arange(N)[None] < n_pts[:, None])
    count = ok.sum(1)
    shift_m = np.where(count > 0, _row_medians(np.where(ok, res, np.inf), np.maximum(count, 1)), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = pts / rng_m[..., None]
    return count, shift_m, np.where(ok[..., None], unit, 0.0).sum(1)
