"""The daemon's response bodies as pydantic models: they describe the API in its OpenAPI document. The handlers
send the JSON that `FrameResult.to_dict()` gives (the same as `pallet6d run`'s lines); the tests validate real
responses against these models, so the description cannot drift from what is sent."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from ..forklift import FACE_NORMALS, PICK_REASONS
from ..results import REJECT_REASONS

__all__ = ["PalletsResponse", "Pallet", "Forklift", "Pocket", "Fit", "Rejected", "ReadyResponse", "FloorCheck"]

Vec3 = list[float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class Fit(_Strict):
    inlier_fraction: float = Field(description="fraction of the posed model's points that the depth confirms")
    free_space_violation: float = Field(description="fraction where the camera saw through the posed wood")
    score: float = Field(description="inlier_fraction * (1 - free_space_violation)")


class Pocket(_Strict):
    side: Literal["left", "right"] = Field(description="as seen from the forklift")
    centre_m: Vec3 = Field(description="centre of the opening in the face plane, vehicle frame, metres")
    width_m: float
    height_m: float
    state: Literal["clear", "blocked", "hidden"] = Field(description="what the depth shows inside the pocket")
    open_rays: int = Field(description="rays through the opening that see free space")
    blocked_rays: int = Field(description="rays that meet a surface in the pocket or just in front of it")
    free_fraction: float = Field(description="share of the forks' path past the mouth that the depth shows free")
    occupied_fraction: float = Field(description="share of the forks' path from the mouth in where the depth shows "
                                                 "a surface inside the pocket")


class Forklift(_Strict):
    face: Literal[tuple(FACE_NORMALS)] = Field(description="the pallet face towards the forks (pallet frame)")
    face_centre_m: Vec3 = Field(description="centre of that face, vehicle frame, metres")
    face_yaw_deg: float = Field(description="0: the forks point straight into the face; positive: turned "
                                            "anticlockwise seen from above")
    lateral_offset_m: float = Field(description="the face centre's y (left of the forks' centre line)")
    distance_m: float = Field(description="the face centre's x (ahead of the fork roots)")
    view_angle_deg: float = Field(description="angle between the face's normal and the line of sight")
    pockets: list[Pocket] = Field(description="left, then right")
    pick_safe: bool = Field(description="both pockets clear and the face seen squarely enough")
    reason: Literal[PICK_REASONS] = Field(description="why not safe ('' when safe)")
    detail: str


class Pallet(_Strict):
    class_: str = Field(alias="class", description="the detector class")
    pallet_type: str = Field(description="the pallet type whose geometry posed it (e.g. epal)")
    t_m: Vec3 = Field(description="pallet centre, camera frame (OpenCV axes: x right, y down, z forward), metres")
    quat_wxyz: list[float] = Field(description="pallet -> camera rotation")
    confidence: float
    detector_score: float
    box_xyxy: list[float] = Field(description="the detector's box, image pixels")
    n_valid_points: int
    fit: Fit
    t_vehicle_m: Vec3 | None = Field(None, description="pallet centre, vehicle frame (x forward along the forks, "
                                                       "y left, z up, origin on the floor between the fork "
                                                       "roots), metres; vehicle frame only")
    quat_vehicle_wxyz: list[float] | None = Field(None, description="pallet -> vehicle rotation; vehicle frame only")
    forklift: Forklift | None = Field(None, description="front face, pockets and pick_safe; vehicle frame only, "
                                                        "for pallet types with fork pockets")


class Rejected(_Strict):
    reason: Literal[REJECT_REASONS]
    detail: str
    detector_score: float
    box_xyxy: list[float]
    n_valid_points: int
    pose: Pallet | None = Field(None, description="the pose that was computed, then rejected")


class PalletsResponse(_Strict):
    """The latest result (`GET /v1/pallets`, `POST /v1/detect`, each event of `GET /v1/stream`)."""

    seq: int = Field(description="increases by one per published result")
    frame: int = Field(description="the source's frame number")
    capture_timestamp_s: float = Field(description="capture time (device clock; recording time for replays)")
    received_unix_s: float = Field(description="wall-clock time the daemon took the frame")
    age_s: float = Field(description="seconds since the daemon took the frame")
    trigger: Literal["continuous", "detect"]
    output_frame: Literal["vehicle", "camera"] = Field(description="vehicle: each pallet also carries t_vehicle_m, "
                                                                   "quat_vehicle_wxyz and forklift")
    source: str
    image_hw: list[int]
    latency_ms: dict[str, float] = Field(description="milliseconds per estimator stage, and total")
    pallets: list[Pallet] = Field(description="accepted pallets, highest detector score first")
    rejected: list[Rejected] = Field(description="detections that did not become poses, with reasons")
    n_outside_hint: int = Field(0, description="accepted poses dropped by the request's region hint")
    error: str | None = Field(None, description="why this frame gives no pallets, e.g. vehicle-frame output "
                                                "withheld because the camera moved since calibration")


class Measured(_Strict):
    measured: float | None = Field(description="null: not measured (no floor seen yet)")
    expected: float
    tolerance: float


class FloorCheck(_Strict):
    state: Literal["ok", "failed", "unknown", "not_configured"]
    detail: str
    file: str | None = Field(None, description="the calibration file")
    when_unseen: Literal["ready", "not_ready"] | None = None
    checks: int = 0
    checked_age_s: float | None = Field(None, description="seconds since the last check")
    camera_height_m: Measured | None = Field(None, description="the camera's height above the floor")
    floor_tilt_deg: Measured | None = Field(None, description="angle between the seen and the calibrated floor")


class ReadyResponse(_Strict):
    ready: bool
    checks: dict[str, bool] = Field(description="model, camera, results, calibration: which part is (not) ready")
    reasons: list[str] = Field(description="a sentence per failing check")
    mode: Literal["continuous", "triggered"]
    output_frame: Literal["vehicle", "camera"]
    calibration: FloorCheck
    camera_frame_age_s: float | None
    result_age_s: float | None
    camera_error: str | None
