"""Write generated frames as a BOP dataset (models, scenes, masks) and optional label previews."""
from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Callable

import cv2

from pallet6d.runtime.geometry import invert_T
from pallet6d.runtime.bop import BopGT, BopWriter, models_info_entry, write_models_info
from pallet6d.sim.generate import SimFrame, generate_frame, obj_id_of
from pallet6d.sim.pallet_free import generate_pallet_free_frame
from pallet6d.sim.pallets import PALLET_MODELS, get_pallet_model
from pallet6d.sim.presets import SimConfig
from pallet6d.sim.preview import draw_preview

__all__ = ["GT_INFO_VERSION", "IMAGES_PER_SCENE", "FORKLIFT_GT_FILE", "write_models", "frame_to_bop_gts",
           "forklift_entry", "read_forklift_gt", "write_dataset"]

log = logging.getLogger(__name__)
IMAGES_PER_SCENE = 1000   # as in BOP's train_pbr: scene folders are chunks of 1000 frames
# what the annotations mean, written into each sim_config: 2 = px_count_all / visib_fract count the silhouette
# out of view too (BOP's calc_gt_info); 1 (before 2026-11-22, or absent) counted only the part in the image
GT_INFO_VERSION = 2
FORKLIFT_GT_FILE = "scene_forklift.json"   # per scene folder, beside scene_gt.json (docs/sim-scenes.md)


def write_models(root) -> None:
    """ROOT/models/obj_{id:06d}.ply (mm) and models_info.json for every type of the catalogue, each under its
    stable obj_id (so a dataset extended later with other types stays whole). Beside the BOP fields each
    entry carries the type's `name`,
    its fork openings `pockets` ({face: [[min_mm, max_mm], [min_mm, max_mm]]}, left then right) and its
    `refine_starts` (yaw_deg, dx_m, dy_m rows); bop_toolkit ignores them."""
    infos = {}
    for name in PALLET_MODELS:
        model = get_pallet_model(name)
        obj_id = obj_id_of(name)
        model.write_ply(Path(root) / "models" / f"obj_{obj_id:06d}.ply")
        entry = models_info_entry(model.diameter_m, -model.size_m / 2, model.size_m, model.symmetries)
        entry["name"] = name
        entry["pockets"] = {face: (pk * 1000.0).round(3).tolist() for face, pk in model.pockets_m.items()}
        entry["refine_starts"] = model.refine_starts.round(6).tolist()
        infos[obj_id] = entry
    write_models_info(root, infos)


def forklift_entry(frame: SimFrame) -> dict:
    """One image's entry of scene_forklift.json (docs/sim-scenes.md): the camera-to-vehicle transform
    (BOP style, mm; null without a vehicle), the forks, and each pallet's front face and pockets."""
    v = frame.vehicle
    index = {p.instance_id: k for k, p in enumerate(frame.pallets)}
    pallets = []
    for f in frame.faces:
        p = frame.pallets[index[f.instance_id]]
        pallets.append({"gt_index": index[f.instance_id], "obj_id": p.obj_id,
                        "target": f.instance_id == frame.target_instance, **f.to_json()})
    entry: dict = {"cam_R_c2v": None, "cam_t_c2v": None, "forks": None, "pallets": pallets}
    if v is not None:
        entry["cam_R_c2v"] = [float(x) for x in v.T_vehicle_cam[:3, :3].ravel()]
        entry["cam_t_c2v"] = [float(x) * 1000.0 for x in v.T_vehicle_cam[:3, 3]]
        entry["forks"] = {"z_mm": v.fork_z_m * 1000.0, "spread_mm": v.fork_spread_m * 1000.0,
                          "length_mm": v.fork_length_m * 1000.0, "width_mm": v.fork_width_m * 1000.0,
                          "thickness_mm": v.fork_thickness_m * 1000.0}
    return entry


def _write_forklift(path: Path, entries: dict[str, dict]) -> None:
    data = json.loads(path.read_text()) if path.exists() else {}
    data.update(entries)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dict(sorted(data.items(), key=lambda kv: int(kv[0]))), indent=1))


def read_forklift_gt(scene_dir) -> dict[int, dict]:
    """scene_forklift.json of a scene folder as {im_id: entry}; {} when the file is absent."""
    path = Path(scene_dir) / FORKLIFT_GT_FILE
    if not path.exists():
        return {}
    return {int(k): v for k, v in json.loads(path.read_text()).items()}


def frame_to_bop_gts(frame: SimFrame) -> list[BopGT]:
    return [BopGT(obj_id=p.obj_id, T_cam_model=p.T_cam_pallet, bbox_obj_xywh=p.bbox_obj_xywh,
                  bbox_visib_xywh=p.bbox_visib_xywh, visib_fract=p.visib_fract, mask_visib=p.mask_visib,
                  mask=p.mask_full, px_count_all=p.px_count_all, px_count_visib=p.px_count_visib,
                  px_count_valid=p.px_count_valid) for p in frame.pallets]


def write_dataset(config: SimConfig, frames: int, seed: int, out, split: str = "train", preview: bool = False,
                  start: int = 0, progress: Callable[[int], None] | None = None,
                  pallet_free: str | None = None) -> list[Path]:
    """Generate `frames` frames (indices start .. start+frames-1) into a BOP dataset at `out`.

    :param pallet_free: None, or where the loads go ("set-down", "hanging") in frames of the preset's scenes drawn
        without their pallets and written with no ground truth (`pallet_free.generate_pallet_free_frame`).

    :return: the preview image paths (empty without `preview`).
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    out = Path(out)
    write_models(out)
    previews: list[Path] = []
    meta = {"generator": "pallet6d.sim", "gt_info_version": GT_INFO_VERSION, "seed": seed, "start": start,
            "frames": frames, "config": dataclasses.asdict(config), "pallet_free": pallet_free}
    (out / split).mkdir(parents=True, exist_ok=True)
    (out / split / f"sim_config_{start:06d}.json").write_text(json.dumps(meta, indent=1))
    side: dict[str, dict] = {}
    side_scene = None
    with BopWriter(out, split) as writer:
        for index in range(start, start + frames):
            frame = generate_frame(config, seed, index) if pallet_free is None else \
                generate_pallet_free_frame(config, seed, index, pallet_free)
            scene_id, im_id = divmod(index, IMAGES_PER_SCENE)
            writer.write_frame(scene_id, im_id, frame.rgb, frame.depth_m, frame.K, frame_to_bop_gts(frame),
                               T_cam_world=invert_T(frame.T_world_cam))
            if side_scene is not None and scene_id != side_scene:
                _write_forklift(writer.scene_dir(side_scene) / FORKLIFT_GT_FILE, side)
                side = {}
            side_scene = scene_id
            side[str(im_id)] = forklift_entry(frame)
            if preview:
                path = out / "preview" / split / f"{scene_id:06d}_{im_id:06d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(path), draw_preview(frame)[:, :, ::-1])
                previews.append(path)
            if progress is not None:
                progress(1)
        if side_scene is not None:
            _write_forklift(writer.scene_dir(side_scene) / FORKLIFT_GT_FILE, side)
    return previews

