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
from pallet6d.sim.pallets import PALLET_MODELS, get_pallet_model
from pallet6d.sim.presets import SimConfig
from pallet6d.sim.preview import draw_preview

__all__ = ["GT_INFO_VERSION", "IMAGES_PER_SCENE", "write_models", "frame_to_bop_gts", "write_dataset"]

log = logging.getLogger(__name__)
IMAGES_PER_SCENE = 1000   # as in BOP's train_pbr: scene folders are chunks of 1000 frames
# what the annotations mean, written into each sim_config: 2 = px_count_all / visib_fract count the silhouette
# out of view too (BOP's calc_gt_info); 1 (before 2026-11-22, or absent) counted only the part in the image
GT_INFO_VERSION = 2


def write_models(root) -> None:
    """ROOT/models/obj_{id:06d}.ply (mm) and models_info.json for every pallet model (obj_id = position + 1)."""
    infos = {}
    for name in PALLET_MODELS:
        model = get_pallet_model(name)
        obj_id = obj_id_of(name)
        model.write_ply(Path(root) / "models" / f"obj_{obj_id:06d}.ply")
        entry = models_info_entry(model.diameter_m, -model.size_m / 2, model.size_m, model.symmetries)
        entry["name"] = name   # not a BOP field; bop_toolkit ignores it
        infos[obj_id] = entry
    write_models_info(root, infos)


def frame_to_bop_gts(frame: SimFrame) -> list[BopGT]:
    return [BopGT(obj_id=p.obj_id, T_cam_model=p.T_cam_pallet, bbox_obj_xywh=p.bbox_obj_xywh,
                  bbox_visib_xywh=p.bbox_visib_xywh, visib_fract=p.visib_fract, mask_visib=p.mask_visib,
                  mask=p.mask_full, px_count_all=p.px_count_all, px_count_visib=p.px_count_visib,
                  px_count_valid=p.px_count_valid) for p in frame.pallets]


def write_dataset(config: SimConfig, frames: int, seed: int, out, split: str = "train", preview: bool = False,
                  start: int = 0, progress: Callable[[int], None] | None = None) -> list[Path]:
    """Generate `frames` frames (indices start .. start+frames-1) into a BOP dataset at `out`.

    :return: the preview image paths (empty without `preview`).
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    out = Path(out)
    write_models(out)
    previews: list[Path] = []
    meta = {"generator": "pallet6d.sim", "gt_info_version": GT_INFO_VERSION, "seed": seed, "start": start,
            "frames": frames, "config": dataclasses.asdict(config)}
    (out / split).mkdir(parents=True, exist_ok=True)
    (out / split / f"sim_config_{start:06d}.json").write_text(json.dumps(meta, indent=1))
    with BopWriter(out, split) as writer:
        for index in range(start, start + frames):
            frame = generate_frame(config, seed, index)
            scene_id, im_id = divmod(index, IMAGES_PER_SCENE)
            writer.write_frame(scene_id, im_id, frame.rgb, frame.depth_m, frame.K, frame_to_bop_gts(frame),
                               T_cam_world=invert_T(frame.T_world_cam))
            if preview:
                path = out / "preview" / split / f"{scene_id:06d}_{im_id:06d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(path), draw_preview(frame)[:, :, ::-1])
                previews.append(path)
            if progress is not None:
                progress(1)
    return previews

