"""Scene-generation presets mirroring the paper's three datasets (section 4.1).

- ``virtual-clean``: 1224x370, forklift camera aligned with the pallet to pick up, no occluders (4.1.1).
- ``virtual-occluded``: 1224x370, misaligned camera, occluding boxes, pallets in the aisle, partly visible
  targets (4.1.2).
- ``indoor-noisy``: RealSense D435 colour-aligned 848x480, one pallet with stacked boxes on the floor of a
  room at 1-5 m, noisy stereo depth, low light, motion blur (4.1.3).

and two for real warehouses (docs/sim-scenes.md):
- ``forklift-approach``: the forklift's own view (camera on the fork carriage 0.1-2.5 m above the floor,
  0.5-6 m from the target face, approach yaw up to +-45 degrees, fork tips in view), D435-like depth, every
  pallet type, loads, stacks, racks, truck beds, distractors, obstacles in pockets, randomised appearance.
- ``mixed``: far rack views, rooms and forklift views mixed, every type and all that content, randomised
  appearance, the depth sensor drawn per frame (ideal, D435, OAK-D, ToF).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from pallet6d.runtime.inputs import MAX_IMAGE_PIXELS
from pallet6d.sim.appearance import AppearanceConfig
from pallet6d.sim.depth_sensors import DepthModel, check_sensor_model
from pallet6d.sim.pallets import PALLET_MODELS, get_pallet_model
from pallet6d.sim.scene import SceneError
from pallet6d.sim.sensors import SENSORS

__all__ = ["SimConfig", "LAYOUTS", "PRESETS", "PAPER_PRESETS", "get_preset"]

_Range = tuple[float, float]
# "warehouse": racks seen from the aisle (paper Fig. 3); "indoor": one pallet in a room; "forklift": the
# forklift's own view of a pallet on the floor, in a rack, on a truck bed or on a stack; "mixed": each
# frame one of the three, drawn with view_probs.
LAYOUTS: tuple[str, ...] = ("warehouse", "indoor", "forklift", "mixed")


@dataclass(frozen=True)
class SimConfig:
    """How to draw random scenes. Ranges are (min, max), drawn uniformly; angles in degrees."""

    name: str
    width: int
    height: int
    hfov_deg: float                                     # horizontal field of view; fx = fy
    layout: str = "warehouse"                           # see LAYOUTS
    pallet_models: tuple[str, ...] = ("epal",)
    target_distance_m: _Range = (1.5, 4.0)              # camera to the target pallet's front face
    camera_above_pallet_m: _Range = (0.25, 0.6)         # camera height above the target pallet's underside
    lateral_offset_m: _Range = (0.0, 0.0)               # sideways offset of the camera from the pallet axis
    yaw_deg: float = 0.0                                # max |misalignment| of the camera about each axis
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    pallet_yaw_jitter_deg: float = 1.0                  # how crooked pallets stand in racks
    occluders: tuple[int, int] = (0, 0)                 # free-standing objects between camera and target
    floor_pallets: tuple[int, int] = (0, 0)             # extra pallets standing in the aisle
    rack_fill: float = 0.7                              # probability that a rack slot holds a pallet
    load_prob: float = 0.6                              # probability that a pallet carries a load
    min_target_visib: float = 0.95                      # the target pallet's required visible fraction
    sensor: str = "ideal"                               # depth sensor: "ideal", "d435", "oakd" or "tof"
    exposure: _Range = (0.85, 1.15)
    rgb_noise_sigma: _Range = (0.0, 0.01)               # gaussian noise on RGB in [0, 1] units
    blur_prob: float = 0.0                              # probability of a motion blur
    max_attempts: int = 20                              # scene draws before giving up on a visible target
    sensor_model: DepthModel | None = None              # tuned model of `sensor`; None = its default model
    appearance: AppearanceConfig | None = None          # randomised appearance; None = the plain look, and then
    #                                                     exposure / rgb_noise_sigma / blur_prob drive the camera
    # Real-warehouse content (off in the paper presets, whose frames must not change): every load kind,
    # stacks of empty pallets, truck beds, distractors, pallet colours, wear and dirt.
    rich_content: bool = False
    missing_board_prob: float = 0.0                     # a pallet lacks one inner top deck board
    target_inside: bool = True                          # the target's whole silhouette must be in the image
    # Forklift views: camera height above the floor, max |approach yaw| of the vehicle to the target face,
    # probability that an obstacle sits in one of the target's fork pockets.
    cam_height_m: _Range = (0.1, 2.5)
    approach_yaw_deg: float = 45.0
    pocket_obstacle_prob: float = 0.0
    view_probs: tuple[float, float, float] = (0.35, 0.15, 0.5)   # "mixed": far/rack, indoor, forklift views
    sensor_mix: tuple[str, ...] = ()                    # when set, each frame draws its depth sensor from these

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ValueError(f"{self.name}: image must be at least 16x16, got {self.width}x{self.height}")
        if self.width * self.height > MAX_IMAGE_PIXELS:   # the runtime refuses larger frames
            raise ValueError(f"{self.name}: image must be at most {MAX_IMAGE_PIXELS / 1e6:.1f} MP (3840x2160), got "
                             f"{self.width}x{self.height}")
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise ValueError(f"{self.name}: hfov_deg must be in [10, 150], got {self.hfov_deg}")
        if self.layout not in LAYOUTS:
            raise ValueError(f"{self.name}: layout must be one of {LAYOUTS}, got {self.layout!r}")
        if len(self.view_probs) != 3 or min(self.view_probs) < 0 or not math.isclose(sum(self.view_probs), 1.0):
            raise ValueError(f"{self.name}: view_probs must be 3 probabilities summing to 1, got {self.view_probs}")
        if not 0.0 <= self.approach_yaw_deg <= 80.0:
            raise ValueError(f"{self.name}: approach_yaw_deg must be in [0, 80], got {self.approach_yaw_deg}")
        if not self.pallet_models:
            raise SceneError(f"{self.name}: pallet_models is empty: a scene needs at least one pallet type")
        for m in self.pallet_models:
            get_pallet_model(m)
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.endswith(("_m", "_deg", "exposure", "sigma", "occluders", "pallets")) and isinstance(v, tuple):
                if len(v) != 2 or not v[0] <= v[1]:
                    raise ValueError(f"{self.name}: {f.name} must be a (min, max) pair with min <= max, got {v}")
        if self.target_distance_m[0] <= 0.3:
            raise SceneError(f"{self.name}: target_distance_m must stay above 0.3 m (the camera would touch "
                             f"the pallet), got {self.target_distance_m}")
        if self.camera_above_pallet_m[0] < 0.0:
            raise SceneError(f"{self.name}: camera_above_pallet_m must be >= 0 (camera below the floor/beam)")
        if self.sensor not in SENSORS:
            raise ValueError(f"{self.name}: sensor must be one of {', '.join(SENSORS)}, got {self.sensor!r}")
        check_sensor_model(self.sensor, self.sensor_model)
        if any(s not in SENSORS for s in self.sensor_mix) or (self.sensor_mix and self.sensor_model is not None):
            raise ValueError(f"{self.name}: sensor_mix must name sensors of {', '.join(SENSORS)} (their default "
                             f"models, so no sensor_model), got {self.sensor_mix}")
        if self.appearance is not None and not isinstance(self.appearance, AppearanceConfig):
            raise TypeError(f"{self.name}: appearance must be an AppearanceConfig or None, got "
                            f"{type(self.appearance).__name__}")
        for name in ("rack_fill", "load_prob", "min_target_visib", "blur_prob", "missing_board_prob",
                     "pocket_obstacle_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{self.name}: {name} must be in [0, 1], got {getattr(self, name)}")
        if self.occluders[0] < 0 or self.floor_pallets[0] < 0 or self.max_attempts < 1:
            raise ValueError(f"{self.name}: counts must be >= 0 and max_attempts >= 1")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsics: square pixels, principal point at the image centre."""
        f = (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)
        return np.array([[f, 0, (self.width - 1) / 2], [0, f, (self.height - 1) / 2], [0, 0, 1]])

    def with_image_size(self, width: int, height: int) -> "SimConfig":
        """The same preset at another image size (same horizontal field of view), e.g. small test renders."""
        return replace(self, width=int(width), height=int(height))


PRESETS: dict[str, SimConfig] = {
    "virtual-clean": SimConfig(
        name="virtual-clean", width=1224, height=370, hfov_deg=82.0,
        target_distance_m=(1.2, 4.0), pallet_yaw_jitter_deg=0.0, min_target_visib=0.98,
        exposure=(0.95, 1.05), rgb_noise_sigma=(0.0, 0.004)),
    "virtual-occluded": SimConfig(
        name="virtual-occluded", width=1224, height=370, hfov_deg=82.0,
        target_distance_m=(1.2, 5.0), lateral_offset_m=(-0.8, 0.8), yaw_deg=15.0, pitch_deg=5.0, roll_deg=3.0,
        pallet_yaw_jitter_deg=4.0, occluders=(1, 3), floor_pallets=(0, 3), min_target_visib=0.1,
        exposure=(0.7, 1.2), rgb_noise_sigma=(0.0, 0.015)),
    "indoor-noisy": SimConfig(
        name="indoor-noisy", width=848, height=480, hfov_deg=69.4, layout="indoor",
        target_distance_m=(1.0, 5.0), camera_above_pallet_m=(0.25, 0.9), lateral_offset_m=(-0.5, 0.5),
        yaw_deg=10.0, pitch_deg=4.0, roll_deg=2.0, occluders=(0, 1), load_prob=0.85, min_target_visib=0.3,
        sensor="d435", exposure=(0.3, 0.8), rgb_noise_sigma=(0.01, 0.04), blur_prob=0.3),
    # The forklift's own view (a D435 on the fork carriage) of every pallet type in real-warehouse scenes.
    "forklift-approach": SimConfig(
        name="forklift-approach", width=848, height=480, hfov_deg=69.4, layout="forklift",
        pallet_models=PALLET_MODELS, target_distance_m=(0.5, 6.0), occluders=(0, 2), floor_pallets=(1, 4),
        load_prob=0.7, min_target_visib=0.25, target_inside=False, sensor="d435", appearance=AppearanceConfig(),
        rich_content=True, missing_board_prob=0.1, pocket_obstacle_prob=0.15),
    # Everything randomised: far rack views, rooms and forklift views, all types, all content.
    "mixed": SimConfig(
        name="mixed", width=848, height=480, hfov_deg=69.4, layout="mixed", pallet_models=PALLET_MODELS,
        target_distance_m=(0.5, 6.0), camera_above_pallet_m=(0.1, 1.2), lateral_offset_m=(-0.8, 0.8),
        yaw_deg=15.0, pitch_deg=6.0, roll_deg=3.0, pallet_yaw_jitter_deg=4.0, occluders=(0, 3),
        floor_pallets=(0, 4), load_prob=0.7, min_target_visib=0.2, target_inside=False, sensor="d435",
        sensor_mix=("ideal", "d435", "oakd", "tof"), appearance=AppearanceConfig(), rich_content=True,
        missing_board_prob=0.1, pocket_obstacle_prob=0.1),
}
# The presets that mirror the paper's datasets: their frames stay the same for the same seed.
PAPER_PRESETS: tuple[str, ...] = ("virtual-clean", "virtual-occluded", "indoor-noisy")


def get_preset(name: str) -> SimConfig:
    """The preset called `name` (one of PRESETS)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}")
    return PRESETS[name]
