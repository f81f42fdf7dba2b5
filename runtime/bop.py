"""Reading and writing datasets in the BOP format (numpy + OpenCV + json).

Layout (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md)::

    ROOT/models/models_info.json, obj_000001.ply, ...
    ROOT/<split>/<scene_id:06d>/scene_camera.json    cam_K (3x3 row-major), depth_scale [, cam_R_w2c, cam_t_w2c]
                               scene_gt.json        per image: [{cam_R_m2c, cam_t_m2c (mm), obj_id}, ...]
                               scene_gt_info.json   per image: [{bbox_obj, bbox_visib, px_count_*, visib_fract}]
                               rgb/{im_id:06d}.png|.jpg   (or gray/)
                               depth/{im_id:06d}.png      uint16, depth_mm = value * depth_scale
                               mask/{im_id:06d}_{gt_idx:06d}.png, mask_visib/... (optional)
                               scene_forklift.json  per image: {cam_R_c2v, cam_t_c2v (mm) or null, ...} (optional;
                                                    this project's forklift views, docs/sim-scenes.md)

Depth units: the writer stores millimetres (`depth_scale` 1.0): 1 mm steps, up to 65.535 m; pixels
beyond that are stored as 0 (no data). The reader honours any `depth_scale` (e.g. 0.1 in some BOP sets).
Datasets made elsewhere load as well: missing masks give None, missing scene_gt_info gives None boxes
and NaN visible fractions, missing depth gives zeros, rgb may be .jpg or grayscale.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

__all__ = ["BopFormatError", "BopGT", "BopFrame", "BopWriter", "BopDataset", "models_info_entry",
           "write_models_info", "read_models_info", "read_ply_mesh", "sample_surface"]

log = logging.getLogger(__name__)
_IMG_EXTS = (".png", ".jpg", ".jpeg", ".tif")


class BopFormatError(ValueError):
    """A BOP file is missing, not JSON, or has a missing/malformed field (the message names both)."""


@dataclass
class BopGT:
    """One annotated object instance in an image.

    T_cam_model: (4, 4) metres. bbox_*_xywh: (4,) int or None when unknown. mask_visib / mask: (H, W) bool or None.
    """

    obj_id: int
    T_cam_model: np.ndarray
    bbox_obj_xywh: np.ndarray | None = None
    bbox_visib_xywh: np.ndarray | None = None
    visib_fract: float = math.nan
    mask_visib: np.ndarray | None = None
    mask: np.ndarray | None = None
    px_count_all: int | None = None
    px_count_visib: int | None = None
    px_count_valid: int | None = None

    def __post_init__(self) -> None:
        self.T_cam_model = np.asarray(self.T_cam_model, dtype=np.float64)
        if self.T_cam_model.shape != (4, 4):
            raise ValueError(f"BopGT.T_cam_model must be (4, 4), got {self.T_cam_model.shape}")
        for name in ("bbox_obj_xywh", "bbox_visib_xywh"):
            box = getattr(self, name)
            if box is not None:
                box = np.asarray(box, dtype=np.int64).reshape(-1)
                if box.shape != (4,):
                    raise ValueError(f"BopGT.{name} must be (4,) x, y, w, h, got shape {box.shape}")
                setattr(self, name, box)


@dataclass
class BopFrame:
    """One image: rgb (H, W, 3) uint8 RGB, depth_m (H, W) float32 metres (0 = none), K (3, 3).

    depth_units: (H, W) uint16, the depth image as stored, in units of `depth_scale_mm` millimetres (a camera
    source hands these out unchanged); None when the frame was not read from a dataset.
    T_vehicle_cam: (4, 4) metres, the camera's calibration on its vehicle (scene_forklift.json), else None.
    """

    scene_id: int
    im_id: int
    rgb: np.ndarray
    depth_m: np.ndarray
    K: np.ndarray
    depth_scale_mm: float
    gts: list[BopGT]
    T_cam_world: np.ndarray | None = None
    depth_units: np.ndarray | None = None
    T_vehicle_cam: np.ndarray | None = None

    def __post_init__(self) -> None:
        h, w = self.depth_m.shape
        if self.rgb.shape != (h, w, 3):
            raise ValueError(f"BopFrame: rgb {self.rgb.shape} does not match depth ({h}, {w})")
        if self.K.shape != (3, 3):
            raise ValueError(f"BopFrame: K must be (3, 3), got {self.K.shape}")
        if self.depth_units is not None and (self.depth_units.shape != (h, w) or self.depth_units.dtype != np.uint16):
            raise ValueError(f"BopFrame: depth_units must be ({h}, {w}) uint16, got {self.depth_units.shape} "
                             f"{self.depth_units.dtype}")


# --- JSON helpers -------------------------------------------------------------------------------------

def _read_json(path: Path) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise BopFormatError(f"{path}: file not found") from None
    except json.JSONDecodeError as exc:
        raise BopFormatError(f"{path}: not valid JSON ({exc})") from None


def _field(entry: Any, key: str, path: Path, where: str, n: int | None = None) -> Any:
    """entry[key], checked: a finite number (n None) or a list of n finite numbers."""
    if not isinstance(entry, dict) or key not in entry:
        raise BopFormatError(f"{path}: {where}: missing field '{key}'")
    value = entry[key]
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise BopFormatError(f"{path}: {where}: field '{key}' must be numeric, got {value!r}") from None
    if (n is None and arr.ndim != 0) or (n is not None and arr.shape != (n,)) or not np.all(np.isfinite(arr)):
        want = "a finite number" if n is None else f"a list of {n} finite numbers"
        raise BopFormatError(f"{path}: {where}: field '{key}' must be {want}, got {value!r}")
    return arr if n is not None else float(arr)


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=1)
    tmp.replace(path)


def _int_key(k: str, path: Path, what: str = "an image id") -> int:
    try:
        return int(k)
    except ValueError:
        raise BopFormatError(f"{path}: key {k!r} is not {what}") from None


def _read_image_map(path: Path, lists: bool = False) -> dict[int, Any]:
    """A per-scene JSON file keyed by image id -> {im_id: entry}; `lists`: every entry must be a list."""
    raw = _read_json(path)
    if not isinstance(raw, dict):
        raise BopFormatError(f"{path}: expected an object keyed by image id")
    out = {}
    for k, entry in raw.items():
        im_id = _int_key(k, path)
        if lists and not isinstance(entry, list):
            raise BopFormatError(f"{path}: image {im_id}: expected a list of annotations")
        out[im_id] = entry
    return out


def _pose_from_mm(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """4x4 metres from a BOP rotation (9 values) and translation in millimetres."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.reshape(3, 3), t_mm / 1000.0
    return T


# --- models ----------------------------------------------------------------------------------------------

def models_info_entry(diameter_m: float, min_m, size_m, symmetries: np.ndarray | None = None) -> dict:
    """A models_info.json entry (millimetres) from metric quantities.

    :param min_m: (3,) minimum corner of the model's bounding box. :param size_m: (3,) its size.
    :param symmetries: optional (S, 4, 4) transforms in metres; the identity is dropped (BOP lists only
        the non-trivial ones).
    """
    entry = {"diameter": float(diameter_m) * 1000.0}
    for axis, lo, size in zip("xyz", np.asarray(min_m, dtype=np.float64), np.asarray(size_m, dtype=np.float64)):
        entry[f"min_{axis}"] = lo * 1000.0
        entry[f"size_{axis}"] = size * 1000.0
    if symmetries is not None:
        syms = []
        for T in np.asarray(symmetries, dtype=np.float64).reshape(-1, 4, 4):
            if np.allclose(T, np.eye(4)):
                continue
            T = T.copy()
            T[:3, 3] *= 1000.0
            syms.append([float(v) for v in T.ravel()])
        if syms:
            entry["symmetries_discrete"] = syms
    return entry


def write_models_info(root, infos: dict[int, dict]) -> Path:
    """Write ROOT/models/models_info.json from {obj_id: models_info_entry(...)}."""
    path = Path(root) / "models" / "models_info.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_json(path, {str(int(k)): v for k, v in sorted(infos.items())})
    return path


def read_models_info(path) -> dict[int, dict]:
    """models_info.json as {obj_id: entry}, with the fields the runtime uses checked."""
    path = Path(path)
    raw = _read_json(path)
    if not isinstance(raw, dict):
        raise BopFormatError(f"{path}: expected an object keyed by obj_id")
    out = {}
    for k, entry in raw.items():
        obj_id = _int_key(k, path, "an obj_id")
        _field(entry, "diameter", path, f"obj_id {obj_id}")
        for i, T in enumerate(entry.get("symmetries_discrete", [])):
            _field({"symmetries_discrete": T}, "symmetries_discrete", path, f"obj_id {obj_id} symmetry {i}", 16)
        out[obj_id] = entry
    return out


def _rot_about(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx


def symmetries_from_info(entry: dict, continuous_steps: int = 36) -> np.ndarray:
    """(S, 4, 4) symmetry transforms in metres, identity first, from one models_info entry.

    Continuous symmetries (axis, offset in mm) are discretised into `continuous_steps` rotations and
    combined with the discrete ones.
    """
    discrete = [np.eye(4)]
    for T in entry.get("symmetries_discrete", []):
        T = np.asarray(T, dtype=np.float64).reshape(4, 4).copy()
        T[:3, 3] /= 1000.0
        if not np.allclose(T, np.eye(4)):
            discrete.append(T)
    continuous = [np.eye(4)]
    for sym in entry.get("symmetries_continuous", []):
        axis = np.asarray(sym["axis"], dtype=np.float64)
        offset = np.asarray(sym.get("offset", [0, 0, 0]), dtype=np.float64) / 1000.0
        for k in range(1, continuous_steps):
            R = _rot_about(axis, 2 * math.pi * k / continuous_steps)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = offset - R @ offset
            continuous.append(T)
    return np.stack([c @ d for c in continuous for d in discrete])


# --- writing ------------------------------------------------------------------------------------------

class BopWriter:
    """Writes frames into ROOT/<split>/<scene_id:06d>/; the scene JSON files are written on `close()`
    (and whenever a new scene starts). Use as a context manager.

    :param depth_scale_mm: millimetres per depth PNG unit (1.0: mm).
    """

    def __init__(self, root, split: str = "train", depth_scale_mm: float = 1.0, write_full_masks: bool = True):
        if not depth_scale_mm > 0:
            raise ValueError(f"depth_scale_mm must be positive, got {depth_scale_mm}")
        if not split or "/" in split or split.startswith("models"):
            raise ValueError(f"invalid split name {split!r}")
        self.root, self.split = Path(root), split
        self.depth_scale_mm = float(depth_scale_mm)
        self.write_full_masks = write_full_masks
        self._scene_id: int | None = None
        self._camera: dict[str, dict] = {}
        self._gt: dict[str, list] = {}
        self._info: dict[str, list] = {}

    def scene_dir(self, scene_id: int) -> Path:
        return self.root / self.split / f"{int(scene_id):06d}"

    def write_frame(self, scene_id: int, im_id: int, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                    gts: list[BopGT], T_cam_world: np.ndarray | None = None) -> None:
        """Write one image with its annotations.

        :param rgb: (H, W, 3) uint8 RGB. :param depth_m: (H, W) metres, 0 = none. :param K: (3, 3).
        :param gts: annotations; their masks (H, W) bool are written when present.
        """
        rgb = np.asarray(rgb)
        depth_m = np.asarray(depth_m, dtype=np.float64)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        if depth_m.shape != rgb.shape[:2]:
            raise ValueError(f"depth_m shape {depth_m.shape} does not match rgb {rgb.shape[:2]}")
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        if self._scene_id is not None and scene_id != self._scene_id:
            self.flush()
        self._scene_id = int(scene_id)
        d = self.scene_dir(scene_id)
        for sub in ("rgb", "depth", "mask_visib") + (("mask",) if self.write_full_masks else ()):
            (d / sub).mkdir(parents=True, exist_ok=True)
        name = f"{int(im_id):06d}"
        cv2.imwrite(str(d / "rgb" / f"{name}.png"), rgb[:, :, ::-1])
        units = np.round(np.nan_to_num(depth_m, nan=0.0) * 1000.0 / self.depth_scale_mm)
        units[(units < 0) | (units > 65535)] = 0
        cv2.imwrite(str(d / "depth" / f"{name}.png"), units.astype(np.uint16))
        cam = {"cam_K": [float(v) for v in K.ravel()], "depth_scale": self.depth_scale_mm}
        if T_cam_world is not None:
            T_cam_world = np.asarray(T_cam_world, dtype=np.float64)
            cam["cam_R_w2c"] = [float(v) for v in T_cam_world[:3, :3].ravel()]
            cam["cam_t_w2c"] = [float(v) * 1000.0 for v in T_cam_world[:3, 3]]
        self._camera[str(int(im_id))] = cam
        gt_list, info_list = [], []
        for k, gt in enumerate(gts):
            gt_list.append({"cam_R_m2c": [float(v) for v in gt.T_cam_model[:3, :3].ravel()],
                            "cam_t_m2c": [float(v) * 1000.0 for v in gt.T_cam_model[:3, 3]],
                            "obj_id": int(gt.obj_id)})
            info = {"bbox_obj": _box_list(gt.bbox_obj_xywh), "bbox_visib": _box_list(gt.bbox_visib_xywh),
                    "visib_fract": None if math.isnan(gt.visib_fract) else float(gt.visib_fract)}
            for key in ("px_count_all", "px_count_visib", "px_count_valid"):
                info[key] = None if getattr(gt, key) is None else int(getattr(gt, key))
            info_list.append(info)
            for sub, mask in (("mask_visib", gt.mask_visib), ("mask", gt.mask if self.write_full_masks else None)):
                if mask is not None:
                    if mask.shape != depth_m.shape:
                        raise ValueError(f"gt {k} {sub} shape {mask.shape} does not match the image {depth_m.shape}")
                    cv2.imwrite(str(d / sub / f"{name}_{k:06d}.png"), mask.astype(np.uint8) * 255)
        self._gt[str(int(im_id))] = gt_list
        self._info[str(int(im_id))] = info_list

    def flush(self) -> None:
        """Write the current scene's JSON files (merging with files already there)."""
        if self._scene_id is None:
            return
        d = self.scene_dir(self._scene_id)
        d.mkdir(parents=True, exist_ok=True)
        for fname, new in (("scene_camera.json", self._camera), ("scene_gt.json", self._gt),
                           ("scene_gt_info.json", self._info)):
            path = d / fname
            data = _read_json(path) if path.exists() else {}
            data.update(new)
            _write_json(path, dict(sorted(data.items(), key=lambda kv: int(kv[0]))))
        self._camera, self._gt, self._info = {}, {}, {}

    def close(self) -> None:
        self.flush()
        self._scene_id = None

    def __enter__(self) -> "BopWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _box_list(box) -> list[int]:
    return [-1, -1, 0, 0] if box is None else [int(v) for v in np.asarray(box).reshape(4)]


# --- reading ------------------------------------------------------------------------------------------

def _find_image(folder: Path, name: str) -> Path | None:
    for ext in _IMG_EXTS:
        p = folder / f"{name}{ext}"
        if p.exists():
            return p
    return None


class BopDataset:
    """Frames of one split of a BOP dataset, in order of (scene_id, im_id).

    :param root: dataset root (holding `models/` and the split folders).
    :param split: split folder name; None picks the only split present (ValueError when several).
    """

    def __init__(self, root, split: str | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise ValueError(f"BOP dataset root {self.root} is not a directory")
        splits = sorted(p.name for p in self.root.iterdir()
                        if p.is_dir() and not p.name.startswith("models") and _scene_dirs(p))
        if split is None:
            if len(splits) != 1:
                raise ValueError(f"{self.root}: pass split=..., found {len(splits)} splits: {splits}")
            split = splits[0]
        elif split not in splits:
            raise ValueError(f"{self.root}: no split {split!r} (with scene folders); found {splits}")
        self.split = split
        info_path = self.root / "models" / "models_info.json"
        self.models_info: dict[int, dict] = read_models_info(info_path) if info_path.exists() else {}
        self._scenes: dict[int, dict[str, Any]] = {}
        self._index: list[tuple[int, int]] = []
        for scene_dir in _scene_dirs(self.root / split):
            scene_id = int(scene_dir.name)
            scene = self._load_scene(scene_dir)
            self._scenes[scene_id] = scene
            self._index.extend((scene_id, im_id) for im_id in sorted(scene["camera"]))
        log.debug("BOP %s/%s: %d frames in %d scenes", self.root, split, len(self._index), len(self._scenes))

    @staticmethod
    def _load_scene(d: Path) -> dict[str, Any]:
        cam_path = d / "scene_camera.json"
        camera = {}
        for im_id, entry in _read_image_map(cam_path).items():
            K = _field(entry, "cam_K", cam_path, f"image {im_id}", 9).reshape(3, 3)
            scale = _field(entry, "depth_scale", cam_path, f"image {im_id}") if "depth_scale" in entry else 1.0
            if not scale > 0:
                raise BopFormatError(f"{cam_path}: image {im_id}: field 'depth_scale' must be positive, got {scale}")
            T = None
            if "cam_R_w2c" in entry and "cam_t_w2c" in entry:
                T = _pose_from_mm(_field(entry, "cam_R_w2c", cam_path, f"image {im_id}", 9),
                                  _field(entry, "cam_t_w2c", cam_path, f"image {im_id}", 3))
            camera[im_id] = (K, scale, T)
        gt: dict[int, list] = {}
        gt_path = d / "scene_gt.json"
        if gt_path.exists():
            for im_id, entries in _read_image_map(gt_path, lists=True).items():
                items = []
                for j, e in enumerate(entries):
                    where = f"image {im_id} annotation {j}"
                    R = _field(e, "cam_R_m2c", gt_path, where, 9).reshape(3, 3)
                    t = _field(e, "cam_t_m2c", gt_path, where, 3)
                    obj = _field(e, "obj_id", gt_path, where)
                    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
                        raise BopFormatError(f"{gt_path}: {where}: field 'cam_R_m2c' is not a rotation matrix")
                    if obj != int(obj) or obj < 1:
                        raise BopFormatError(f"{gt_path}: {where}: field 'obj_id' must be a positive integer")
                    items.append((int(obj), _pose_from_mm(R, t)))
                gt[im_id] = items
        info: dict[int, list] = {}
        info_path = d / "scene_gt_info.json"
        if info_path.exists():
            for im_id, entries in _read_image_map(info_path).items():
                if not isinstance(entries, list) or len(entries) != len(gt.get(im_id, [])):
                    raise BopFormatError(f"{info_path}: image {im_id}: expected one entry per scene_gt.json "
                                         f"annotation ({len(gt.get(im_id, []))})")
                items = []
                for j, e in enumerate(entries):
                    where = f"image {im_id} annotation {j}"
                    vf = e.get("visib_fract") if isinstance(e, dict) else None
                    items.append({
                        "bbox_obj": _field(e, "bbox_obj", info_path, where, 4).astype(np.int64),
                        "bbox_visib": _field(e, "bbox_visib", info_path, where, 4).astype(np.int64),
                        "visib_fract": math.nan if vf is None else _field(e, "visib_fract", info_path, where),
                        **{key: (int(e[key]) if e.get(key) is not None else None)
                           for key in ("px_count_all", "px_count_visib", "px_count_valid")},
                    })
                info[im_id] = items
        vehicle: dict[int, np.ndarray] = {}
        forklift_path = d / "scene_forklift.json"
        if forklift_path.exists():
            for im_id, e in _read_image_map(forklift_path).items():
                if isinstance(e, dict) and e.get("cam_R_c2v") is not None:
                    where = f"image {im_id}"
                    R = _field(e, "cam_R_c2v", forklift_path, where, 9).reshape(3, 3)
                    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
                        raise BopFormatError(f"{forklift_path}: {where}: field 'cam_R_c2v' is not a rotation matrix")
                    vehicle[im_id] = _pose_from_mm(R, _field(e, "cam_t_c2v", forklift_path, where, 3))
        return {"dir": d, "camera": camera, "gt": gt, "info": info, "vehicle": vehicle}

    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, i: int) -> BopFrame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        scene_id, im_id = self._index[i]
        s = self._scenes[scene_id]
        d: Path = s["dir"]
        K, scale, T_cam_world = s["camera"][im_id]
        name = f"{im_id:06d}"
        rgb_path = _find_image(d / "rgb", name) or _find_image(d / "gray", name)
        if rgb_path is None:
            raise BopFormatError(f"{d}: no rgb/ or gray/ image for image id {im_id}")
        img = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
        if img is None:
            raise BopFormatError(f"{rgb_path}: unreadable image")
        rgb = np.ascontiguousarray(img[:, :, ::-1])
        depth_units = _read_depth_units(d / "depth", name, rgb.shape[:2])
        depth_m = depth_units.astype(np.float32) * np.float32(scale / 1000.0)
        gts = []
        infos = s["info"].get(im_id)
        for j, (obj_id, T) in enumerate(s["gt"].get(im_id, [])):
            info = infos[j] if infos is not None else {}
            gts.append(BopGT(
                obj_id=obj_id, T_cam_model=T.copy(), bbox_obj_xywh=info.get("bbox_obj"),
                bbox_visib_xywh=info.get("bbox_visib"), visib_fract=info.get("visib_fract", math.nan),
                mask_visib=_read_mask(d / "mask_visib" / f"{name}_{j:06d}.png", rgb.shape[:2]),
                mask=_read_mask(d / "mask" / f"{name}_{j:06d}.png", rgb.shape[:2]),
                px_count_all=info.get("px_count_all"), px_count_visib=info.get("px_count_visib"),
                px_count_valid=info.get("px_count_valid")))
        return BopFrame(scene_id=scene_id, im_id=im_id, rgb=rgb, depth_m=depth_m, K=K.copy(), depth_scale_mm=scale,
                        gts=gts, T_cam_world=None if T_cam_world is None else T_cam_world.copy(),
                        depth_units=depth_units, T_vehicle_cam=s["vehicle"].get(im_id))

    def model_symmetries(self, obj_id: int) -> np.ndarray:
        """(S, 4, 4) symmetry transforms of a model in metres, identity first."""
        if int(obj_id) not in self.models_info:
            raise ValueError(f"{self.root / 'models' / 'models_info.json'}: no entry for obj_id {obj_id} "
                             f"(known: {sorted(self.models_info)})")
        return symmetries_from_info(self.models_info[int(obj_id)])

    def model_path(self, obj_id: int) -> Path:
        """Path of the model's PLY mesh (millimetres)."""
        return self.root / "models" / f"obj_{int(obj_id):06d}.ply"

    def model_points(self, obj_id: int, n: int = 2000, seed: int = 0) -> np.ndarray:
        """(n, 3) points sampled uniformly on the model's mesh surface (`read_ply_mesh`), metres."""
        verts_mm, faces = read_ply_mesh(self.model_path(obj_id))
        return sample_surface(verts_mm / 1000.0, faces, n, seed)


def read_ply_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a PLY mesh (ascii or binary little-endian; float x, y, z first of the vertex
    properties, faces as lists of 3 indexes). :return: (v, 3) float64, (f, 3) int64.
    :raises BopFormatError: another layout."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise BopFormatError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii", "replace").splitlines()
    fmt = next((ln.split()[1] for ln in header if ln.startswith("format ")), "")
    counts, props, element = {}, {"vertex": [], "face": []}, None
    for ln in header:
        w = ln.split()
        if w[:1] == ["element"]:
            element, counts[w[1]] = w[1], int(w[2])
        elif w[:1] == ["property"] and element in props:
            props[element].append(w[1:])
    vp, fp = props["vertex"], props["face"]
    if fmt not in ("ascii", "binary_little_endian") or [p[-1] for p in vp[:3]] != ["x", "y", "z"] \
            or any(p[0] != "float" for p in vp) or len(fp) != 1 or fp[0][:1] != ["list"]:
        raise BopFormatError(f"{path}: expected float x, y, z vertices and one face list, {fmt} or ascii")
    nv, nf = counts.get("vertex", 0), counts.get("face", 0)
    body = data[end + len(b"end_header\n"):]
    if fmt == "ascii":
        rows = body.decode("ascii").split("\n")
        verts = np.array([r.split()[:3] for r in rows[:nv]], np.float64).reshape(-1, 3)
        faces = np.array([r.split()[1:4] for r in rows[nv:nv + nf]], np.int64).reshape(-1, 3)
    else:
        verts = np.frombuffer(body, "<f4", nv * len(vp)).reshape(nv, len(vp))[:, :3].astype(np.float64)
        count_t, index_t = {"uchar": "u1", "uint8": "u1"}.get(fp[0][1]), {"int": "<i4", "uint": "<u4",
                                                                          "int32": "<i4", "uint32": "<u4"}.get(fp[0][2])
        if count_t is None or index_t is None:
            raise BopFormatError(f"{path}: face list of {fp[0][1]} / {fp[0][2]} is not supported")
        rec = np.frombuffer(body, np.dtype([("n", count_t), ("i", index_t, (3,))]), nf, offset=nv * len(vp) * 4)
        if np.any(rec["n"] != 3):
            raise BopFormatError(f"{path}: only triangle faces are supported")
        faces = rec["i"].astype(np.int64)
    if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(verts):
        raise BopFormatError(f"{path}: no triangles, or a face index outside the {len(verts)} vertices")
    return verts, faces


def sample_surface(verts: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points uniform on a triangle mesh's surface (triangles by area, then uniform barycentrics).
    :param verts: (v, 3); :param faces: (f, 3) vertex indexes."""
    tri = np.asarray(verts, np.float64)[np.asarray(faces)]                      # (f, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("the mesh has no area")
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(tri), size=int(n), p=area / area.sum())
    a, b = rng.random((2, int(n), 1))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[pick]
    return t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0])


def _scene_dirs(split_dir: Path) -> list[Path]:
    return sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit() and len(p.name) == 6)


def _read_depth_units(folder: Path, name: str, hw: tuple[int, int]) -> np.ndarray:
    """(H, W) uint16 depth image `name` of `folder` as stored (BOP: a 16-bit PNG); zeros when there is none."""
    path = _find_image(folder, name)
    if path is None:
        return np.zeros(hw, dtype=np.uint16)
    raw = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
    if raw is None or raw.shape != hw:
        raise BopFormatError(f"{path}: unreadable or not the size of the rgb image")
    if raw.dtype not in (np.uint8, np.uint16):
        raise BopFormatError(f"{path}: depth must be an 8- or 16-bit integer image, got {raw.dtype}")
    return raw.astype(np.uint16, copy=False)


def _read_mask(path: Path, hw: tuple[int, int]) -> np.ndarray | None:
    if not path.exists():
        return None
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None or m.shape != hw:
        raise BopFormatError(f"{path}: unreadable mask or not the size of the rgb image")
    return m > 127
