"""What a forklift needs of a posed pallet, in the calibrated vehicle frame. Pure numpy functions.

Vehicle frame: x forward along the forks, y left, z up, origin on the floor between the fork roots (metres).
Pallet frame: origin at the centre of the pallet's bounding box, x along its length, y along its width, z up.

Per pallet, from its type's geometry (`size_m`, `boxes_m`, `pockets_m`):

- the front face: of the faces with fork pockets, the one whose outward normal points most towards the vehicle
  (against the forks' direction, -x);
- the face centre (centre of that face of the bounding box, at half the pallet's height), the face's yaw
  relative to the forks (0 when the forks point straight into it, positive when it is turned anticlockwise seen
  from above), the lateral offset (its y) and the distance (its x: from the fork roots along the forks);
- the left and right pocket (left / right as seen looking at the face from outside, i.e. from the forklift):
  the centre of the opening in the face plane, its width and height;
- whether each pocket is clear: rays cast through a grid over the opening (`structure.cast_rays_boxes` gives
  where the pallet's own boards and blocks end the free space) are compared with the observed depth. A surface
  inside the pocket, or in the forks' path just in front of its mouth, is *blocked* evidence; depth at or
  behind where the pocket ends is *open*; a surface further in front (an occluder) or no depth is no evidence.
  The forks' path is checked in volume too: points sampled inside the pocket, between `min_open_depth_m` and
  `clear_depth_m` in, are *seen free* where the depth lies at or behind them. A pocket with too little evidence,
  or whose deeper part the depth shows free too little of (seen so obliquely that its own blocks hide what lies
  past its mouth), is *hidden*;
- `pick_safe`: false with the reason when the face is seen too obliquely, or a pocket is blocked or hidden.

`forklift_info` does one pallet; `attach_forklift` adds `T_vehicle_pallet` and the forklift outputs to every
pose of a `FrameResult`; `vehicle_frame_result` does that for an estimator's result of one frame (what
`pallet6d run --calibration` and the daemon give).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Mapping

import numpy as np

from .geometry import check_K, invert_T, project_points, transform_points
from .level import LevelParams, level_poses
from .structure import cast_rays_boxes

__all__ = ["ForkliftParams", "Pocket", "ForkliftInfo", "FACE_NORMALS", "front_face", "face_frame_points",
           "face_yaw_deg", "pocket_evidence", "pocket_free_fraction", "pocket_occupied_fraction", "vehicle_pose",
           "forklift_info", "attach_forklift", "pallet_types_by_name", "vehicle_frame_result", "PICK_REASONS"]

log = logging.getLogger(__name__)

FACE_NORMALS = {"+x": np.array([1.0, 0.0, 0.0]), "-x": np.array([-1.0, 0.0, 0.0]),
                "+y": np.array([0.0, 1.0, 0.0]), "-y": np.array([0.0, -1.0, 0.0])}
POCKET_STATES = ("clear", "blocked", "hidden")
# why a pallet is not safe to pick, as stable codes ("" when it is)
PICK_REASONS = ("", "face_oblique", "pocket_blocked", "pocket_hidden")


@dataclass(frozen=True)
class ForkliftParams:
    """Thresholds of the pocket check and `pick_safe` (lengths in metres).

    :ivar grid: rays per side of the grid over each pocket opening.
    :ivar inset: fraction of the opening's width and height left out at each edge (board edges, depth edges).
    :ivar clear_depth_m: how deep into the pocket the depth must show free space (less where the ray leaves the
        pocket sooner: into the pallet's own blocks, or through its floor or deck).
    :ivar min_open_depth_m: a ray is open evidence only where it sees this far into the pocket (along it): an
        oblique or steep view that sees only the pocket's first centimetres cannot tell that it is free.
    :ivar min_free_fraction: of the pocket's volume from `min_open_depth_m` to `clear_depth_m` in (the forks' path
        past the mouth), the share the depth must show free; less -> hidden. An object past the mouth seen
        obliquely sits behind the pallet's own block and leaves few blocked rays, but leaves that volume unseen.
    :ivar max_occupied_fraction: of the pocket's volume from its mouth to `clear_depth_m` in, the share where the
        depth shows a surface inside the pocket in front of the sample point (something in the forks' path that the
        pallet's own boards do not explain); more -> blocked. An object seen past the pallet's own block through a
        sliver of the opening leaves the rays through the inset opening open and most of the volume free.
    :ivar slice_m: spacing along the pocket of the volume's sample points (`grid` x `grid` per slice).
    :ivar mouth_m: a surface this close in front of the pocket's mouth is in the forks' path: blocked evidence.
    :ivar tol_m, tol_quad_per_m: depth tolerance `tol_m + tol_quad_per_m * z**2` (stereo noise grows with z**2).
    :ivar min_rays: fewer open + blocked rays -> the pocket is hidden.
    :ivar max_blocked_fraction: blocked / (open + blocked) above this -> the pocket is blocked.
    :ivar max_view_angle_deg: the angle between the face's normal and the line of sight from the face's centre
        to the camera; above it the face is seen too obliquely to judge its pockets.
    :ivar level: how `T_vehicle_pallet` is levelled, set on the floor and refined (`level.LevelParams`); None:
        the estimate as it is.
    """

    grid: int = 8
    inset: float = 0.15
    clear_depth_m: float = 0.4
    min_open_depth_m: float = 0.2
    min_free_fraction: float = 0.1
    max_occupied_fraction: float = 0.025
    slice_m: float = 0.025
    mouth_m: float = 0.1
    tol_m: float = 0.03
    tol_quad_per_m: float = 0.006
    min_rays: int = 8
    max_blocked_fraction: float = 0.15
    max_view_angle_deg: float = 50.0
    level: LevelParams | None = LevelParams()

    def __post_init__(self) -> None:
        if int(self.grid) < 2 or int(self.min_rays) < 1:
            raise ValueError(f"grid must be >= 2 and min_rays >= 1, got {self.grid}, {self.min_rays}")
        if not 0.0 <= self.inset < 0.5:
            raise ValueError(f"inset must be in [0, 0.5), got {self.inset}")
        for name in ("clear_depth_m", "min_open_depth_m", "mouth_m", "tol_m", "tol_quad_per_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.slice_m > 0:
            raise ValueError(f"slice_m must be > 0, got {self.slice_m}")
        for name in ("max_blocked_fraction", "min_free_fraction", "max_occupied_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0.0 < self.max_view_angle_deg <= 90.0:
            raise ValueError(f"max_view_angle_deg must be in (0, 90], got {self.max_view_angle_deg}")


def _vec(value, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite shape {shape}, got {arr.shape}")
    arr = arr.copy()
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class Pocket:
    """One fork pocket of the front face (vehicle frame, metres).

    :ivar side: "left" or "right", seen from the forklift. :ivar centre_vehicle_m: (3,) centre of the opening in
    the face plane. :ivar width_m, height_m: the opening's size. :ivar state: "clear", "blocked" or "hidden".
    :ivar open_rays, blocked_rays: the depth evidence (rays through the opening).
    :ivar free_fraction: share of the forks' path past the mouth that the depth shows free (`pocket_free_fraction`).
    :ivar occupied_fraction: share of the forks' path from the mouth in where the depth shows a surface inside the
        pocket (`pocket_occupied_fraction`).
    """

    side: str
    centre_vehicle_m: np.ndarray
    width_m: float
    height_m: float
    state: str
    open_rays: int = 0
    blocked_rays: int = 0
    free_fraction: float = 0.0
    occupied_fraction: float = 0.0

    def __post_init__(self) -> None:
        if self.side not in ("left", "right"):
            raise ValueError(f"Pocket.side must be 'left' or 'right', got {self.side!r}")
        if self.state not in POCKET_STATES:
            raise ValueError(f"Pocket.state must be one of {POCKET_STATES}, got {self.state!r}")
        object.__setattr__(self, "centre_vehicle_m", _vec(self.centre_vehicle_m, (3,), "Pocket.centre_vehicle_m"))
        for name in ("width_m", "height_m"):
            v = float(getattr(self, name))
            if not v > 0:
                raise ValueError(f"Pocket.{name} must be positive, got {v}")
            object.__setattr__(self, name, v)
        for name in ("free_fraction", "occupied_fraction"):
            f = float(getattr(self, name))
            if not 0.0 <= f <= 1.0:
                raise ValueError(f"Pocket.{name} must be in [0, 1], got {f}")
            object.__setattr__(self, name, f)

    def to_dict(self) -> dict:
        return {"side": self.side, "centre_m": [round(float(x), 4) for x in self.centre_vehicle_m],
                "width_m": round(self.width_m, 4), "height_m": round(self.height_m, 4), "state": self.state,
                "open_rays": int(self.open_rays), "blocked_rays": int(self.blocked_rays),
                "free_fraction": round(self.free_fraction, 3), "occupied_fraction": round(self.occupied_fraction, 3)}


@dataclass(frozen=True)
class ForkliftInfo:
    """A pallet's front face and pockets as a forklift steers by them (vehicle frame, metres, degrees).

    :ivar face: the pallet-frame face ("+x", "-x", "+y", "-y"). :ivar face_centre_vehicle_m: (3,).
    :ivar face_normal_vehicle: (3,) outward unit normal. :ivar face_yaw_deg: yaw of the face relative to the forks.
    :ivar lateral_offset_m: the face centre's y (left positive). :ivar distance_m: the face centre's x.
    :ivar view_angle_deg: angle between the face normal and the line of sight to the camera.
    :ivar pockets: (left, right). :ivar pick_safe: both pockets clear and the face seen squarely enough.
    :ivar reason: one of `PICK_REASONS` ("" when safe). :ivar detail: a sentence with the numbers.
    """

    face: str
    face_centre_vehicle_m: np.ndarray
    face_normal_vehicle: np.ndarray
    face_yaw_deg: float
    lateral_offset_m: float
    distance_m: float
    view_angle_deg: float
    pockets: tuple[Pocket, Pocket]
    pick_safe: bool
    reason: str = ""
    detail: str = ""

    def __post_init__(self) -> None:
        if self.face not in FACE_NORMALS:
            raise ValueError(f"ForkliftInfo.face must be one of {tuple(FACE_NORMALS)}, got {self.face!r}")
        object.__setattr__(self, "face_centre_vehicle_m",
                           _vec(self.face_centre_vehicle_m, (3,), "ForkliftInfo.face_centre_vehicle_m"))
        object.__setattr__(self, "face_normal_vehicle",
                           _vec(self.face_normal_vehicle, (3,), "ForkliftInfo.face_normal_vehicle"))
        for name in ("face_yaw_deg", "lateral_offset_m", "distance_m", "view_angle_deg"):
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise ValueError(f"ForkliftInfo.{name} must be finite, got {v}")
            object.__setattr__(self, name, v)
        if len(self.pockets) != 2 or not all(isinstance(p, Pocket) for p in self.pockets) \
                or (self.pockets[0].side, self.pockets[1].side) != ("left", "right"):
            raise ValueError("ForkliftInfo.pockets must be (left Pocket, right Pocket)")
        object.__setattr__(self, "pockets", tuple(self.pockets))
        if self.reason not in PICK_REASONS or (self.reason == "") != bool(self.pick_safe):
            raise ValueError(f"ForkliftInfo.reason must be one of {PICK_REASONS}, empty exactly when pick_safe; got "
                             f"pick_safe={self.pick_safe}, reason={self.reason!r}")
        object.__setattr__(self, "pick_safe", bool(self.pick_safe))

    def to_dict(self) -> dict:
        return {"face": self.face, "face_centre_m": [round(float(x), 4) for x in self.face_centre_vehicle_m],
                "face_yaw_deg": round(self.face_yaw_deg, 2), "lateral_offset_m": round(self.lateral_offset_m, 4),
                "distance_m": round(self.distance_m, 4), "view_angle_deg": round(self.view_angle_deg, 1),
                "pockets": [p.to_dict() for p in self.pockets], "pick_safe": self.pick_safe,
                "reason": self.reason, "detail": self.detail}


def front_face(pockets_m: Mapping[str, np.ndarray], T_vehicle_pallet: np.ndarray) -> str | None:
    """The face with fork pockets whose outward normal points most towards the vehicle: most against the forks'
    direction (-x), so its yaw relative to the forks is within +-45 degrees.

    :param pockets_m: face -> (2, 2, 3) pocket boxes (pallet frame). :param T_vehicle_pallet: (4, 4).
    :return: the face, or None for a pallet without pockets.
    """
    R = np.asarray(T_vehicle_pallet, dtype=np.float64)[:3, :3]
    best, best_cos = None, -np.inf
    for face in pockets_m:
        cos = -float((R @ FACE_NORMALS[face])[0])     # the normal against the forks' direction (-x)
        if cos > best_cos:
            best, best_cos = face, cos
    return best


def face_frame_points(pockets_face: np.ndarray, size_m, face: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A face's centre and its pockets' opening centres in the face plane, pallet frame.

    :param pockets_face: (2, 2, 3) min/max corners of the face's two pockets, left then right.
    :return: face centre (3,), pocket centres (2, 3), pocket sizes (2, 2) as (width, height).
    """
    pk = np.asarray(pockets_face, dtype=np.float64)
    size = np.asarray(size_m, dtype=np.float64)
    n = FACE_NORMALS[face]
    depth_axis = 0 if face[1] == "x" else 1
    centres = (pk[:, 0] + pk[:, 1]) / 2
    centres[:, depth_axis] = size[depth_axis] / 2 * n[depth_axis]
    sizes = np.stack([pk[:, 1, 1 - depth_axis] - pk[:, 0, 1 - depth_axis], pk[:, 1, 2] - pk[:, 0, 2]], axis=1)
    return n * size / 2, centres, sizes


def face_yaw_deg(normal_vehicle: np.ndarray) -> float:
    """Yaw of a face relative to the forks from its outward normal (vehicle frame): 0 when the normal points back
    along -x (the forks point straight into it), positive when the face is turned anticlockwise seen from above."""
    n = np.asarray(normal_vehicle, dtype=np.float64)
    return float(np.degrees(np.arctan2(-n[1], -n[0])))


def _pocket_grid(pocket: np.ndarray, size_m: np.ndarray, face: str, grid: int, inset: float) -> np.ndarray:
    """(grid * grid, 3) points on a pocket's opening in the face plane (pallet frame), edges inset."""
    depth_axis = 0 if face[1] == "x" else 1
    lo, hi = pocket[0], pocket[1]
    s = inset + (1 - 2 * inset) * (np.arange(grid) + 0.5) / grid
    a, b = np.meshgrid(s, s, indexing="ij")
    pts = np.zeros((grid * grid, 3))
    lat = 1 - depth_axis
    pts[:, lat] = lo[lat] + a.ravel() * (hi[lat] - lo[lat])
    pts[:, 2] = lo[2] + b.ravel() * (hi[2] - lo[2])
    pts[:, depth_axis] = size_m[depth_axis] / 2 * FACE_NORMALS[face][depth_axis]
    return pts


def _exit_param(origin: np.ndarray, dirs: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(r,) ray parameter where rays `origin + s * dirs` (r, 3) leave an axis-aligned box (2, 3) (inf: never in)."""
    box = np.asarray(box, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(np.abs(dirs) > 1e-12, 1.0 / dirs, 1e12)
    t1, t2 = (box[0] - origin) * inv, (box[1] - origin) * inv
    near, far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    return np.where(near <= far, far, np.inf)


def _pocket_inputs(T_cam_pallet, K, depth_m, size_m) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pocket checks' inputs as float arrays; depth that is not (H, W) is an error."""
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth_m.shape}")
    return (np.asarray(T_cam_pallet, dtype=np.float64), check_K(K), depth_m,
            np.asarray(size_m, dtype=np.float64))


def pocket_evidence(T_cam_pallet: np.ndarray, boxes_m: np.ndarray, pockets_face: np.ndarray, size_m, face: str,
                    depth_m: np.ndarray, K: np.ndarray, params: ForkliftParams = ForkliftParams()) -> np.ndarray:
    """Open and blocked rays through each pocket of a face.

    :param T_cam_pallet: (4, 4). :param boxes_m: (k, 2, 3) the pallet's boards and blocks (pallet frame).
    :param pockets_face: (2, 2, 3) the face's pockets, left then right. :param size_m: (3,).
    :param depth_m: (H, W) observed depth, metres, 0 = none. :param K: (3, 3).
    :return: (2, 2) int: per pocket (open rays, blocked rays).
    """
    T, K, depth_m, size = _pocket_inputs(T_cam_pallet, K, depth_m, size_m)
    h, w = depth_m.shape
    n_cam = T[:3, :3] @ FACE_NORMALS[face]
    T_pallet_cam = invert_T(T)
    out = np.zeros((2, 2), dtype=np.int64)
    for k in range(2):
        pts_cam = _pocket_grid(np.asarray(pockets_face[k], dtype=np.float64), size, face, params.grid,
                               params.inset) @ T[:3, :3].T + T[:3, 3]
        pts_cam = pts_cam[pts_cam[:, 2] > 0.05]
        if not len(pts_cam):
            continue
        uv = np.round(pts_cam[:, :2] / pts_cam[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]).astype(np.int64)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        uv = np.unique(uv[inside], axis=0)
        if not len(uv):
            continue
        rays = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])
        denom = rays @ n_cam
        with np.errstate(divide="ignore", invalid="ignore"):
            z_entry = np.where(denom < -1e-9, (n_cam @ pts_cam[0]) / denom, np.nan)   # face plane, seen from outside
        dirs_p = rays @ T_pallet_cam[:3, :3].T
        t_box, _ = cast_rays_boxes(T_pallet_cam[None, :3, 3], dirs_p[None], boxes_m)
        t_box = np.minimum(t_box[0], _exit_param(T_pallet_cam[:3, 3], dirs_p, pockets_face[k]))
        d = depth_m[uv[:, 1], uv[:, 0]].astype(np.float64)
        ok = np.isfinite(z_entry) & (d > 0) & np.isfinite(d) & (t_box >= z_entry - 1e-6)  # entry not behind wood
        z_entry, t_box, d, dirs_p = z_entry[ok], t_box[ok], d[ok], dirs_p[ok]
        tol = params.tol_m + params.tol_quad_per_m * z_entry ** 2
        free_to = np.minimum(t_box, z_entry + params.clear_depth_m)
        # how far past the face plane, along the pocket, the ray sees free space
        depth_axis = 0 if face[1] == "x" else 1
        reach = np.abs((free_to - z_entry) * dirs_p[:, depth_axis])
        open_ = (d >= free_to - tol) & (reach >= params.min_open_depth_m)
        blocked = (d < free_to - tol) & (d >= z_entry - params.mouth_m)
        out[k] = int(open_.sum()), int(blocked.sum())
    return out


def pocket_free_fraction(T_cam_pallet: np.ndarray, boxes_m: np.ndarray, pockets_face: np.ndarray, size_m,
                         face: str, depth_m: np.ndarray, K: np.ndarray,
                         params: ForkliftParams = ForkliftParams()) -> np.ndarray:
    """Share of each pocket's volume from `min_open_depth_m` to `clear_depth_m` in (the forks' path past the
    mouth) that the depth shows free: sample points (`grid` x `grid` over the inset opening, every `slice_m` along
    the pocket) that no board or block of the pallet hides from the camera and whose pixel's depth lies at or
    behind them.

    :param T_cam_pallet: (4, 4). :param boxes_m: (k, 2, 3) the pallet's boards and blocks (pallet frame).
    :param pockets_face: (2, 2, 3) the face's pockets, left then right. :param size_m: (3,).
    :param depth_m: (H, W) observed depth, metres, 0 = none. :param K: (3, 3).
    :return: (2,) float in [0, 1], left then right (1 where the parameters leave no volume to check).
    """
    return _pocket_volume(T_cam_pallet, boxes_m, pockets_face, size_m, face, depth_m, K, params)[0]


def pocket_occupied_fraction(T_cam_pallet: np.ndarray, boxes_m: np.ndarray, pockets_face: np.ndarray, size_m,
                             face: str, depth_m: np.ndarray, K: np.ndarray,
                             params: ForkliftParams = ForkliftParams()) -> np.ndarray:
    """Share of each pocket's volume from its mouth to `clear_depth_m` in where the depth shows a surface inside
    the pocket in front of the sample point: the ray of the point's pixel meets no board or block of the pallet
    before the point, and its depth lies more than the tolerance in front of the point but not in front of the
    first slice of points, half a `slice_m` in from the face (what stands at the mouth, the forklift's own fork tips
    too, is left to the rays of `pocket_evidence`). The pixel's own ray, not the point's, decides what the pallet
    hides: at a block's edge the two differ, and the depth read is the pixel's.

    :param T_cam_pallet: (4, 4). :param boxes_m: (k, 2, 3) the pallet's boards and blocks (pallet frame).
    :param pockets_face: (2, 2, 3) the face's pockets, left then right. :param size_m: (3,).
    :param depth_m: (H, W) observed depth, metres, 0 = none. :param K: (3, 3).
    :return: (2,) float in [0, 1], left then right (0 where the parameters leave no volume to check).
    """
    return _pocket_volume(T_cam_pallet, boxes_m, pockets_face, size_m, face, depth_m, K, params)[1]


def _pocket_volume(T_cam_pallet, boxes_m, pockets_face, size_m, face: str, depth_m, K,
                   params: ForkliftParams) -> tuple[np.ndarray, np.ndarray]:
    """`pocket_free_fraction` and `pocket_occupied_fraction` from one set of sample points: both pockets' volume
    from the mouth to `clear_depth_m` in, the free share read on the slices from `min_open_depth_m` in."""
    T, K, depth_m, size = _pocket_inputs(T_cam_pallet, K, depth_m, size_m)
    h, w = depth_m.shape
    along = np.arange(params.slice_m / 2, params.clear_depth_m, params.slice_m)
    if not len(along):
        return np.ones(2), np.zeros(2)
    deep = along >= params.min_open_depth_m - 1e-9                     # the slices the free share reads
    inward = -FACE_NORMALS[face]
    mouths = np.stack([_pocket_grid(np.asarray(pockets_face[k], dtype=np.float64), size, face, params.grid,
                                    params.inset) for k in range(2)])                           # (2, g*g, 3)
    pts_p = mouths[:, None] + along[None, :, None, None] * inward                             # (2, s, g*g, 3)
    pts = transform_points(T, pts_p.reshape(-1, 3))
    z = pts[:, 2]
    front = z > 0.05
    u, v = np.round(np.where(front[:, None], project_points(pts, K), -1.0)).astype(np.int64).T
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.zeros(len(pts))
    d[inside] = depth_m[v[inside], u[inside]]
    d = np.where(np.isfinite(d), d, 0.0)
    tol = params.tol_m + params.tol_quad_per_m * z ** 2
    T_pallet_cam = invert_T(T)
    origin = T_pallet_cam[None, :3, 3]
    # free: no board or block before the point along its own ray (parameter = camera depth)
    zs = np.where(front, z, 1.0)
    t_point, _ = cast_rays_boxes(origin, ((pts / zs[:, None]) @ T_pallet_cam[:3, :3].T)[None], boxes_m)
    free = inside & (t_point[0] >= z - 1e-6) & (d > 0) & (d >= z - tol)
    free = free.reshape(2, len(along), -1)[:, deep].reshape(2, -1).mean(1) if deep.any() else np.ones(2)
    # occupied: judged on the ray of the pixel whose depth was read
    rays = np.column_stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(u))])   # depth = 1
    t_pixel, _ = cast_rays_boxes(origin, (rays @ T_pallet_cam[:3, :3].T)[None], boxes_m)
    n_cam = T[:3, :3] @ FACE_NORMALS[face]
    on_plane = transform_points(T, pts_p[0, 0, :1])[0]                   # on the first slice's plane, camera frame
    facing = rays @ n_cam
    with np.errstate(divide="ignore", invalid="ignore"):
        z_first = np.where(facing < -1e-9, (n_cam @ on_plane) / facing, np.inf)   # where the ray crosses it
    occupied = inside & (t_pixel[0] >= z - 1e-6) & (d > 0) & (d < z - tol) & (d >= z_first)
    return free, occupied.reshape(2, -1).mean(1)


def _pocket_state(open_rays: int, blocked_rays: int, free_fraction: float, occupied_fraction: float,
                  params: ForkliftParams) -> str:
    if occupied_fraction > params.max_occupied_fraction:
        return "blocked"
    seen = open_rays + blocked_rays
    if seen < params.min_rays:
        return "hidden"
    if blocked_rays > params.max_blocked_fraction * seen:
        return "blocked"
    return "hidden" if free_fraction < params.min_free_fraction else "clear"


def vehicle_pose(T_cam_pallet: np.ndarray, T_vehicle_cam: np.ndarray, size_m,
                 params: ForkliftParams = ForkliftParams(), boxes_m: np.ndarray | None = None,
                 depth_m: np.ndarray | None = None, K: np.ndarray | None = None,
                 box_xyxy=None) -> np.ndarray:
    """(4, 4) `T_vehicle_pallet` of one pose: levelled, set on the floor where it nearly is, and refined in yaw and
    position on its box's depth (`level.level_poses` with `params.level`; without the depth, box or boards only
    levelled and set on the floor)."""
    T_vc = np.asarray(T_vehicle_cam, dtype=np.float64)
    T_cp = np.asarray(T_cam_pallet, dtype=np.float64)
    if params.level is None:
        return T_vc @ T_cp
    height = float(np.asarray(size_m, dtype=np.float64)[2])
    box = None if box_xyxy is None else np.asarray(box_xyxy, dtype=np.float64)[None]
    return level_poses(T_cp[None], T_vc, np.array([height]), params.level, None if boxes_m is None else [boxes_m],
                       depth_m, K, box)[0]


def forklift_info(T_cam_pallet: np.ndarray, T_vehicle_cam: np.ndarray, size_m, pockets_m: Mapping[str, np.ndarray],
                  boxes_m: np.ndarray | None, depth_m: np.ndarray | None, K: np.ndarray | None,
                  params: ForkliftParams = ForkliftParams(), box_xyxy=None) -> ForkliftInfo | None:
    """The forklift outputs of one posed pallet (see the module docstring).

    :param T_cam_pallet: (4, 4) the pallet's pose. :param T_vehicle_cam: (4, 4) from the calibration.
    :param size_m: (3,) the type's size. :param pockets_m: face -> (2, 2, 3) the type's pockets.
    :param boxes_m: (k, 2, 3) the type's boards and blocks; None (or no depth): the pockets are "hidden".
    :param depth_m: (H, W) observed depth, metres. :param K: (3, 3).
    :param box_xyxy: the pose's detection box, pixels: with it `vehicle_pose` refines the levelled pose.
    :return: None for a type without fork pockets. Everything is of the pose `vehicle_pose` gives.
    """
    T_cam_pallet = np.asarray(T_cam_pallet, dtype=np.float64)
    T_vehicle_cam = np.asarray(T_vehicle_cam, dtype=np.float64)
    if T_cam_pallet.shape != (4, 4) or T_vehicle_cam.shape != (4, 4):
        raise ValueError(f"T_cam_pallet and T_vehicle_cam must be (4, 4), got {T_cam_pallet.shape}, "
                         f"{T_vehicle_cam.shape}")
    T_vp = vehicle_pose(T_cam_pallet, T_vehicle_cam, size_m, params, boxes_m, depth_m, K, box_xyxy)
    T_cam_pallet = invert_T(T_vehicle_cam) @ T_vp
    face = front_face(pockets_m, T_vp)
    if face is None:
        return None
    centre_p, pocket_p, sizes = face_frame_points(pockets_m[face], size_m, face)
    centre_v = T_vp[:3, :3] @ centre_p + T_vp[:3, 3]
    pockets_v = pocket_p @ T_vp[:3, :3].T + T_vp[:3, 3]
    normal_v = T_vp[:3, :3] @ FACE_NORMALS[face]
    normal_c = T_cam_pallet[:3, :3] @ FACE_NORMALS[face]
    centre_c = T_cam_pallet[:3, :3] @ centre_p + T_cam_pallet[:3, 3]
    view = float(np.degrees(np.arccos(np.clip(-normal_c @ centre_c / max(np.linalg.norm(centre_c), 1e-9), -1, 1))))
    if boxes_m is None or depth_m is None or K is None:
        evidence, free, occupied = np.zeros((2, 2), dtype=np.int64), np.zeros(2), np.zeros(2)
    else:
        args = (T_cam_pallet, boxes_m, pockets_m[face], size_m, face, depth_m, K, params)
        evidence, (free, occupied) = pocket_evidence(*args), _pocket_volume(*args)
    pockets = tuple(Pocket(side, pockets_v[k], sizes[k, 0], sizes[k, 1],
                           _pocket_state(int(evidence[k, 0]), int(evidence[k, 1]), float(free[k]),
                                         float(occupied[k]), params),
                           int(evidence[k, 0]), int(evidence[k, 1]), float(free[k]), float(occupied[k]))
                    for k, side in enumerate(("left", "right")))
    reason, detail = "", ""
    if view > params.max_view_angle_deg:
        reason = "face_oblique"
        detail = f"face seen at {view:.0f} deg from square (max {params.max_view_angle_deg:.0f})"
    elif any(p.state == "blocked" for p in pockets):
        reason = "pocket_blocked"
        detail = "; ".join(_blocked_detail(p, params) for p in pockets if p.state == "blocked")
    elif any(p.state == "hidden" for p in pockets):
        reason = "pocket_hidden"
        detail = "; ".join(_hidden_detail(p, params) for p in pockets if p.state == "hidden")
    return ForkliftInfo(face=face, face_centre_vehicle_m=centre_v, face_normal_vehicle=normal_v,
                        face_yaw_deg=face_yaw_deg(normal_v), lateral_offset_m=float(centre_v[1]),
                        distance_m=float(centre_v[0]), view_angle_deg=view, pockets=pockets,
                        pick_safe=reason == "", reason=reason, detail=detail)


def _blocked_detail(pocket: Pocket, params: ForkliftParams) -> str:
    if pocket.occupied_fraction > params.max_occupied_fraction:
        return (f"{pocket.side} pocket blocked (depth shows a surface in {pocket.occupied_fraction:.0%} of its path "
                f"0-{params.clear_depth_m:.2f} m in, max {params.max_occupied_fraction:.1%})")
    return (f"{pocket.side} pocket blocked ({pocket.blocked_rays} of {pocket.open_rays + pocket.blocked_rays} rays "
            "find a surface in it)")


def _hidden_detail(pocket: Pocket, params: ForkliftParams) -> str:
    seen = pocket.open_rays + pocket.blocked_rays
    if seen < params.min_rays:
        return f"{pocket.side} pocket hidden ({seen} rays with depth, need {params.min_rays})"
    return (f"{pocket.side} pocket hidden (depth shows {pocket.free_fraction:.0%} of its path "
            f"{params.min_open_depth_m:.2f}-{params.clear_depth_m:.2f} m in free, need {params.min_free_fraction:.0%})")


def pallet_types_by_name(bundle) -> dict[str, object]:
    """A bundle's pallet types by type name and by the name of the detector class that reports each."""
    out = {t.name: t for t in bundle.pallet_types}
    for t in bundle.pallet_types:
        if 0 <= t.class_id < len(bundle.classes):
            out.setdefault(bundle.classes[t.class_id], t)
    return out


def attach_forklift(result, T_vehicle_cam: np.ndarray, pallet_types: Mapping[str, object], depth_m: np.ndarray,
                    K: np.ndarray, params: ForkliftParams = ForkliftParams()):
    """A `FrameResult` whose poses also carry `T_vehicle_pallet` (`vehicle_pose`: levelled, on the floor where
    it nearly is, refined in yaw and position on the pose's box) and their `ForkliftInfo`.

    :param result: the estimator's `FrameResult` for this frame.
    :param T_vehicle_cam: (4, 4) from a valid calibration (`CalibrationMonitor.ok`).
    :param pallet_types: pallet type name -> type with `size_m`, `pockets_m`, `boxes_m` (a bundle's
        `{t.name: t for t in bundle.pallet_types}`); a pose is looked up by its `pallet_type`, else its class.
    :param depth_m: (H, W) the frame's depth, metres. :param K: (3, 3).
    """
    T_vc = np.asarray(T_vehicle_cam, dtype=np.float64)
    poses = []
    for p in result.poses:
        name = getattr(p, "pallet_type", "") or p.class_name
        ptype = pallet_types.get(name)
        info, T_vp = None, T_vc @ p.T_cam_pallet
        if ptype is None:
            log.warning("no pallet type %r: no fork pockets for this pose", name)
        else:
            T_vp = vehicle_pose(p.T_cam_pallet, T_vc, ptype.size_m, params, ptype.boxes_m, depth_m, K, p.box_xyxy)
            # of that pose (no box: levelling it again changes nothing and it is not refined twice)
            info = forklift_info(invert_T(T_vc) @ T_vp, T_vc, ptype.size_m, ptype.pockets_m, ptype.boxes_m, depth_m,
                                 K, params)
        poses.append(replace(p, T_vehicle_pallet=T_vp, forklift=info))
    return replace(result, poses=poses)


def vehicle_frame_result(result, T_vehicle_cam: np.ndarray, bundle, frame,
                         params: ForkliftParams = ForkliftParams()):
    """The estimator's `FrameResult` of `frame` in the vehicle frame: every pose with `T_vehicle_pallet` and its
    front face, pockets and `pick_safe`, from the bundle's pallet types and the frame's depth.

    :param T_vehicle_cam: (4, 4) from a valid calibration. :param bundle: the estimator's bundle (its
        `pallet_types` and `classes`). :param frame: the `RGBDFrame` the result is of (`depth_m`, `K`).
    """
    return attach_forklift(result, T_vehicle_cam, pallet_types_by_name(bundle), frame.depth_m, frame.K, params)
