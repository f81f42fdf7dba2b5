"""Several coloured lights with shadows for ray-cast box scenes.

Shadows are exact shadow rays: for each light, every lit surface point's segment to the light is tested
against the boxes that can block it. The boxes are culled as the ray caster culls them: seen from the light,
a segment to a point projects to that point's image position, so only the boxes whose screen rectangle
(in the light's view) holds the point can block it. Points are binned on a grid in the light's view and each
box is tested against the points of the cells its rectangle covers.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pallet6d.sim.raycast import box_screen_rects
from pallet6d.sim.shading import SurfaceHits

__all__ = ["PointLight", "shadow_visibility", "light_hits", "ambient_occlusion"]


@dataclass(frozen=True)
class PointLight:
    """A lamp: position (world, metres), RGB colour, intensity at `ref_m`, spot cone about `axis_world`.

    Irradiance falls off as (ref_m / d)^2; outside the cone (half angle `cone_deg`) it fades to 0 over 10 deg.
    """

    position_world: np.ndarray
    color: np.ndarray
    intensity: float
    axis_world: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    cone_deg: float = 70.0
    ref_m: float = 4.0

    def __post_init__(self) -> None:
        for name in ("position_world", "color", "axis_world"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"PointLight.{name} must be a finite (3,) vector, got {v}")
            object.__setattr__(self, name, v)
        if np.linalg.norm(self.axis_world) == 0 or self.intensity < 0 or not 0 < self.cone_deg <= 89:
            raise ValueError(f"PointLight: axis must be non-zero, intensity >= 0, cone in (0, 89] deg: {self}")
        object.__setattr__(self, "axis_world", self.axis_world / np.linalg.norm(self.axis_world))


def _basis(z: np.ndarray) -> np.ndarray:
    """(3, 3) rows x, y, z of a right-handed frame whose z is the unit vector `z`."""
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def shadow_visibility(points_cam: np.ndarray, light_cam: np.ndarray, axis_cam: np.ndarray, R_cam_box: np.ndarray,
                      t_cam_box: np.ndarray, half_m: np.ndarray, max_tan: float = 4.0, grid: int = 96,
                      end_gap_m: float = 0.002) -> np.ndarray:
    """Which points see the light (no box on the segment between them).

    :param points_cam: (P, 3) surface points, camera frame. :param light_cam: (3,) light position.
    :param axis_cam: (3,) unit direction the light faces; points behind it, or more than atan(max_tan) off it,
        are reported unlit. :param R_cam_box, t_cam_box, half_m: (N, 3, 3), (N, 3), (N, 3) the boxes.
    :param end_gap_m: the last bit of each segment (at the surface point) that is not tested.
    :return: (P,) bool, True = lit.
    """
    axis = np.asarray(axis_cam, np.float64)
    B = _basis(axis / np.linalg.norm(axis))
    light = np.asarray(light_cam, np.float64)
    q = (np.asarray(points_cam, np.float64) - light) @ B.T                # points in the light frame
    lit = np.zeros(len(q), dtype=bool)
    front = q[:, 2] > 1e-6
    u = np.where(front, q[:, 0] / np.where(front, q[:, 2], 1), np.inf)
    v = np.where(front, q[:, 1] / np.where(front, q[:, 2], 1), np.inf)
    cand = np.flatnonzero(front & (np.abs(u) < max_tan) & (np.abs(v) < max_tan))
    if cand.size == 0:
        return lit
    u, v = u[cand], v[cand]
    lo_u, lo_v = u.min(), v.min()
    span = max(u.max() - lo_u, v.max() - lo_v, 1e-3)
    scale = (grid - 1) / span
    cu = np.clip(np.floor((u - lo_u) * scale + 0.5), 0, grid - 1).astype(np.int64)
    cv = np.clip(np.floor((v - lo_v) * scale + 0.5), 0, grid - 1).astype(np.int64)
    key = cv * grid + cu
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(grid * grid + 1))
    K_light = np.array([[scale, 0, -lo_u * scale], [0, scale, -lo_v * scale], [0, 0, 1.0]])
    R_l = np.einsum("ij,njk->nik", B, np.asarray(R_cam_box, np.float64))
    t_l = (np.asarray(t_cam_box, np.float64) - light) @ B.T
    half = np.asarray(half_m, np.float64)
    rects = box_screen_rects(R_l, t_l, half, K_light, (grid, grid), near_m=1e-4)
    rects[:, :2] = np.maximum(rects[:, :2] - 1, 0)                          # cells a point may round into
    rects[:, 2:] = np.minimum(rects[:, 2:] + 1, grid)
    # Candidate points per box from a summed-area table of the cell counts: boxes with none are skipped.
    counts = np.diff(starts).reshape(grid, grid)
    sat = np.zeros((grid + 1, grid + 1), np.int64)
    sat[1:, 1:] = counts.cumsum(0).cumsum(1)
    u0s, v0s, u1s, v1s = rects.T
    n_cand = sat[v1s, u1s] - sat[v0s, u1s] - sat[v1s, u0s] + sat[v0s, u0s]
    blocked = np.zeros(cand.size, dtype=bool)
    qx, qy, qz = (np.ascontiguousarray(q[cand, k], dtype=np.float32) for k in range(3))
    seg_len = np.linalg.norm(q[cand], axis=1)
    t_end = 1.0 - end_gap_m / np.maximum(seg_len, 1e-9)
    for i in np.flatnonzero((rects[:, 2] > rects[:, 0]) & (rects[:, 3] > rects[:, 1]) & (n_cand > 0)):
        u0, v0, u1, v1 = rects[i]
        if (v1 - v0) * (u1 - u0) > grid * grid // 4:
            idx = np.flatnonzero((cu >= u0) & (cu < u1) & (cv >= v0) & (cv < v1))
        else:
            parts = [order[starts[r * grid + u0]:starts[r * grid + u1]] for r in range(v0, v1)]
            idx = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        idx = idx[~blocked[idx]]
        if idx.size == 0:
            continue
        # Segment light -> point, parameter s in [0, 1], in the box's frame: x(s) = o + s * d.
        o = R_l[i].T @ (-t_l[i])
        Ri = R_l[i].astype(np.float32)
        g = (qx[idx], qy[idx], qz[idx])

        def direction(a: int, g=g, Ri=Ri) -> np.ndarray:
            return g[0] * Ri[0, a] + g[1] * Ri[1, a] + g[2] * Ri[2, a]

        # Where the light is outside the box beyond a face, only points behind that face's plane can be
        # blocked (a floor under every point blocks nothing): this culls most pairs before the slab test.
        keep = None
        for a in np.flatnonzero(np.abs(o) > half[i]):
            k = np.sign(o[a]) * (np.float32(o[a]) + direction(a)) < half[i, a]
            keep = k if keep is None else keep & k
        if keep is not None:
            idx = idx[keep]
            if idx.size == 0:
                continue
            g = (g[0][keep], g[1][keep], g[2][keep])
        s_near = np.full(idx.size, -np.inf, np.float32)
        s_far = np.full(idx.size, np.inf, np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            for a in range(3):
                inv = np.float32(1.0) / direction(a, g)
                s1 = np.float32(-half[i, a] - o[a]) * inv
                s2 = np.float32(half[i, a] - o[a]) * inv
                np.maximum(s_near, np.minimum(s1, s2), out=s_near)
                np.minimum(s_far, np.maximum(s1, s2), out=s_far)
        hit = (s_near <= s_far) & (s_far > 1e-7) & (s_near < t_end[idx])
        blocked[idx[hit]] = True
    lit[cand] = ~blocked
    return lit


def _shadow_samples(hits: SurfaceHits, need: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Which hits get an exact shadow ray: those on even rows and columns, and every hit whose 2x2 block's
    anchor (top-left pixel) lies on another box face or is unlit; the rest copy their anchor's visibility
    (shadow edges are then 2 px steps, a quarter of the rays).

    :return: hit indices to trace, and (hits that copy, the anchor hits they copy from).
    """
    h, w = hits.image_hw
    hit_at = np.full(h * w, -1, dtype=np.int64)
    hit_at[hits.pix] = np.arange(hits.pix.size)
    r, c = np.divmod(hits.pix[need], w)
    anchor = hit_at[(r - r % 2) * w + (c - c % 2)]
    is_anchor = (r % 2 == 0) & (c % 2 == 0)
    a = np.maximum(anchor, 0)
    same = (anchor >= 0) & (hits.box[a] == hits.box[need]) & (hits.axis[a] == hits.axis[need]) & (e[a] > 1e-4)
    exact = is_anchor | ~same
    return need[exact], (need[~exact], anchor[~exact])


def light_hits(hits: SurfaceHits, light: PointLight, T_cam_world: np.ndarray, boxes: tuple, shadows: bool
               ) -> np.ndarray:
    """(P,) float32 irradiance of each hit from one light: cos(incidence) x fall-off x cone x shadow.

    :param boxes: (R_cam_box (N, 3, 3), t_cam_box (N, 3), half_m (N, 3)).
    """
    R_cw, t_cw = T_cam_world[:3, :3], T_cam_world[:3, 3]
    axis = R_cw @ light.axis_world
    pos = R_cw @ light.position_world + t_cw
    to_light = pos[None] - hits.p_cam.astype(np.float64)
    dist = np.linalg.norm(to_light, axis=1)
    l_dir = to_light / np.maximum(dist, 1e-9)[:, None]
    cos_i = np.maximum((hits.normal_cam * l_dir).sum(1), 0)
    falloff = (light.ref_m / np.maximum(dist, 1.0)) ** 2          # no flare where a lamp nearly touches a wall
    off = np.degrees(np.arccos(np.clip(-(l_dir @ axis), -1, 1)))
    cone = np.clip((light.cone_deg + 10.0 - off) / 10.0, 0, 1)
    e = light.intensity * cos_i * falloff * cone
    if shadows:
        need = np.flatnonzero(e > 1e-4)
        exact, copy_from = _shadow_samples(hits, need, e)
        if exact.size:
            max_tan = np.tan(np.radians(min(light.cone_deg + 10.0, 84.0))) * 1.05
            vis = np.zeros(len(e), dtype=bool)
            vis[exact] = shadow_visibility(hits.p_cam[exact], pos, axis, *boxes, max_tan=max_tan)
            vis[copy_from[0]] = vis[copy_from[1]]
            e[need[~vis[need]]] = 0.0
    return e.astype(np.float32)


def ambient_occlusion(hits: SurfaceHits, radius_m: float = 0.5, step: int = 2) -> np.ndarray:
    """(P,) float32 in [0, 1]: how much of each hit's hemisphere nearby visible surfaces cover (screen space).

    For each pixel (on a grid `step` pixels apart), neighbours on rings whose points stand in front of its
    tangent plane within `radius_m` occlude it, weighted by how steeply they rise: pallet pockets, the foot
    of a load and the floor under a rack come out dark, flat open surfaces stay at 0.
    """
    h, w = hits.image_hw
    p = hits.to_image(hits.p_cam)[::step, ::step]
    n = hits.to_image(hits.normal_cam)[::step, ::step]
    px, py, pz = (np.ascontiguousarray(p[..., k]) for k in range(3))
    nx, ny, nz = (np.ascontiguousarray(n[..., k]) for k in range(3))
    valid = pz > 0
    hs, ws = valid.shape
    occ = np.zeros((hs, ws), np.float32)
    count = 0
    for r in (2, 4, 8, 14):
        for k in range(8):
            ang = 2 * np.pi * (k + 0.5 * (r % 4 == 0)) / 8
            dy, dx = int(round(r * np.sin(ang))), int(round(r * np.cos(ang)))
            count += 1
            if abs(dy) >= hs or abs(dx) >= ws:
                continue
            ys, yd = (slice(dy, hs), slice(0, hs - dy)) if dy >= 0 else (slice(0, hs + dy), slice(-dy, hs))
            xs, xd = (slice(dx, ws), slice(0, ws - dx)) if dx >= 0 else (slice(0, ws + dx), slice(-dx, ws))
            ex, ey, ez = px[ys, xs] - px[yd, xd], py[ys, xs] - py[yd, xd], pz[ys, xs] - pz[yd, xd]
            dist = np.sqrt(ex * ex + ey * ey + ez * ez) + np.float32(1e-6)
            rise = (nx[yd, xd] * ex + ny[yd, xd] * ey + nz[yd, xd] * ez) / dist   # sine of the neighbour's elevation
            near = np.clip(1 - dist / np.float32(radius_m), 0, 1)
            occ[yd, xd] += np.clip(rise - np.float32(0.1), 0, 1) * near * (valid[ys, xs] & valid[yd, xd])
    ao = np.clip(3.0 * occ / count, 0, 1)
    full = np.repeat(np.repeat(ao, step, 0), step, 1)[:h, :w]
    return full.reshape(-1)[hits.pix]
