"""Depth sensor models by name: "ideal", "d435" (active stereo), "oakd" (passive stereo), "tof".

`depth_model_for(name)` gives a sensor's default model; `apply_sensor` turns ideal depth into that sensor's
depth. Each model is a frozen dataclass of its parameters, so a preset can carry a tuned one.
"""
from __future__ import annotations

import numpy as np

from pallet6d.sim.oakd import OakdStereoModel, apply_oakd
from pallet6d.sim.sensors import SENSORS, PixelInfo, StereoDepthModel, apply_depth_model
from pallet6d.sim.tof import ToFDepthModel, apply_tof

__all__ = ["DepthModel", "SENSOR_MODELS", "depth_model_for", "check_sensor_model", "apply_sensor"]

DepthModel = StereoDepthModel | OakdStereoModel | ToFDepthModel
SENSOR_MODELS: dict[str, type | None] = {"ideal": None, "d435": StereoDepthModel, "oakd": OakdStereoModel,
                                         "tof": ToFDepthModel}
assert tuple(SENSOR_MODELS) == SENSORS


def depth_model_for(name: str) -> DepthModel | None:
    """The default model of the sensor called `name` (None for "ideal")."""
    if name not in SENSOR_MODELS:
        raise ValueError(f"unknown depth sensor {name!r}; known sensors: {', '.join(SENSORS)}")
    cls = SENSOR_MODELS[name]
    return None if cls is None else cls()


def check_sensor_model(name: str, model: DepthModel | None) -> None:
    """Raise ValueError unless `model` is None or a model of the sensor called `name`."""
    cls = SENSOR_MODELS.get(name)
    if name not in SENSOR_MODELS:
        raise ValueError(f"unknown depth sensor {name!r}; known sensors: {', '.join(SENSORS)}")
    if model is not None and (cls is None or type(model) is not cls):
        want = "no model" if cls is None else cls.__name__
        raise ValueError(f"sensor {name!r} takes {want}, got a {type(model).__name__}")


def apply_sensor(depth_m: np.ndarray, f_px: float, model: DepthModel | None, info: PixelInfo | None,
                 rng: np.random.Generator) -> np.ndarray:
    """Sensor depth (H, W) float32 metres, 0 = invalid, from ideal depth (H, W) metres.

    :param info: per-pixel scene data; required by the OAK-D and ToF models, unused by the others.
    """
    if model is None or isinstance(model, StereoDepthModel):
        return apply_depth_model(depth_m, f_px, model, rng)
    if info is None:
        raise ValueError(f"{type(model).__name__} needs the per-pixel scene data (PixelInfo)")
    if isinstance(model, OakdStereoModel):
        return apply_oakd(depth_m, f_px, model, info, rng)
    if isinstance(model, ToFDepthModel):
        return apply_tof(depth_m, f_px, model, info, rng)
    raise TypeError(f"unknown depth model type {type(model).__name__}")
