"""Random warehouse scenes (paper Fig. 3): racks with pallets and loads, aisle pallets, occluders, walls,
and a forklift camera placed in front of a pallet to pick up; with `rich_content`, the real-warehouse
content of `loads.py`; with the "forklift" layout, the forklift's own view (`forklift_view.py`).

World frame: z up, floor z = 0. The rack row runs along x with its front at y = 0 and its depth along +y;
the aisle is y < 0. Pallets in racks have their length (x) along the rack depth, so the forklift's forks
enter along the pallet's x axis, as with EUR pallets on 2.7 m beams (three per bay, 800 mm side out).
"""
from __future__ import annotations

import math

import numpy as np

from pallet6d.runtime.geometry import make_T
from pallet6d.sim.forklift_view import place_forklift
from pallet6d.sim.loads import WOOD_COLORS, distractor_boxes, load_boxes, pallet_look, pocket_obstacle, truck_bed_boxes
from pallet6d.sim.pallets import face_normal, get_pallet_model
from pallet6d.sim.presets import LAYOUTS, SimConfig
from pallet6d.sim.scene import (MATERIALS, Box, Light, PalletPlacement, Scene, SceneError, look_at_T_world_cam,
                                pallet_boxes)

__all__ = ["build_scene"]

M = {name: i for i, name in enumerate(MATERIALS)}
RACK_DEPTH_M = 1.1
BAY_CLEAR_M = 2.7
UPRIGHT_M = (0.1, 0.08)
BEAM_H_M = 0.12


def _rz(yaw_rad: float) -> np.ndarray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _rot(axis: int, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _box(center, size, material: str, color, seed: int = 0, yaw: float = 0.0, R=None) -> Box:
    R = _rz(yaw) if R is None else R
    return Box(make_T(R, center), np.asarray(size, dtype=np.float64) / 2, M[material], color, 0, seed)


class _Builder:
    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.cfg, self.rng = cfg, rng
        self.boxes: list[Box] = []
        self.pallets: list[PalletPlacement] = []
        self.pallet_top: dict[int, float] = {}

    def seed(self) -> int:
        return int(self.rng.integers(0, 2 ** 20))

    # --- pallets and their loads --------------------------------------------------------------------
    def add_pallet(self, model_name: str, xy: tuple[float, float], z_floor: float, yaw: float,
                   clearance_m: float, load: bool = True) -> PalletPlacement:
        model = get_pallet_model(model_name)
        T = make_T(_rz(yaw), [xy[0], xy[1], z_floor + model.size_m[2] / 2])
        p = PalletPlacement(len(self.pallets) + 1, model_name, T)
        self.pallets.append(p)
        if self.cfg.rich_content:
            color, parts, missing = pallet_look(self.rng, model_name, self.cfg.missing_board_prob)
            self.boxes.extend(pallet_boxes(p, color, self.seed(), missing=missing, part_colors=parts))
            if load and self.rng.random() < self.cfg.load_prob and clearance_m > 0.25:
                self.boxes.extend(load_boxes(self.rng, p, clearance_m))
            return p
        color = WOOD_COLORS[self.rng.integers(len(WOOD_COLORS))] * self.rng.uniform(0.9, 1.08, 3)
        self.boxes.extend(pallet_boxes(p, color, self.seed()))
        if self.rng.random() < self.cfg.load_prob and clearance_m > 0.25:
            self.add_load(p, clearance_m)
        return p

    def random_model(self) -> str:
        return self.cfg.pallet_models[int(self.rng.integers(len(self.cfg.pallet_models)))]

    def add_stack(self, model_name: str, xy, yaw: float, count: int) -> list[PalletPlacement]:
        """A stack of empty pallets of one type (the top one may carry a load)."""
        h = get_pallet_model(model_name).size_m[2]
        out = []
        for k in range(count):
            yaw_k = yaw + math.radians(self.rng.uniform(-2, 2))
            xy_k = (xy[0] + self.rng.uniform(-0.015, 0.015), xy[1] + self.rng.uniform(-0.015, 0.015))
            out.append(self.add_pallet(model_name, xy_k, k * h, yaw_k, 2.0, load=k == count - 1))
        return out

    def free(self, xy, radius: float) -> bool:
        """No pallet or stack already stands within `radius` plus its own half diagonal of `xy` (floor)."""
        for p in self.pallets:
            r = np.linalg.norm(get_pallet_model(p.model_name).size_m[:2]) / 2
            if np.hypot(*(np.asarray(xy) - p.T_world_pallet[:2, 3])) < radius + r + 0.1:
                return False
        return True

    def add_load(self, p: PalletPlacement, clearance_m: float) -> None:
        """Boxes stacked on a pallet (cardboard layers, or a stretch-wrapped block)."""
        rng = self.rng
        model = get_pallet_model(p.model_name)
        L, W, H = model.size_m
        R = p.T_world_pallet[:3, :3]
        top = p.T_world_pallet[:3, 3] + R[:, 2] * (H / 2)
        max_h = min(clearance_m - 0.05, 1.6)
        if rng.random() < 0.25:
            h = rng.uniform(0.3, max_h)
            size = [L - rng.uniform(0.0, 0.06), W - rng.uniform(0.0, 0.06), h]
            color = np.array([0.82, 0.84, 0.86]) * rng.uniform(0.85, 1.05)
            self.boxes.append(_box(top + R[:, 2] * h / 2, size, "film", color, self.seed(), R=R))
            return
        bx, by, bz = rng.uniform(0.25, 0.6), rng.uniform(0.2, 0.4), rng.uniform(0.15, 0.4)
        nx, ny = max(int(L // bx), 1), max(int(W // by), 1)
        layers = int(rng.integers(1, max(int(max_h // bz), 1) + 1))
        base = np.array([0.66, 0.50, 0.33]) * rng.uniform(0.85, 1.1, 3)
        for k in range(layers):
            last = k == layers - 1
            for i in range(nx):
                for j in range(ny):
                    if rng.random() < (0.45 if last else 0.08):
                        continue   # missing boxes, mostly in the top layer
                    c = np.array([(i + 0.5) * L / nx - L / 2, (j + 0.5) * W / ny - W / 2, (k + 0.5) * bz])
                    c[:2] += rng.uniform(-0.01, 0.01, 2)
                    size = [L / nx - 0.01, W / ny - 0.01, bz - 0.002]
                    color = base * rng.uniform(0.93, 1.07, 3)
                    self.boxes.append(_box(top + R @ c, size, "cardboard", color, self.seed(), R=R))
            if not last and k >= 1 and rng.random() < 0.2:
                break

    # --- warehouse structures -------------------------------------------------------------------------
    def add_room(self, half_x: float, y_back: float, y_front: float, height: float) -> None:
        rng = self.rng
        floor_col = np.array([0.62, 0.62, 0.6]) * rng.uniform(0.8, 1.15) * rng.uniform(0.95, 1.05, 3)
        self.boxes.append(_box([0, 0, -0.05], [200, 200, 0.1], "concrete", floor_col, self.seed()))
        wall_col = np.array([0.85, 0.85, 0.82]) * rng.uniform(0.8, 1.05, 3)
        cy = (y_back + y_front) / 2
        span_y = y_back - y_front
        self.boxes.append(_box([0, y_back + 0.1, height / 2], [2 * half_x + 0.4, 0.2, height], "wall", wall_col,
                               self.seed()))
        self.boxes.append(_box([0, y_front - 0.1, height / 2], [2 * half_x + 0.4, 0.2, height], "wall", wall_col,
                               self.seed()))
        for sx in (-1, 1):
            self.boxes.append(_box([sx * (half_x + 0.1), cy, height / 2], [0.2, span_y, height], "wall", wall_col,
                                   self.seed()))
        self.boxes.append(_box([0, cy, height + 0.1], [2 * half_x, span_y, 0.2], "wall",
                               np.array([0.5, 0.5, 0.52]), self.seed()))

    def add_racks(self) -> tuple[list[int], float]:
        """A rack row; returns the instance ids of pallets in it and the row's half length."""
        rng, cfg = self.rng, self.cfg
        n_bays = int(rng.integers(3, 6))
        pitch = BAY_CLEAR_M + UPRIGHT_M[0]
        x0 = -n_bays * pitch / 2
        levels = [0.0]
        for _ in range(int(rng.integers(2, 4))):
            levels.append(levels[-1] + rng.uniform(1.45, 1.8) + (BEAM_H_M if levels[-1] == 0 else 0))
        top = levels[-1] + rng.uniform(0.9, 1.3)
        upright_col = [np.array([0.1, 0.25, 0.6]), np.array([0.15, 0.3, 0.2]), np.array([0.35, 0.37, 0.4])][
            int(rng.integers(3))] * rng.uniform(0.85, 1.15)
        beam_col = np.array([0.95, 0.45, 0.08]) * rng.uniform(0.85, 1.05, 3)
        for i in range(n_bays + 1):
            x = x0 + i * pitch
            for y in (UPRIGHT_M[1] / 2, RACK_DEPTH_M - UPRIGHT_M[1] / 2):
                self.boxes.append(_box([x, y, top / 2], [UPRIGHT_M[0], UPRIGHT_M[1], top], "metal", upright_col,
                                       self.seed()))
            for z in np.arange(0.3, top, 1.2):     # frame braces between front and back uprights
                self.boxes.append(_box([x, RACK_DEPTH_M / 2, z], [0.03, RACK_DEPTH_M - 0.16, 0.03], "metal",
                                       upright_col, self.seed()))
        ids = []
        for b in range(n_bays):
            xc = x0 + (b + 0.5) * pitch
            for li, z in enumerate(levels):
                if z > 0:
                    for y in (0.025, RACK_DEPTH_M - 0.025):
                        self.boxes.append(_box([xc, y, z - BEAM_H_M / 2], [BAY_CLEAR_M, 0.05, BEAM_H_M], "metal",
                                               beam_col, self.seed()))
                clearance = (levels[li + 1] - BEAM_H_M - z if li + 1 < len(levels) else 2.0) - 0.15
                model_name = cfg.pallet_models[int(rng.integers(len(cfg.pallet_models)))]
                model = get_pallet_model(model_name)
                n_slots = max(int(BAY_CLEAR_M // (model.size_m[1] + 0.07)), 1)
                gap = (BAY_CLEAR_M - n_slots * model.size_m[1]) / (n_slots + 1)
                for s in range(n_slots):
                    if rng.random() >= cfg.rack_fill:
                        continue
                    x = xc - BAY_CLEAR_M / 2 + gap + model.size_m[1] / 2 + s * (model.size_m[1] + gap)
                    jitter = math.radians(rng.uniform(-1, 1) * cfg.pallet_yaw_jitter_deg)
                    yaw = math.pi / 2 * (1 if rng.random() < 0.5 else -1) + jitter
                    xy = (x + rng.uniform(-0.02, 0.02), RACK_DEPTH_M / 2 + rng.uniform(-0.04, 0.04))
                    ids.append(self.add_pallet(model_name, xy, z, yaw, clearance - model.size_m[2]).instance_id)
        # Yellow floor line along the aisle.
        self.boxes.append(_box([0, -0.2, 0.0015], [n_bays * pitch, 0.08, 0.003], "plastic",
                               np.array([0.9, 0.75, 0.1]), self.seed()))
        return ids, n_bays * pitch / 2

    def add_occluder(self, xy: np.ndarray, yaw: float) -> None:
        rng = self.rng
        kind = rng.random()
        if kind < 0.5:   # a stack of cardboard boxes
            z = 0.0
            base = np.array([0.66, 0.50, 0.33]) * rng.uniform(0.85, 1.1, 3)
            for _ in range(int(rng.integers(1, 4))):
                size = rng.uniform([0.3, 0.3, 0.2], [0.7, 0.6, 0.5])
                self.boxes.append(_box([xy[0], xy[1], z + size[2] / 2], size, "cardboard",
                                       base * rng.uniform(0.93, 1.07, 3), self.seed(), yaw + rng.uniform(-0.2, 0.2)))
                z += size[2]
        elif kind < 0.8:  # a plastic bin or crate
            size = rng.uniform([0.4, 0.4, 0.4], [1.0, 0.8, 1.2])
            color = np.array([[0.1, 0.3, 0.7], [0.7, 0.1, 0.1], [0.2, 0.5, 0.2], [0.8, 0.7, 0.1]])[
                int(rng.integers(4))]
            self.boxes.append(_box([xy[0], xy[1], size[2] / 2], size, "plastic", color, self.seed(), yaw))
        else:             # a building column
            size = [0.4, 0.4, 8.0]
            self.boxes.append(_box([xy[0], xy[1], 4.0], size, "wall", np.array([0.7, 0.7, 0.68]), self.seed(), yaw))


def _camera_for(b: _Builder, target: PalletPlacement, approach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forklift camera facing `target` along the horizontal unit vector `approach`; returns (T_world_cam, eye)."""
    cfg, rng = b.cfg, b.rng
    model = get_pallet_model(target.model_name)
    centre = target.T_world_pallet[:3, 3]
    side = np.cross(approach, [0, 0, 1.0])
    half_depth = abs(approach @ target.T_world_pallet[:3, :3] @ (model.size_m / 2 * [1, 0, 0])) \
        + abs(approach @ target.T_world_pallet[:3, :3] @ (model.size_m / 2 * [0, 1, 0]))
    dist = rng.uniform(*cfg.target_distance_m) + half_depth
    lateral = rng.uniform(*cfg.lateral_offset_m)
    eye = centre - approach * dist + side * lateral
    eye[2] = centre[2] - model.size_m[2] / 2 + rng.uniform(*cfg.camera_above_pallet_m)
    # Aligned: look along the approach, pitched at the pallet centre; then the forklift's misalignment.
    look = centre - side * lateral if cfg.yaw_deg == 0 else centre
    T = look_at_T_world_cam(eye, look)
    d = [rng.uniform(-1, 1) * a for a in (cfg.pitch_deg, cfg.yaw_deg, cfg.roll_deg)]
    R_mis = _rot(0, math.radians(d[0])) @ _rot(1, math.radians(d[1])) @ _rot(2, math.radians(d[2]))
    T[:3, :3] = T[:3, :3] @ R_mis
    return T, eye


def _face_towards(p: PalletPlacement, direction_world: np.ndarray) -> str:
    """The face with fork pockets whose outward normal is closest to `direction_world`."""
    faces = list(get_pallet_model(p.model_name).pockets_m)
    if not faces:
        raise SceneError(f"{p.model_name} has no fork pockets: a forklift cannot pick it up")
    return max(faces, key=lambda f: float((p.T_world_pallet[:3, :3] @ face_normal(f)) @ direction_world))


def _yaw_facing(b: _Builder, model_name: str, direction_world, jitter_deg: float) -> float:
    """A yaw that turns one random pocket face of the model towards `direction_world` (+- jitter)."""
    faces = list(get_pallet_model(model_name).pockets_m)
    n = face_normal(faces[int(b.rng.integers(len(faces)))])
    return math.atan2(direction_world[1], direction_world[0]) - math.atan2(n[1], n[0]) \
        + math.radians(b.rng.uniform(-1, 1) * jitter_deg)


def _add_extras(b: _Builder, half_x: float, y_range: tuple[float, float], n_pallets: int, n_distractors: int,
                keep_out) -> None:
    """Pallets, stacks of empty pallets and distractors on the floor, away from `keep_out(xy)`."""
    rng = b.rng
    for _ in range(n_pallets):
        xy = np.array([rng.uniform(-half_x, half_x), rng.uniform(*y_range)])
        if keep_out(xy) or not b.free(xy, 0.75):
            continue
        model_name = b.random_model()
        yaw = rng.uniform(-math.pi, math.pi) if rng.random() < 0.5 else _yaw_facing(b, model_name, [0, -1, 0], 10)
        if rng.random() < 0.35:
            b.add_stack(model_name, xy, yaw, int(rng.integers(2, 8)))
        else:
            b.add_pallet(model_name, tuple(xy), 0.0, yaw, 2.0)
    for _ in range(n_distractors):
        xy = np.array([rng.uniform(-half_x, half_x), rng.uniform(*y_range)])
        if keep_out(xy) or not b.free(xy, 0.6):
            continue
        b.boxes.extend(distractor_boxes(rng, xy, rng.uniform(-math.pi, math.pi)))


def _build_forklift(b: _Builder) -> Scene:
    """The forklift's own view: a target pallet on the floor, in a rack, on a truck bed or on a stack of
    pallets, other pallets and clutter around, and the vehicle approaching it from the aisle (-y)."""
    cfg, rng = b.cfg, b.rng
    kind = rng.choice(["floor", "rack", "truck", "stack"], p=[0.4, 0.3, 0.15, 0.15])
    y_front = -cfg.target_distance_m[1] - 3.5
    half_x = rng.uniform(5.0, 9.0)
    back = (RACK_DEPTH_M + rng.uniform(0.2, 0.5) if kind == "rack" else rng.uniform(3.0, 4.0) if kind == "truck"
            else rng.uniform(2.0, 6.0))                    # the back wall
    if kind == "rack":
        rack_ids, half_len = b.add_racks()
        half_x = max(half_x, half_len + 1.0)
        low = [i for i in rack_ids if b.pallets[i - 1].T_world_pallet[2, 3] < cfg.cam_height_m[1] - 0.4]
        if not low:
            x = rng.uniform(-half_len + 1.0, half_len - 1.0)
            low = [b.add_pallet(b.random_model(), (x, RACK_DEPTH_M / 2), 0.0, math.pi / 2, 1.5).instance_id]
        target = b.pallets[low[int(rng.integers(len(low)))] - 1]
    elif kind == "truck":
        bed_h, bed_len = rng.uniform(1.0, 1.4), rng.uniform(6.0, 12.0)
        bed_y = 1.225
        b.boxes.extend(truck_bed_boxes(rng, (0.0, bed_y), 0.0, bed_len, bed_h))
        ids = []
        x = -bed_len / 2 + 0.1
        while True:
            model_name = b.random_model()
            size = get_pallet_model(model_name).size_m
            yaw = _yaw_facing(b, model_name, [0, -1, 0], 3)
            extent = abs(math.cos(yaw)) * size[0] + abs(math.sin(yaw)) * size[1]
            if x + extent > bed_len / 2 - 0.1:
                break
            depth = abs(math.sin(yaw)) * size[0] + abs(math.cos(yaw)) * size[1]
            y = bed_y - 1.225 + depth / 2 + rng.uniform(0.0, 0.08)
            if rng.random() < 0.85:
                ids.append(b.add_pallet(model_name, (x + extent / 2, y), bed_h, yaw, 2.5).instance_id)
            x += extent + rng.uniform(0.02, 0.3)
        if not ids:
            ids = [b.add_pallet(b.random_model(), (0.0, 0.6), bed_h, math.pi / 2, 2.5).instance_id]
        target = b.pallets[ids[int(rng.integers(len(ids)))] - 1]
    else:
        model_name = b.random_model()
        yaw = _yaw_facing(b, model_name, [0, -1, 0], 30)
        xy = (rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3))
        if kind == "stack":
            stack = b.add_stack(model_name, xy, yaw, int(rng.integers(2, 7)))
            low = [p for p in stack if p.T_world_pallet[2, 3] < cfg.cam_height_m[1] - 0.4]
            target = low[int(rng.integers(len(low)))]
        else:
            target = b.add_pallet(model_name, xy, 0.0, yaw, 2.0)
        for side in (-1, 1):   # neighbours in the same row
            if rng.random() < 0.6:
                gap = rng.uniform(0.05, 0.6)
                size = get_pallet_model(model_name).size_m
                nxy = (xy[0] + side * (max(size[:2]) + gap), xy[1] + rng.uniform(-0.1, 0.1))
                if b.free(nxy, 0.3):
                    b.add_pallet(b.random_model(), nxy, 0.0, yaw + math.radians(rng.uniform(-5, 5)), 2.0)
    b.add_room(half_x, back, y_front, rng.uniform(4.0, 9.0))
    face = _face_towards(target, np.array([0.0, -1.0, 0.0]))
    n_w = target.T_world_pallet[:3, :3] @ face_normal(face)
    centre = target.T_world_pallet[:3, 3]
    corridor = lambda xy: abs(xy[0] - centre[0]) < 1.6 and xy[1] < centre[1] + 0.8  # noqa: E731
    n_floor = int(rng.integers(cfg.floor_pallets[0], cfg.floor_pallets[1] + 1))
    _add_extras(b, half_x - 0.8, (y_front + 1.0, back - 0.8 if kind != "rack" else -1.0), n_floor,
                int(rng.integers(1, 5)), corridor)
    if rng.random() < cfg.pocket_obstacle_prob:
        b.boxes.extend(pocket_obstacle(rng, target, face))
    vehicle = place_forklift(rng, target, face, cfg.target_distance_m, cfg.approach_yaw_deg, cfg.K,
                             (cfg.height, cfg.width), cfg.cam_height_m)
    b.boxes.extend(vehicle.boxes)
    T_world_cam = vehicle.T_world_vehicle @ vehicle.T_vehicle_cam
    eye = T_world_cam[:3, 3]
    dist = float(np.linalg.norm(centre[:2] - eye[:2]))
    for _ in range(int(rng.integers(cfg.occluders[0], cfg.occluders[1] + 1))):
        if dist < 2.5:
            break
        f = rng.uniform(0.4, 0.75)
        xy = eye[:2] + f * (centre[:2] - eye[:2]) + np.array([-n_w[1], n_w[0]]) * rng.uniform(-0.9, 0.9)
        b.boxes.extend(distractor_boxes(rng, xy, rng.uniform(-0.4, 0.4)))
    light = _random_light(rng)
    return Scene(b.boxes, b.pallets, T_world_cam, cfg.K, (cfg.height, cfg.width), light, target.instance_id,
                 vehicle=vehicle)


def _random_light(rng: np.random.Generator) -> Light:
    light_dir = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.2, 0.8), -1.0])
    return Light(light_dir, intensity=rng.uniform(0.45, 0.8), ambient=rng.uniform(0.25, 0.45),
                 headlight=rng.uniform(0.05, 0.25))


def build_scene(cfg: SimConfig, rng: np.random.Generator) -> Scene:
    """Draw one random scene for `cfg` (not yet checked for target visibility: see generate.py)."""
    b = _Builder(cfg, rng)
    layout = cfg.layout
    if layout == "mixed":
        layout = LAYOUTS[int(rng.choice(3, p=cfg.view_probs))]
    if layout == "forklift":
        return _build_forklift(b)
    if layout == "warehouse":
        rack_ids, half_len = b.add_racks()
        y_front = -cfg.target_distance_m[1] - 3.5
        b.add_room(half_len + rng.uniform(1.5, 4.0), RACK_DEPTH_M + rng.uniform(0.2, 0.5), y_front, 9.0)
        aisle_ids = []
        for _ in range(int(rng.integers(cfg.floor_pallets[0], cfg.floor_pallets[1] + 1))):
            xy = (rng.uniform(-half_len + 0.8, half_len - 0.8), rng.uniform(-2.5, -1.0))
            if any(np.hypot(*(np.array(xy) - p.T_world_pallet[:2, 3])) < 1.6 for p in b.pallets if p.instance_id
                   in aisle_ids):
                continue
            aisle_ids.append(b.add_pallet(cfg.pallet_models[int(rng.integers(len(cfg.pallet_models)))], xy, 0.0,
                                          rng.uniform(-math.pi, math.pi), 2.0).instance_id)
        if cfg.rich_content:
            _add_extras(b, half_len, (y_front + 1.0, -1.0), int(rng.integers(0, 4)), int(rng.integers(0, 4)),
                        lambda xy: abs(xy[0]) < 1.0)
        candidates = rack_ids + aisle_ids
        if not candidates:   # an empty rack: put one pallet on the floor level so there is a target
            x = rng.uniform(-half_len + 1.0, half_len - 1.0)
            candidates = [b.add_pallet(cfg.pallet_models[0], (x, RACK_DEPTH_M / 2), 0.0, math.pi / 2, 1.5)
                          .instance_id]
        target = b.pallets[candidates[int(rng.integers(len(candidates)))] - 1]
        if target.instance_id in aisle_ids:
            x_axis = target.T_world_pallet[:3, 0].copy()
            x_axis[2] = 0
            approach = x_axis / np.linalg.norm(x_axis)
            if approach[1] < 0:  # approach from the aisle side, not from the rack
                approach = -approach
        else:
            approach = np.array([0.0, 1.0, 0.0])
    else:
        x_room, y_back = rng.uniform(3.0, 5.0), rng.uniform(1.0, 3.0)
        b.add_room(x_room, y_back, -cfg.target_distance_m[1] - 2.5, rng.uniform(2.6, 3.5))
        yaw = math.pi / 2 + math.radians(rng.uniform(-1, 1) * 10.0)
        target = b.add_pallet(cfg.pallet_models[int(rng.integers(len(cfg.pallet_models)))],
                              (rng.uniform(-0.5, 0.5), 0.0), 0.0, yaw, 2.0)
        for _ in range(int(rng.integers(1, 4))):   # clutter along the walls
            b.add_occluder(np.array([rng.uniform(-x_room + 0.5, x_room - 0.5), y_back - rng.uniform(0.4, 0.8)]),
                           rng.uniform(-0.3, 0.3))
        if cfg.rich_content:
            _add_extras(b, x_room - 0.8, (-cfg.target_distance_m[1] - 2.0, y_back - 0.8), int(rng.integers(0, 3)),
                        int(rng.integers(0, 3)), lambda xy: abs(xy[0]) < 1.5 and xy[1] < 1.0)
        approach = np.array([0.0, 1.0, 0.0])
    T_world_cam, eye = _camera_for(b, target, approach)
    # Occluders stand on the floor between the camera and the target.
    centre = target.T_world_pallet[:3, 3]
    for _ in range(int(rng.integers(cfg.occluders[0], cfg.occluders[1] + 1))):
        f = rng.uniform(0.35, 0.75)
        xy = eye[:2] + f * (centre[:2] - eye[:2]) + np.cross(approach, [0, 0, 1])[:2] * rng.uniform(-0.7, 0.7)
        b.add_occluder(xy, rng.uniform(-0.4, 0.4))
    return Scene(b.boxes, b.pallets, T_world_cam, cfg.K, (cfg.height, cfg.width), _random_light(rng),
                 target.instance_id)
