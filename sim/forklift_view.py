"""The forklift's own view: a vehicle with forks carrying the camera, and the pallets' faces and fork
pockets as a forklift needs them (camera and vehicle frames).

Vehicle frame (DESIGN.md): x forward along the forks, y left, z up, origin on the floor between the fork
roots. The camera sits on the fork carriage at a random height, pitch and offset; the fork tines are boxes
of the scene that move with the vehicle and show at the bottom of the image.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from pallet6d.runtime.geometry import invert_T, make_T, transform_points
from pallet6d.sim.pallets import face_normal, get_pallet_model
from pallet6d.sim.scene import MATERIALS, Box, ForkliftVehicle, PalletPlacement, Scene, obb_overlap

__all__ = ["R_VEHICLE_CAM0", "PalletFaceGT", "front_face", "face_gts", "place_forklift", "pocket_box_world",
           "pocket_visibility"]

# Camera looking straight along the forks: OpenCV axes (x right, y down, z forward) in the vehicle frame.
R_VEHICLE_CAM0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
_FORK_COLOR = np.array([0.16, 0.16, 0.17])
_TIP_M = 0.12                      # the tapered last part of a tine, half as thick


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _fork_boxes(T_world_vehicle: np.ndarray, z_m: float, spread_m: float, length_m: float, width_m: float,
                thick_m: float, seed: int) -> tuple[Box, ...]:
    out = []
    metal = MATERIALS.index("metal")
    for side in (1.0, -1.0):
        y = side * spread_m / 2
        for x0, x1, t in ((0.0, length_m - _TIP_M, thick_m), (length_m - _TIP_M, length_m, thick_m / 2)):
            centre = [(x0 + x1) / 2, y, z_m + t / 2]
            out.append(Box(T_world_vehicle @ make_T(np.eye(3), centre), [(x1 - x0) / 2, width_m / 2, t / 2], metal,
                           _FORK_COLOR, 0, seed))
    return tuple(out)


def place_forklift(rng: np.random.Generator, target: PalletPlacement, face: str, distance_m: tuple[float, float],
                   approach_yaw_deg: float, K: np.ndarray, image_hw: tuple[int, int],
                   cam_height_m: tuple[float, float] = (0.1, 2.5)) -> ForkliftVehicle:
    """A forklift facing `face` of the target pallet, with the camera 0.5-6 m (`distance_m`) from the face.

    Far away the vehicle approaches at up to +-`approach_yaw_deg` with the forks at a random height; closer
    than the forks are long it is lined up with the pockets (forks at pocket height, tines in the pockets),
    as a forklift must be there. The camera is pitched so that the fork tips show at the bottom of the
    image while the face stays in view (where both cannot be had, the face).
    """
    model = get_pallet_model(target.model_name)
    if face not in model.pockets_m:
        raise ValueError(f"{target.model_name} has no fork pockets on face {face!r}")
    T_wp = target.T_world_pallet
    n_w = T_wp[:3, :3] @ face_normal(face)
    centre_w = transform_points(T_wp, model.face_centre_m(face)[None])[0]
    pockets_w = transform_points(T_wp, model.pockets_m[face].reshape(-1, 3)).reshape(2, 2, 3)
    pocket_z = (float(pockets_w[:, :, 2].min()), float(pockets_w[:, :, 2].max()))
    pocket_lo, pocket_hi = model.pockets_m[face][:, 0], model.pockets_m[face][:, 1]
    lateral_axis = 1 if face[1] == "x" else 0
    pocket_c = (pocket_lo[:, lateral_axis] + pocket_hi[:, lateral_axis]) / 2
    pocket_w = pocket_hi[:, lateral_axis] - pocket_lo[:, lateral_axis]
    h, w = image_hw
    hhalf, vhalf = math.atan((w / 2) / K[0, 0]), math.atan((h / 2) / K[1, 1])

    length = rng.uniform(0.9, 1.2)
    width = rng.uniform(0.09, 0.13)
    thick = rng.uniform(0.035, 0.05)
    cam_x, cam_y = rng.uniform(-0.05, 0.10), rng.uniform(-0.12, 0.12)
    mount = rng.uniform(0.08, 0.35)                     # camera above the forks' top
    d = rng.uniform(*distance_m)
    inward = math.atan2(-n_w[1], -n_w[0])              # heading straight into the face
    pocket_h = pocket_z[1] - pocket_z[0]
    aligned = d < length + cam_x + 0.15
    if aligned and min(pocket_w) > width + 0.02 and pocket_h > thick + 0.01:
        # Lined up: the tines enter the pockets.
        heading = inward + math.radians(rng.uniform(-1.5, 1.5))
        spread = float(abs(pocket_c[0] - pocket_c[1]) + rng.uniform(-1, 1) * max(min(pocket_w) - width - 0.02, 0) / 2)
        fork_z = pocket_z[0] + rng.uniform(0.004, pocket_h - thick - 0.004)
        side = np.array([-math.sin(heading), math.cos(heading)])
        fwd = np.array([math.cos(heading), math.sin(heading)])
        origin_xy = centre_w[:2] + side * rng.uniform(-0.01, 0.01) - fwd * (d + cam_x)
    else:
        heading = inward + math.radians(rng.uniform(-1, 1) * approach_yaw_deg)
        bearing = rng.uniform(-0.5, 0.5) * hhalf        # where the face centre lies from the camera
        spread = rng.uniform(0.45, 0.75)
        fork_z = float(np.clip(pocket_z[0] + rng.uniform(-0.25, 0.35), 0.0, cam_height_m[1] - mount - thick))
        ray = np.array([math.cos(heading + bearing), math.sin(heading + bearing)])
        cam_xy = centre_w[:2] - d * ray
        origin_xy = cam_xy - _rz(heading)[:2, :2] @ [cam_x, cam_y]
    cam_z = float(np.clip(fork_z + thick + mount, *cam_height_m))
    # Pitch (down > 0): the fork tips in the lower part of the image, the face centre in view.
    tip_below = math.atan2(cam_z - fork_z - thick / 2, length - cam_x)
    face_above = math.atan2(centre_w[2] - cam_z, max(d, 0.3))
    lo = max(tip_below - 0.85 * vhalf, -face_above - 0.8 * vhalf, math.radians(-5))
    hi = min(tip_below - 0.3 * vhalf, 0.8 * vhalf - face_above, math.radians(30))
    # Where both cannot be had (a camera high above a close face), the face wins: it is looked at straight.
    pitch = rng.uniform(lo, hi) if lo < hi else float(np.clip(-face_above, math.radians(-5), math.radians(40)))
    mount_yaw, roll = math.radians(rng.uniform(-2, 2)), math.radians(rng.uniform(-1.5, 1.5))
    R_vc = _rz(mount_yaw) @ _ry(pitch) @ R_VEHICLE_CAM0 @ _rz(roll)       # roll about the optical axis
    T_vehicle_cam = make_T(R_vc, [cam_x, cam_y, cam_z])
    T_world_vehicle = make_T(_rz(heading), [origin_xy[0], origin_xy[1], 0.0])
    boxes = _fork_boxes(T_world_vehicle, fork_z, spread, length, width, thick, int(rng.integers(0, 2 ** 20)))
    return ForkliftVehicle(T_world_vehicle, T_vehicle_cam, boxes, float(fork_z), float(spread), float(length),
                           float(width), float(thick), target_face=face)


def pocket_box_world(placement: PalletPlacement, face: str) -> tuple[np.ndarray, np.ndarray]:
    """The two fork pockets of a face as oriented boxes: (2, 4, 4) centre poses and (2, 3) half sizes."""
    model = get_pallet_model(placement.model_name)
    pk = model.pockets_m[face]
    T = np.stack([placement.T_world_pallet @ make_T(np.eye(3), (lo + hi) / 2) for lo, hi in pk])
    return T, (pk[:, 1] - pk[:, 0]) / 2


def front_face(placement: PalletPlacement, eye_world: np.ndarray) -> str | None:
    """The pallet face with fork pockets that looks most towards `eye_world` (None: no face has pockets)."""
    model = get_pallet_model(placement.model_name)
    best, best_cos = None, -np.inf
    for face in model.pockets_m:
        n = placement.T_world_pallet[:3, :3] @ face_normal(face)
        c = transform_points(placement.T_world_pallet, model.face_centre_m(face)[None])[0]
        to_eye = np.asarray(eye_world, dtype=np.float64) - c
        cos = float(n @ to_eye / max(np.linalg.norm(to_eye), 1e-9))
        if cos > best_cos:
            best, best_cos = face, cos
    return best


@dataclass(frozen=True)
class PalletFaceGT:
    """A pallet's front face and fork pockets in one frame, as a forklift needs them.

    The front face is the face the forklift approaches (the target of a forklift view), else the face with
    pockets that looks most towards the camera; pockets are left then right as seen from outside that face.
    Camera-frame quantities always; vehicle-frame ones when the frame has a vehicle (else None).

    :ivar face_centre_cam: (3,) metres. :ivar face_normal_cam: (3,) outward unit normal.
    :ivar pocket_centres_cam: (2, 3) centres of the pocket openings in the face plane.
    :ivar pocket_size_m: (2, 2) width and height of each opening.
    :ivar pocket_blocked: (2,) something other than the pallet itself (and the vehicle's forks) is inside
        the pocket, anywhere along its depth.
    :ivar face_yaw_deg: yaw of the face relative to the forks: 0 when the forks point straight into it,
        positive when the face is turned anticlockwise seen from above (vehicle frame).
    :ivar pocket_visib_fract: (2,) the part of each opening the camera sees (nothing in front of it, inside
        the image), 0 when the face looks away; None until measured on a rendered depth image.
    """

    instance_id: int
    face: str
    face_centre_cam: np.ndarray
    face_normal_cam: np.ndarray
    pocket_centres_cam: np.ndarray
    pocket_size_m: np.ndarray
    pocket_blocked: np.ndarray
    face_centre_vehicle: np.ndarray | None = None
    face_normal_vehicle: np.ndarray | None = None
    pocket_centres_vehicle: np.ndarray | None = None
    face_yaw_deg: float | None = None
    pocket_visib_fract: np.ndarray | None = None

    def __post_init__(self) -> None:
        shapes = {"face_centre_cam": (3,), "face_normal_cam": (3,), "pocket_centres_cam": (2, 3),
                  "pocket_size_m": (2, 2), "pocket_blocked": (2,), "face_centre_vehicle": (3,),
                  "face_normal_vehicle": (3,), "pocket_centres_vehicle": (2, 3), "pocket_visib_fract": (2,)}
        for name, shape in shapes.items():
            value = getattr(self, name)
            if value is not None and np.shape(value) != shape:
                raise ValueError(f"PalletFaceGT.{name} must be {shape}, got {np.shape(value)}")
        if self.face not in ("+x", "-x", "+y", "-y"):
            raise ValueError(f"PalletFaceGT.face must be a pallet face, got {self.face!r}")

    def pocket_corners_cam(self, T_cam_pallet: np.ndarray) -> np.ndarray:
        """(2, 4, 3) corners of the two openings in the face plane (camera frame), around each opening."""
        up = T_cam_pallet[:3, 2]
        lateral = np.cross(up, self.face_normal_cam)
        signs = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], dtype=np.float64)
        return np.stack([c + (signs[:, :1] * w / 2) * lateral + (signs[:, 1:] * h / 2) * up
                         for c, (w, h) in zip(self.pocket_centres_cam, self.pocket_size_m)])

    def to_json(self) -> dict:
        """BOP-style JSON entry: millimetres, plain lists."""
        mm = lambda v: None if v is None else [float(x) for x in np.asarray(v).ravel() * 1000.0]  # noqa: E731
        pockets = []
        for k, side in enumerate(("left", "right")):
            pockets.append({
                "side": side, "centre_cam_mm": mm(self.pocket_centres_cam[k]),
                "centre_vehicle_mm": None if self.pocket_centres_vehicle is None
                else mm(self.pocket_centres_vehicle[k]),
                "width_mm": float(self.pocket_size_m[k, 0] * 1000.0),
                "height_mm": float(self.pocket_size_m[k, 1] * 1000.0), "blocked": bool(self.pocket_blocked[k]),
                "visib_fract": None if self.pocket_visib_fract is None else float(self.pocket_visib_fract[k])})
        return {"face": self.face, "face_centre_cam_mm": mm(self.face_centre_cam),
                "face_normal_cam": [float(x) for x in self.face_normal_cam],
                "face_centre_vehicle_mm": mm(self.face_centre_vehicle),
                "face_normal_vehicle": None if self.face_normal_vehicle is None
                else [float(x) for x in self.face_normal_vehicle],
                "face_yaw_deg": self.face_yaw_deg, "pockets": pockets}


def _blocked(scene: Scene, placement: PalletPlacement, face: str) -> np.ndarray:
    own_vehicle = set() if scene.vehicle is None else {id(b) for b in scene.vehicle.boxes}
    others = [b for b in scene.boxes if b.instance_id != placement.instance_id and id(b) not in own_vehicle]
    if not others:
        return np.zeros(2, dtype=bool)
    T_o = np.stack([b.T_world_box for b in others])
    h_o = np.stack([b.half_size_m for b in others])
    T_pk, h_pk = pocket_box_world(placement, face)
    out = np.zeros(2, dtype=bool)
    for k in range(2):
        reach = np.linalg.norm(h_o, axis=1) + np.linalg.norm(h_pk[k])          # bounding spheres first
        near = np.linalg.norm(T_o[:, :3, 3] - T_pk[k, :3, 3], axis=1) < reach
        if near.any():
            out[k] = bool(obb_overlap(T_pk[k], h_pk[k], T_o[near], h_o[near], margin_m=0.002).any())
    return out


def face_gts(scene: Scene, instance_ids) -> list[PalletFaceGT]:
    """Front face and pockets of the given pallets of a scene (those without pockets are left out)."""
    T_cam_world = scene.T_cam_world
    eye = scene.T_world_cam[:3, 3]
    T_vehicle_world = None if scene.vehicle is None else invert_T(scene.vehicle.T_world_vehicle)
    out = []
    by_id = {p.instance_id: p for p in scene.pallets}
    for iid in instance_ids:
        p = by_id[iid]
        approached = scene.vehicle is not None and iid == scene.target_instance and scene.vehicle.target_face
        face = scene.vehicle.target_face if approached else front_face(p, eye)
        if face is None:
            continue
        model = get_pallet_model(p.model_name)
        pk = model.pockets_m[face]
        n_p = face_normal(face)
        depth_axis = 0 if face[1] == "x" else 1
        centres = (pk[:, 0] + pk[:, 1]) / 2
        centres[:, depth_axis] = model.size_m[depth_axis] / 2 * n_p[depth_axis]    # in the face plane
        size = np.stack([pk[:, 1, 1 - depth_axis] - pk[:, 0, 1 - depth_axis], pk[:, 1, 2] - pk[:, 0, 2]], 1)
        pts_w = transform_points(p.T_world_pallet, np.vstack([model.face_centre_m(face)[None], centres]))
        n_w = p.T_world_pallet[:3, :3] @ n_p
        cam = transform_points(T_cam_world, pts_w)
        kw = {}
        if T_vehicle_world is not None:
            veh = transform_points(T_vehicle_world, pts_w)
            n_v = T_vehicle_world[:3, :3] @ n_w
            kw = dict(face_centre_vehicle=veh[0], face_normal_vehicle=n_v, pocket_centres_vehicle=veh[1:],
                      face_yaw_deg=float(math.degrees(math.atan2(-n_v[1], -n_v[0]))))
        out.append(PalletFaceGT(iid, face, cam[0], T_cam_world[:3, :3] @ n_w, cam[1:], size,
                                _blocked(scene, p, face), **kw))
    return out


def pocket_visibility(face: PalletFaceGT, T_cam_pallet: np.ndarray, depth_ideal_m: np.ndarray,
                      K: np.ndarray, tol_m: float = 0.01) -> np.ndarray:
    """(2,) visible fraction of each pocket opening: pixels of the opening (its projection, the part
    outside the image included) whose exact depth is not in front of the face plane, over all its pixels.

    :param depth_ideal_m: (H, W) exact depth, 0 where nothing was hit (free view).
    """
    h, w = depth_ideal_m.shape
    out = np.zeros(2)
    if face.face_normal_cam @ face.face_centre_cam >= 0:      # the face looks away from the camera
        return out
    corners = face.pocket_corners_cam(T_cam_pallet)
    for k in range(2):
        if np.any(corners[k, :, 2] < 0.05):
            continue
        uv = (corners[k] @ K.T)[:, :2] / corners[k, :, 2:]
        x, y = uv[:, 0], uv[:, 1]
        area = 0.5 * abs(float(x @ np.roll(y, 1) - y @ np.roll(x, 1)))
        if area < 1.0:
            continue
        mask = np.zeros((h, w), dtype=np.uint8)
        cv2.fillConvexPoly(mask, np.round(uv * 16).astype(np.int32), 1, cv2.LINE_8, 4)
        v, u = np.nonzero(mask)
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.size)], 1)
        z_plane = (face.face_normal_cam @ face.face_centre_cam) / (rays @ face.face_normal_cam)
        d = depth_ideal_m[v, u]
        seen = (d == 0) | (d >= z_plane - tol_m)
        out[k] = min(float(seen.sum()) / area, 1.0)
    return out
