"""`PalletEstimator`: RGB-D frame -> pallet 6D poses, on a model bundle's ONNX graphs (never torch).

The estimator is a pipeline of four stages (paper section 3), batched over the pallets of a frame, that pass
one record of candidates (`candidates.Candidates`, a row per detection) from one to the next:

    DetectorStage       letterbox -> detector.onnx -> YOLOv8 decode + NMS             stage_detector.py
    PoseNetworkStage    crop / encode / sample N points -> fusion.onnx -> pose.onnx    stage_pose.py
                        -> most confident per-point hypothesis
    RefinerStage        robust point-to-plane ICP on the box's depth against the      stage_refine.py
                        candidate's pallet type (+ ICP from starts around the pose)
    FitCheckStage       geometric fit check against the depth image, acceptance       stage_fit.py

Each candidate's pallet type comes from its detector class; the refiner and the fit check use that type's
own geometry (`stage_geometry.py`).

`predict(...)` returns the accepted `PalletPose`s; `estimate(...)` returns the whole `FrameResult`:
accepted poses, rejected detections with their reasons, per-stage milliseconds. `estimate_boxes(...)`
starts after the detector, for a forklift that already runs a shared object detector. `candidates(...)`
returns the stages' record itself (every row's network and refined pose, fit and rejection reason).
"""
from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import wait
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .inputs import check_nonfinite_mode
from .bundle import Bundle, BundleError, load_bundle
from .candidates import Candidates
from .deadline import Deadline, elapsed_ms
from .depth_proposals import DepthProposals, framing_iou, propose_boxes
from .detector import Detections
from .evaluation import box_iou
from .floor import FloorPlane, on_floor, refine_floor
from .inputs import check_rgb, check_rgbd
from .level import LevelParams, climb_poses, level_in_camera, up_in_camera
from .overlap import duplicate_of
from .refine import MAX_STARTS
from .results import FitScore, FrameResult, PalletPose, Rejection
from .sessions import OnnxModel
from .stage_detector import DetectorStage
from .stage_fit import FitCheckStage
from .roi import RegionOfInterest, roi_filter
from .structure import StructureParams
from .stage_geometry import bundle_geometries
from .stage_type import TypeChoiceStage
from .stage_pose import PoseNetworkStage
from .stage_refine import RefinerStage
from .weak_boxes import WeakBoxes, inside_fraction

__all__ = ["EstimatorOptions", "PalletEstimator", "MAX_THREADS", "check_threads"]

# onnxruntime makes every pool's threads when a session is built: a mistyped count (100000) would hang there
MAX_THREADS = 64
STAGES = ("preprocess", "detector", "decode_nms", "pose_inputs", "fusion", "pose", "selection", "refine", "fit")


def check_threads(threads) -> int:
    """`threads` as an int. :raises ValueError: not an integer in 1..MAX_THREADS."""
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or not 1 <= threads <= MAX_THREADS:
        raise ValueError(f"threads must be an integer in 1..{MAX_THREADS}, got {threads!r}")
    return int(threads)


@dataclass(frozen=True)
class EstimatorOptions:
    """Run-time choices (the model's own sizes and normalisation come from the bundle, never from here).

    :ivar score_threshold: detector class score a box must exceed.
    :ivar iou_threshold: NMS IoU above which the weaker box of the same class goes.
    :ivar detector_mirror: the detector also sees the frame mirrored left to right, and each anchor's class scores
        are averaged with those of the anchor it mirrors before the threshold; the boxes stay the frame's own (a
        second detector run: about 8 ms int8 on 2 cores). A box only one view believes in falls under the
        threshold. Real photographs (held out): false boxes per pallet-free photo 0.73 -> 0.47, precision 54.1 ->
        56.3 % at recall 30.2 -> 29.4 %, large boxes 57.6 / 76.5 -> 60.5 / 78.7 %; simulated validation frames:
        1-5 pallets more within 5 cm on most sets, 2 of 100 fewer on indoor-noisy (docs/experiments/real-data.md).
        Off by default: a second detector run on every frame.
    :ivar max_pallets: at most this many detections (highest scores) go to the pose stage. Each costs tens of
        ms on 2 cores (`benchmarks/latency.py`); 16 covers the fullest racks of the validation sets (18 pallets
        at least 10 % visible; 35 of 200 occluded frames have more than 8).
    :ivar depth_range_m: (min, max) depth of a pixel to become a point; None = the bundle's.
    :ivar min_valid_points: fewer valid depth pixels in a box -> rejected ("too_few_points").
    :ivar min_confidence: best per-point confidence below this -> rejected ("low_confidence"). 0.1 kept every
        pose within 5 cm of a true pallet on validation frames and removes about half of the poses made up
        from mismatched depth (`docs/experiments/min-confidence.md`).
    :ivar min_fit: fit score below this -> rejected ("poor_fit"); 0 disables the check.
    :ivar fit_tol_m: distance tolerance of the fit score, metres.
    :ivar refine: refine each pose on the box's depth by robust point-to-plane ICP against the pallet's
        boards and blocks (`refine.py`; needs `boxes_m` in the bundle's pallet model, else skipped). The
        refined pose replaces the network's only when the depth is clean enough for ICP to be trusted
        (`refine_max_rms_m`) and it fits the depth at least as well (`refine_margin`).
    :ivar refine_max_rms_m: keep the refined pose only when ICP's final point-to-plane RMS is below this,
        metres. On stereo-noisy depth ICP drifts (started at the true pose on D435-like depth it ends within
        5 cm only 42 % of the time) and its RMS sits at 4-5 mm; on clean depth it is 0.5-4 mm. Chosen on
        validation frames (seeds 8011-8013, shipped network; ADD-sym @5 cm of detected pallets): on
        indoor-noisy the network alone 69.5 %, ICP by the fit score alone 55 %, this gate 70.5 %;
        on the virtual sets it keeps ICP's gain (virtual-clean 81 -> 89 %, virtual-occluded 50 -> 70 %).
    :ivar refine_margin: the refined pose must also beat the network's fit score by this much (0: at least
        match it; -1: ICP's pose whenever its RMS allows).
    :ivar refine_points: at most this many depth points of the box go into the refinement.
    :ivar refine_iterations: refinement steps (0 disables it too).
    :ivar refine_starts: then also run ICP from this many poses around the pose so far, the first of
        `refine.start_offsets` (yaw +-15 degrees, +-10 cm along the pallet's length, +-10 cm along its width,
        +-5 cm along the length and the width, then +-30 degrees, +-20 cm along the length); a landing that ICP trusts
        (`refine_start_max_rms_m`) and that explains the box's depth better (fit score at
        `refine_select_tol_m`) replaces it. It pulls the network's larger errors back into ICP's basin.
        0 turns it off. 6 against 4: validation virtual-occluded 79.6 -> 82.0 % within 5 cm, virtual-clean
        96.8 -> 97.3 %, indoor-noisy unchanged; 10 changed 1 pallet in 1815 more, for half again the time of a
        frame (`benchmarks/results/refine-starts.md`).
    :ivar refine_start_points: depth points each extra start uses (an even subset of `refine_points`).
    :ivar refine_select_tol_m: tolerance of the fit score that compares landings, metres (tighter than
        `fit_tol_m`: on depth clean enough to trust ICP, 1.5 cm separates the right landing).
    :ivar refine_start_max_rms_m: a landing counts only when its ICP RMS is below this, metres. Stricter
        than `refine_max_rms_m`: on stereo-noisy depth some landings reach 3-4 mm by chance and then win
        wrongly; on clean depth most landings that help are below 3 mm.
    :ivar type_candidates: where one detector class reports several pallet types, the candidate is refined
        with this many of them, those that best fit the depth and show their boards and openings at the
        network's pose, and the refined pose that does so best decides its type (`stage_type.py`).
    :ivar type_candidates_levelled: the same with the camera's calibration, where each of them is also levelled
        before it is judged (`level`), and the first type always counts among them; at least as many as a
        candidate's types (11 in the default bundle): every one, unranked. The ranking at the network's pose is a
        poor guide: on the calibrated forklift-approach validation frames every type levelled finds 165 of 470
        pallets within 5 cm, the four best-ranked 150, for a third to four fifths more of a frame's time
        (docs/experiments/pallet-types.md). Without a calibration 4 types gain a quarter of a point on the paper
        presets for 8-10 ms a pallet, so `type_candidates` stays 2.
    :ivar type_score_ratio: a detector with a class per pallet type can be unsure between look-alike types: a
        pallet class that scores a detection at least this fraction of its best class's score offers its types
        too, and the type choice above decides by the depth. 1: the best class's types alone.
    :ivar type_margin: in that choice, a candidate keeps the first of its types (its class's first type in the
        bundle's order, e.g. the EPAL) unless another type's score (fit times structure agreement, 0-1) is higher by
        more than this: types that look alike from the pallet's side then keep the common one. 0.1 keeps the
        paper presets' EPALs EPALs with every type in the bundle (docs/experiments/pallet-types.md); 0 for a site
        whose types are equally common.
    :ivar type_margin_levelled: the same where the types are judged levelled (with the camera's calibration): each
        type has then been searched and refined on the floor in its own right, and a smaller margin lets the
        pallet's own type win where the first one only looks alike from the front (a 1200 x 1000 pallet posed as an
        EPAL sits 10 cm off). Calibrated forklift-approach validation frames within 5 cm, the precision of the
        accepted poses: 45.3 %, 0.962 at 0.08, 48.5 %, 0.960 at 0.04, 48.7 %, 0.954 at 0; the EPAL pocket targets
        lose a few D435-like ones below 0.08 (docs/experiments/pallet-types.md).
    :ivar type_first_enough: without a calibration, a candidate whose first type scores at least this (fit times
        structure agreement, 0-1) at its refined pose keeps that type, and the other types are neither ranked nor
        refined: they are tried where the first type fits poorly. On the validation frames no other type won where
        the first scored 0.6 or more (the mixed preset's winners replaced first types scoring up to 0.596), while
        about half of the paper presets' EPALs score that much: the type choice's second refinement and ranking are
        skipped for them. None: every candidate's types are compared.
    :ivar nonfinite_depth: "raise" on NaN/inf depth, or "as_missing".
    :ivar seed: seed of the per-detection point sampling.
    :ivar structure: thresholds of the structure check (`structure.py`): the depth must show the posed pallet's
        boards and fork openings where the pose puts them, and the detector's box must match it; a pose that
        fails is rejected ("no_pallet_structure"). It also asks whether the depth belongs to the image: the
        detector's box must have a pallet's metric size at the depth inside it ("size_mismatch": depth scale or
        focal length off) and, over the whole frame, the depth's edges must lie on the colour image's at zero shift
        and not as well with the depth shifted 24 px, and the depth must not be flat there (`min_registration_peak`,
        the registration test; else every candidate of the frame -> "depth_image_mismatch": another frame's depth,
        a wall's, depth not registered to the image; a flat depth refuses the detector's candidates only, not the
        depth's proposals); without a vehicle calibration, candidates failing the metric size refuse the whole frame
        unless more whole boxes pass every test (`frame_size_vouched`); opt-in, the same per candidate
        (`min_edge_auc`) and a frame-wide size veto (`frame_size_veto`). None turns the check off. What it keeps
        and refuses: `docs/structure-check.md`.
    :ivar roi: where pallets are expected (an image box and/or a depth hint, `roi.py`); detections outside are
        rejected ("outside_roi") before the pose network. None: everywhere.
    :ivar time_budget_ms: the frame's time budget from the start of `estimate`, milliseconds (None: no limit).
        Candidates are posed in the order of their detector scores; those the budget leaves no time for are
        reported as rejected ("time_budget"), never as poses. The stages check it between units of work (a
        chunk of the pose network's batch, one pallet's refinement), so a frame ends at most one unit late.
    :ivar pallet_lanes: a frame's pallets go through the fusion and pose graphs this many side by side, each on
        one thread (`stage_pose.py`; four pallets, int8, 2 cores: 40 -> 28 ms). It costs memory: a one-thread
        copy of the two graphs and each lane's activations (peak resident memory about 160 -> 220 MB int8,
        `benchmarks/memory.py`), so it is off by default. 1: one after the other, each on all `threads`;
        None: as many lanes as `threads`. With more than one lane the fit check's registration test also runs beside
        the networks, on a thread of its own (`FitCheckStage.start_registration`: 1.5-2.5 ms less a frame, about
        7 MB more memory).
    :ivar level: with the camera's calibration (`estimate(..., T_vehicle_cam=...)`): each pose is levelled, set on
        the floor where it nearly is, and refined in yaw and position with its tilt held (`level.py`) before the fit
        check, whose structure check then also tests the tilt (`StructureParams.max_tilt_deg`). On stereo depth
        too noisy for the 6-DoF refinement this gives poses the fit check can accept. None: not; without a
        calibration it does nothing.
    :ivar pallet_types: the pallet types this site uses, by name (e.g. ("epal",)): only these are posed, and a
        detector class that reports none of them is dropped. A warehouse knows its pallets; telling the estimator
        spares it guessing between look-alike types (an EPAL's front face fits a closed-deck model too), which
        costs accuracy and a refinement per extra type. None: every type of the bundle.
    :ivar weak_boxes: detections scoring under `score_threshold` but at least `WeakBoxes.score_threshold` are posed
        after the others, and kept only where the pose (levelled, with the camera's calibration) shows a pallet's
        structure clearly (`weak_boxes.py`; rejected "no_pallet_structure" otherwise). In `detect` only
        `score_threshold` counts. None: off. Calibrated forklift-approach / mixed test frames 40.9 / 27.8 -> 42.1 /
        28.3 % within 5 cm, no pose more on the pallet-free frames (docs/experiments/forklift.md, "Weak
        detections"); without a calibration the half-hidden pallets of the occluded preset's validation frames 78.4
        -> 79.6 %, no pose more on pallet-free frames or mismatched inputs ("Weak detections without a
        calibration").
    :ivar depth_proposals: with the camera's calibration (and `weak_boxes`), boxes around what stands a pallet's
        height on the floor in the depth (`depth_proposals.py`) are posed too, as detections of score 0 after the
        detector's, where no detection covers them (and, in a second round, where no accepted pose covers them); they
        are judged like weak boxes and their poses must frame their boxes. They find pallets whose look the detector
        does not know (another colour or material): on the calibrated forklift test frames with every pallet repainted
        in a random hue 34.7 / 20.4 -> 36.0 / 21.3 % within 5 cm (as rendered 42.1 / 28.3 -> 42.1 / 29.0 %), no pose
        more on the pallet-free frames (docs/experiments/forklift.md, "Proposals from the depth"). None: off.
    """

    score_threshold: float = 0.25
    iou_threshold: float = 0.5
    detector_mirror: bool = False
    max_pallets: int = 16
    depth_range_m: tuple[float, float] | None = None
    min_valid_points: int = 50
    min_confidence: float = 0.1
    min_fit: float = 0.2
    fit_tol_m: float = 0.04
    refine: bool = True
    refine_max_rms_m: float = 0.004
    refine_margin: float = 0.0
    refine_points: int = 600
    refine_iterations: int = 20
    refine_starts: int = 6
    refine_start_points: int = 300
    refine_select_tol_m: float = 0.015
    refine_start_max_rms_m: float = 0.003
    type_candidates: int = 2
    type_candidates_levelled: int = 11
    type_score_ratio: float = 0.5
    type_margin: float = 0.1
    type_margin_levelled: float = 0.04
    type_first_enough: float | None = 0.6
    nonfinite_depth: str = "raise"
    seed: int = 0
    structure: StructureParams | None = StructureParams()
    roi: RegionOfInterest | None = None
    time_budget_ms: float | None = None
    pallet_lanes: int | None = 1
    pallet_types: tuple[str, ...] | None = None
    level: LevelParams | None = LevelParams()
    weak_boxes: WeakBoxes | None = WeakBoxes()
    depth_proposals: DepthProposals | None = DepthProposals()

    def __post_init__(self) -> None:
        if not 0.0 <= self.score_threshold <= 1.0:
            raise ValueError(f"score_threshold must be in [0, 1], got {self.score_threshold}")
        if not 0.0 <= self.iou_threshold <= 1.0:
            raise ValueError(f"iou_threshold must be in [0, 1], got {self.iou_threshold}")
        if int(self.max_pallets) < 1:
            raise ValueError(f"max_pallets must be >= 1, got {self.max_pallets}")
        if not isinstance(self.detector_mirror, bool):
            raise TypeError(f"detector_mirror must be true or false, got {self.detector_mirror!r}")
        check_nonfinite_mode(self.nonfinite_depth)   # at construction, not at the first frame with NaN depth
        if self.depth_range_m is not None and not 0.0 <= self.depth_range_m[0] < self.depth_range_m[1]:
            raise ValueError(f"depth_range_m must be (min, max) with 0 <= min < max, got {self.depth_range_m}")
        if int(self.min_valid_points) < 1:
            raise ValueError(f"min_valid_points must be >= 1, got {self.min_valid_points}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if not 0.0 <= self.min_fit <= 1.0:
            raise ValueError(f"min_fit must be in [0, 1], got {self.min_fit}")
        if not -1.0 <= self.refine_margin <= 1.0:
            raise ValueError(f"refine_margin must be in [-1, 1], got {self.refine_margin}")
        if not self.refine_max_rms_m > 0:
            raise ValueError(f"refine_max_rms_m must be positive, got {self.refine_max_rms_m}")
        if not self.fit_tol_m > 0:
            raise ValueError(f"fit_tol_m must be positive, got {self.fit_tol_m}")
        if int(self.refine_points) < 10 or int(self.refine_iterations) < 0:
            raise ValueError(f"refine_points must be >= 10 and refine_iterations >= 0, got {self.refine_points}, "
                             f"{self.refine_iterations}")
        if not 0 <= int(self.refine_starts) <= MAX_STARTS:
            raise ValueError(f"refine_starts must be in [0, {MAX_STARTS}], got {self.refine_starts}")
        if int(self.refine_start_points) < 10:
            raise ValueError(f"refine_start_points must be >= 10, got {self.refine_start_points}")
        if not self.refine_select_tol_m > 0:
            raise ValueError(f"refine_select_tol_m must be positive, got {self.refine_select_tol_m}")
        if not self.refine_start_max_rms_m > 0:
            raise ValueError(f"refine_start_max_rms_m must be positive, got {self.refine_start_max_rms_m}")
        for name in ("type_candidates", "type_candidates_levelled"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 < self.type_score_ratio <= 1.0:
            raise ValueError(f"type_score_ratio must be in (0, 1], got {self.type_score_ratio}")
        if self.type_first_enough is not None and not 0.0 < self.type_first_enough <= 1.0:
            raise ValueError(f"type_first_enough must be in (0, 1] or None, got {self.type_first_enough}")
        for name in ("type_margin", "type_margin_levelled"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        if self.time_budget_ms is not None and not self.time_budget_ms >= 0:
            raise ValueError(f"time_budget_ms must be >= 0 or None, got {self.time_budget_ms}")
        if self.pallet_lanes is not None and int(self.pallet_lanes) < 1:
            raise ValueError(f"pallet_lanes must be >= 1 or None, got {self.pallet_lanes}")
        if self.pallet_types is not None:
            if isinstance(self.pallet_types, str) or not all(isinstance(t, str) and t for t in self.pallet_types) \
                    or not self.pallet_types:
                raise ValueError(f"pallet_types must be a non-empty sequence of type names or None, "
                                 f"got {self.pallet_types!r}")
            object.__setattr__(self, "pallet_types", tuple(self.pallet_types))
        if self.weak_boxes is not None and not isinstance(self.weak_boxes, WeakBoxes):
            raise TypeError(f"weak_boxes must be a WeakBoxes or None, got {type(self.weak_boxes).__name__}")
        if self.depth_proposals is not None and not isinstance(self.depth_proposals, DepthProposals):
            raise TypeError(f"depth_proposals must be a DepthProposals or None, got "
                            f"{type(self.depth_proposals).__name__}")


class PalletEstimator:
    """Pallet 6D pose estimation on a model bundle. Not thread-safe: one estimator per thread.

    :param bundle: a loaded `Bundle`.
    :param threads: onnxruntime intra-op threads per graph, and the compiled kernels' threads.
    :param precision: "fp32" or "int8" (the bundle's quantized graphs).
    :param options: `EstimatorOptions`.
    :param clock: the monotonic clock (seconds) the time budget is measured on.

    :ivar detector: `DetectorStage`. :ivar pose_network: `PoseNetworkStage`. :ivar type_choice: `TypeChoiceStage`.
    :ivar refiner: `RefinerStage`.
    :ivar fit_check: `FitCheckStage`. :ivar pallet_types: the bundle's `PalletGeometry`s.
    """

    def __init__(self, bundle: Bundle, threads: int = 2, precision: str = "fp32",
                 options: EstimatorOptions | None = None, clock: Callable[[], float] = time.perf_counter) -> None:
        if precision not in ("fp32", "int8"):
            raise ValueError(f"precision must be 'fp32' or 'int8', got {precision!r}")
        self.threads = check_threads(threads)
        self.bundle = bundle
        self.precision = precision
        self.options = o = options or EstimatorOptions()
        self.clock = clock
        spec = bundle.pose_input_spec()
        if o.depth_range_m is not None:
            spec = replace(spec, depth_range_m=tuple(o.depth_range_m))
        self.spec = spec
        self.pallet_types, self._types_of_class = bundle_geometries(bundle, o.pallet_types)
        # weak boxes come from the same decoding; `_strong` drops them where they do not count
        decode_threshold = o.score_threshold if o.weak_boxes is None else \
            min(o.score_threshold, o.weak_boxes.score_threshold)
        self.detector = DetectorStage(bundle, precision, self.threads, tuple(self._types_of_class), decode_threshold,
                                      o.iou_threshold, o.max_pallets, mirror=o.detector_mirror)
        self.pose_network = PoseNetworkStage(bundle, precision, self.threads, spec, o.seed, o.min_valid_points,
                                             lanes=self.threads if o.pallet_lanes is None else o.pallet_lanes)
        self._check_graphs_match_manifest()
        self.refiner = RefinerStage(self.pallet_types, o, self.threads)
        self.type_choice = TypeChoiceStage(self.pallet_types, self._types_of_class, self.refiner, o.fit_tol_m,
                                           o.type_candidates, o.structure or StructureParams(), o.type_margin,
                                           o.level, o.type_candidates_levelled, o.type_margin_levelled,
                                           o.type_first_enough)
        self.fit_check = FitCheckStage(self.pallet_types, o.fit_tol_m, o.min_fit, o.min_confidence, o.structure,
                                       o.weak_boxes or WeakBoxes())

    @classmethod
    def from_bundle(cls, path: str | Path, threads: int = 2, precision: str = "fp32",
                    **options) -> "PalletEstimator":
        """Load a bundle folder and build the sessions once. Keyword options go to `EstimatorOptions`."""
        return cls(load_bundle(path), threads=threads, precision=precision, options=EstimatorOptions(**options))

    def close(self) -> None:
        """Stop the worker threads (pallet lanes, registration test); an estimator still works afterwards."""
        self.pose_network.close()
        self.fit_check.close()

    # the first pallet type's model, for callers that score or draw one type
    @property
    def model_points_m(self) -> np.ndarray:
        """(n, 3) model points of the bundle's first pallet type, metres."""
        return self.pallet_types[0].points_m

    @property
    def symmetries(self) -> np.ndarray:
        """(S, 4, 4) symmetries of the bundle's first pallet type."""
        return self.pallet_types[0].symmetries

    @property
    def model_size_m(self) -> np.ndarray:
        """(3,) size of the bundle's first pallet type, metres."""
        return self.pallet_types[0].size_m

    @property
    def model_boxes_m(self) -> np.ndarray | None:
        """(k, 2, 3) boards and blocks of the bundle's first pallet type, metres, or None."""
        return self.pallet_types[0].boxes_m

    @property
    def refines(self) -> bool:
        """Whether poses are refined (for at least one pallet type)."""
        return self.refiner.enabled

    def _check_graphs_match_manifest(self) -> None:
        """Fixed axes the graphs declare must equal the manifest's sizes."""
        d, f, q = self.bundle.detector, self.bundle.fusion, self.bundle.pose
        problems = []

        def expect(model: OnnxModel, name: str, axis: int, value: int, what: str) -> None:
            shape = model.input_shape(name)
            if len(shape) <= axis:
                problems.append(f"{model.path.name} input {name!r} has rank {len(shape)}")
            elif isinstance(shape[axis], int) and shape[axis] != value:
                problems.append(f"{model.path.name} input {name!r} axis {axis} is {shape[axis]}, the manifest's "
                                f"{what} is {value}")

        det, fusion, pose = self.detector.model, self.pose_network.fusion, self.pose_network.pose
        expect(det, d.input_name, 1, d.input_channels, "detector input channels (3, or 4 with depth_max_m)")
        for i, (h, w) in enumerate(d.input_sizes):
            where = "detector.input_hw" if not d.multi_size else f"detector.input_sizes[{i}]"
            expect(det, d.input_name, 2, h, f"{where}[0]")
            expect(det, d.input_name, 3, w, f"{where}[1]")
        expect(fusion, f.rgb_input, 2, f.crop_hw[0], "fusion.crop_hw[0]")
        expect(fusion, f.rgb_input, 3, f.crop_hw[1], "fusion.crop_hw[1]")
        expect(pose, q.points_input, 1, q.num_points, "pose.num_points")
        expect(pose, q.features_input, 2, f.feature_dim, "fusion.feature_dim")
        if problems:
            raise BundleError(f"bundle {self.bundle.root} disagrees with its own graphs: " + "; ".join(problems))

    # -- public API -----------------------------------------------------------------------------
    def predict(self, rgb, depth=None, K=None, depth_scale=None) -> list[PalletPose]:
        """Accepted pallet poses of one frame (empty list when none).

        :param rgb: (H, W, 3) uint8 RGB, or an `RGBDFrame` (then depth/K/scale come from it).
        :param depth: (H, W) uint16 (units of `depth_scale` metres, default mm) or float metres, aligned to rgb.
        :param K: (3, 3) intrinsics.
        :param depth_scale: metres per unit of uint16 depth.
        """
        return self.estimate(rgb, depth, K, depth_scale).poses

    def detect(self, rgb: np.ndarray, depth_m: np.ndarray | None = None) -> Detections:
        """The detector stage alone: boxes (image pixels, xyxy), scores and class ids after NMS, highest score
        first, at most `max_pallets` (as `decode_yolov8` returns them).

        :param rgb: (H, W, 3) uint8 RGB. :param depth_m: (H, W) float metres aligned to rgb, or None: used by an
            RGB-D detector (`detector.depth_max_m`), which without it sees "no depth"; an RGB detector ignores it.
        """
        rgb = check_rgb(rgb)
        if depth_m is not None:
            depth_m = np.asarray(depth_m)
            if depth_m.shape != rgb.shape[:2]:
                raise ValueError(f"depth_m is {depth_m.shape}, expected {rgb.shape[:2]} (the rgb image's H, W)")
        return self._strong(self._detect(rgb, {}, depth_m))

    def estimate(self, rgb, depth=None, K=None, depth_scale=None, T_vehicle_cam=None) -> FrameResult:
        """Like `predict`, but the whole `FrameResult` (accepted, rejected, timings).

        :param T_vehicle_cam: (4, 4) the camera's calibration (`calib`), or None: with it the poses stand level on
            the vehicle's floor (`EstimatorOptions.level`); they stay in the camera frame either way.
        """
        t0 = time.perf_counter()
        deadline = Deadline(self.options.time_budget_ms, clock=self.clock)
        rgb, depth_m, K = self.check_inputs(rgb, depth, K, depth_scale)
        T_vc = _check_T_vehicle_cam(T_vehicle_cam)
        timings: dict[str, float] = {}
        cands = self._run(rgb, depth_m, K, self._detect(rgb, timings, depth_m), timings, deadline, T_vc,
                          weak_below=self.options.score_threshold)
        return self._result(cands, depth_m.shape, timings, t0)

    def estimate_boxes(self, rgb, depth=None, K=None, depth_scale=None, boxes_xyxy=None, scores=None,
                       class_ids=None, T_vehicle_cam=None) -> FrameResult:
        """The pose stages on boxes from elsewhere (a shared detector): (n, 4) image pixels, (n,) scores,
        (n,) detector class ids of this bundle (default: the first pallet class); `T_vehicle_cam` as `estimate`."""
        t0 = time.perf_counter()
        deadline = Deadline(self.options.time_budget_ms, clock=self.clock)
        rgb, depth_m, K = self.check_inputs(rgb, depth, K, depth_scale)
        T_vc = _check_T_vehicle_cam(T_vehicle_cam)
        timings: dict[str, float] = {}
        cands = self._run(rgb, depth_m, K, self._boxes(boxes_xyxy, scores, class_ids), timings, deadline, T_vc)
        return self._result(cands, depth_m.shape, timings, t0)

    def candidates(self, rgb, depth=None, K=None, depth_scale=None, detections: Detections | None = None,
                   timings: dict[str, float] | None = None, T_vehicle_cam=None) -> Candidates:
        """Every stage's output for every detection of the frame (`Candidates`), for tools and benchmarks.

        :param detections: boxes from elsewhere (`Detections`, image pixels), or None to run the detector.
        :param timings: optional dict that receives the stages' milliseconds.
        """
        deadline = Deadline(self.options.time_budget_ms, clock=self.clock)
        rgb, depth_m, K = self.check_inputs(rgb, depth, K, depth_scale)
        timings = {} if timings is None else timings
        T_vc = _check_T_vehicle_cam(T_vehicle_cam)
        if detections is not None:
            return self._run(rgb, depth_m, K, detections, timings, deadline, T_vc)
        return self._run(rgb, depth_m, K, self._detect(rgb, timings, depth_m), timings, deadline, T_vc,
                         weak_below=self.options.score_threshold)

    def check_inputs(self, rgb, depth=None, K=None, depth_scale=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The validated frame: (rgb (H, W, 3) uint8, depth float32 metres (H, W), K (3, 3)), from arrays or
        an `RGBDFrame` (`inputs.check_rgbd`)."""
        if hasattr(rgb, "rgb") and hasattr(rgb, "depth") and hasattr(rgb, "K"):   # an RGBDFrame
            frame = rgb
            if depth is not None:
                raise ValueError("pass either an RGBDFrame or rgb + depth, not both")
            rgb, depth = frame.rgb, frame.depth
            K = frame.K if K is None else K
            depth_scale = getattr(frame, "depth_scale_m", None) if depth_scale is None else depth_scale
        if depth is None:
            raise ValueError("depth is missing: pass depth (H, W) aligned to rgb, or an RGBDFrame")
        return check_rgbd(rgb, depth, K, depth_scale, self.options.nonfinite_depth)

    # -- the pipeline ---------------------------------------------------------------------------
    def _detect(self, rgb: np.ndarray, timings: dict[str, float], depth_m: np.ndarray | None = None) -> Detections:
        t = time.perf_counter()
        x, lb = self.detector.preprocess(rgb, depth_m)
        timings["preprocess"] = elapsed_ms(t)
        t = time.perf_counter()
        raw = self.detector.infer(x)
        timings["detector"] = elapsed_ms(t)
        t = time.perf_counter()
        det = self.detector.postprocess(raw, lb)
        timings["decode_nms"] = elapsed_ms(t)
        return det

    def _strong(self, det: Detections) -> Detections:
        """`det` without the weak boxes (those not above `score_threshold`, decoded for `weak_boxes`)."""
        if self.options.weak_boxes is None:
            return det
        return det.take(np.flatnonzero(det.scores > self.options.score_threshold))    # as the decoding compares

    def _boxes(self, boxes_xyxy, scores, class_ids) -> Detections:
        if boxes_xyxy is None:
            raise ValueError("estimate_boxes needs boxes_xyxy (n, 4)")
        boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
        scores = np.ones(len(boxes)) if scores is None else np.asarray(scores, dtype=np.float64).reshape(-1)
        if len(scores) != len(boxes):
            raise ValueError(f"{len(boxes)} boxes but {len(scores)} scores")
        if not (np.isfinite(boxes).all() and np.isfinite(scores).all()):
            raise ValueError("boxes_xyxy and scores must be finite numbers (image pixels; detector scores)")
        first = min(self._types_of_class)
        class_ids = np.full(len(boxes), first) if class_ids is None else np.asarray(class_ids, np.int64).reshape(-1)
        if len(class_ids) != len(boxes):
            raise ValueError(f"{len(boxes)} boxes but {len(class_ids)} class ids")
        unknown = sorted({int(c) for c in class_ids} - set(self._types_of_class))
        if unknown:
            raise ValueError(f"class ids {unknown} are not pallet classes of bundle {self.bundle.name} "
                             f"(pallet classes: {sorted(self._types_of_class)})")
        return Detections(boxes, scores, class_ids)

    def _run(self, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, det: Detections,
             timings: dict[str, float], deadline: Deadline, T_vehicle_cam: np.ndarray | None = None,
             weak_below: float | None = None) -> Candidates:
        """The stages after the detector on `det`, highest score first, at most `max_pallets`; with `weak_below`
        (the detector's own boxes), those not above it are weak boxes (`weak_boxes.py`), and with a calibration the
        depth's proposals too (`depth_proposals.py`): first those no detection covers, then, in a second round,
        those no accepted pose covers."""
        for s in STAGES:
            timings.setdefault(s, 0.0)
        if T_vehicle_cam is not None and self.options.level is not None and self.options.level.floor_from_depth:
            T_vehicle_cam = self._floor_of_frame(T_vehicle_cam, depth_m, K, timings)
        held = None
        if weak_below is not None and T_vehicle_cam is not None and self.options.weak_boxes is not None \
                and self.options.depth_proposals is not None:
            det, held = self._with_depth_proposals(det, depth_m, K, T_vehicle_cam, timings)
        order = np.argsort(-det.scores, kind="stable")
        if held is not None:    # the depth's proposals (score 0, `DepthProposals.max_boxes`) keep places of their own
            own = det.scores[order] == 0.0
            order = np.concatenate([order[~own][:self.options.max_pallets], order[own]])
        else:
            order = order[:self.options.max_pallets]
        det = det.take(order)
        cands = self._pose_candidates(rgb, depth_m, K, det, timings, deadline, T_vehicle_cam, weak_below,
                                      proposed=held is not None)
        if held is None or not len(held):
            return cands
        # the proposals a detection covers are posed where none of the frame's accepted poses took them
        free = held[self._not_taken(held, cands.boxes_xyxy[cands.alive])]
        if not len(free):
            return cands
        retry = self._proposed(det.take(np.zeros(0, dtype=np.int64)), free)
        cands = Candidates.concat([cands, self._pose_candidates(rgb, depth_m, K, retry, timings, deadline,
                                                                T_vehicle_cam, weak_below, proposed=True)])
        self._drop_duplicates(cands, timings)
        return cands

    def _not_taken(self, boxes_xyxy: np.ndarray, taken_xyxy: np.ndarray) -> np.ndarray:
        """(n,) bool: boxes (n, 4) that no box of `taken_xyxy` (m, 4) covers (`DepthProposals.max_iou`) or holds
        (`WeakBoxes.max_inside`)."""
        if len(boxes_xyxy) == 0 or len(taken_xyxy) == 0:
            return np.ones(len(boxes_xyxy), dtype=bool)
        covered = box_iou(boxes_xyxy, taken_xyxy).max(axis=1) >= self.options.depth_proposals.max_iou
        if self.options.weak_boxes is not None:
            covered |= inside_fraction(boxes_xyxy, taken_xyxy) >= self.options.weak_boxes.max_inside
        return ~covered

    def _pose_candidates(self, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, det: Detections,
                         timings: dict[str, float], deadline: Deadline, T_vehicle_cam: np.ndarray | None,
                         weak_below: float | None, proposed: bool) -> Candidates:
        """The stages after the detector on every row of `det` (`proposed`: its score-0 rows are the depth's
        proposals)."""
        options = self._type_options(det)
        type_index = [o[0] for o in options]   # the type choice may change it
        cands = Candidates.new(det.boxes_xyxy, det.scores, det.class_ids, type_index, self.spec.num_points, options)
        weak = None if weak_below is None or self.options.weak_boxes is None else cands.scores <= weak_below
        from_depth = cands.scores == 0.0 if proposed else None       # the depth's proposals: score 0
        if weak is not None:
            self._screen_weak_boxes(cands, weak)
        if self.options.roi is not None:
            keep, why = roi_filter(cands.boxes_xyxy, depth_m, self.options.roi)
            drop = np.flatnonzero(~keep)
            cands.reject(drop, "outside_roi", [why[i] for i in drop])
        if not len(cands):
            return cands
        # the fit check's frame-level registration test needs only the boxes: with lanes (speed before memory: its
        # thread holds a few MB) it runs while the networks do
        registration = None
        if self.pose_network.lanes > 1:
            tested = cands.alive if from_depth is None else cands.alive & ~from_depth
            registration = self.fit_check.start_registration(cands.boxes_xyxy[tested], depth_m, rgb)
        try:
            self.pose_network(rgb, depth_m, K, cands, timings, deadline)
            # the fit check refuses these whatever their type and refinement: not worth either (with a calibration
            # every type of a candidate is levelled, the most costly work of the frame)
            floor = np.full(len(cands), self.options.min_confidence)
            if weak is not None and T_vehicle_cam is not None:
                # the pose of a box the detector is sure of but the network is not is weak (a weak box's or a depth
                # proposal's, unsure twice, is not posed)
                floor[~weak] = min(self.options.min_confidence, self.options.weak_boxes.min_confidence)
                weak |= cands.confidence < self.options.min_confidence
            low = np.flatnonzero(cands.alive & (cands.confidence < floor))
            cands.reject(low, "low_confidence", [f"confidence {c:.3f} < {f}" for c, f in
                                                 zip(cands.confidence[low], floor[low])])
            self.type_choice(cands, depth_m, K, timings, deadline, T_vehicle_cam)
            self.refiner(cands, depth_m, K, timings, deadline)
            up_cam = None
            if T_vehicle_cam is not None and self.options.level is not None:
                pts_of = self._level(cands, depth_m, K, T_vehicle_cam, timings)
                up_cam = up_in_camera(T_vehicle_cam)
            self.fit_check(cands, depth_m, K, timings, rgb, up_cam, registration, weak, from_depth, floor)
            if from_depth is not None:
                self._frame_proposals(cands, K, depth_m.shape, from_depth)
            if up_cam is not None:
                self._climb(cands, depth_m, K, T_vehicle_cam, pts_of, timings)
            self._drop_duplicates(cands, timings)
        finally:
            if registration is not None:        # it reads the caller's arrays: done before they are handed back
                wait([registration[1]])
        return cands

    def _floor_of_frame(self, T_vehicle_cam: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                        timings: dict[str, float]) -> np.ndarray:
        """The calibration with its floor moved onto this frame's floor where the depth shows it near the calibrated
        one (`floor.refine_floor`; `LevelParams.floor_from_depth`), else as it is. Its time counts as refine."""
        if not T_vehicle_cam[2, 3] > 0:             # the camera below its floor: nothing to refine from
            return T_vehicle_cam
        t = time.perf_counter()
        up = T_vehicle_cam[2, :3] / np.linalg.norm(T_vehicle_cam[2, :3])
        floor = refine_floor(FloorPlane(up, float(T_vehicle_cam[2, 3])), depth_m, K)
        timings["refine"] = timings.get("refine", 0.0) + elapsed_ms(t)
        return T_vehicle_cam if floor is None else on_floor(T_vehicle_cam, floor)

    def _with_depth_proposals(self, det: Detections, depth_m: np.ndarray, K: np.ndarray, T_vehicle_cam: np.ndarray,
                              timings: dict[str, float]) -> tuple[Detections, np.ndarray]:
        """`det` and the depth's proposals (`depth_proposals.py`, the nearest `max_boxes`) that no detection covers
        (`_proposed`); and the (m, 4) boxes of the proposals a detection covers, held back."""
        t = time.perf_counter()
        p = self.options.depth_proposals
        boxes = propose_boxes(depth_m, K, T_vehicle_cam, p)[:p.max_boxes]
        free = self._not_taken(boxes, det.boxes_xyxy)
        det = self._proposed(det, boxes[free])
        timings["proposals"] = timings.get("proposals", 0.0) + elapsed_ms(t)
        return det, boxes[~free]

    def _proposed(self, det: Detections, boxes_xyxy: np.ndarray) -> Detections:
        """`det` with the depth's proposals (n, 4) after it: score 0, class scores 0 where the detector gives them
        (so the type choice weighs every class's types)."""
        n = len(boxes_xyxy)
        cs = None if det.class_scores is None else \
            np.concatenate([det.class_scores, np.zeros((n, det.class_scores.shape[1]))])
        return Detections(np.concatenate([det.boxes_xyxy, boxes_xyxy]), np.concatenate([det.scores, np.zeros(n)]),
                          np.concatenate([det.class_ids, np.full(n, min(self._types_of_class))]), cs)

    def _frame_proposals(self, cands: Candidates, K: np.ndarray, image_hw: tuple[int, int],
                         from_depth: np.ndarray) -> None:
        """The depth's proposals (`from_depth` rows) whose accepted pose leaves their box mostly empty, or reaches far
        beyond it, posed something else (`DepthProposals.min_framing_iou`)."""
        rows = np.flatnonzero(cands.alive & from_depth)
        if len(rows) == 0:
            return
        sizes = np.array([self.pallet_types[int(j)].size_m for j in cands.type_index[rows]])
        iou = framing_iou(cands.T_cam_pallet[rows], sizes, K, cands.boxes_xyxy[rows], image_hw)
        low = iou < self.options.depth_proposals.min_framing_iou
        cands.reject(rows[low], "no_pallet_structure",
                     [f"no_pallet_structure: a depth proposal is kept only where its pose frames its box: IoU {v:.2f} "
                      f"< {self.options.depth_proposals.min_framing_iou}" for v in iou[low]])

    def _screen_weak_boxes(self, cands: Candidates, weak: np.ndarray) -> None:
        """Weak boxes mostly inside a stronger detection's box are parts of what it found: not posed."""
        rows = np.flatnonzero(weak & cands.alive)
        inside = inside_fraction(cands.boxes_xyxy[rows], cands.boxes_xyxy[cands.alive & ~weak])
        part = inside >= self.options.weak_boxes.max_inside
        cands.reject(rows[part], "duplicate",
                     [f"duplicate: a weak detection (score {cands.scores[i]:.2f}) {f:.0%} inside a stronger "
                      f"detection's box" for i, f in zip(rows[part], inside[part])])

    def _drop_duplicates(self, cands: Candidates, timings: dict[str, float]) -> None:
        """Of accepted poses that occupy the same space (`overlap.py`), the highest-scoring detection's stays."""
        t = time.perf_counter()
        rows = np.flatnonzero(cands.alive)          # highest detector score first
        if len(rows) > 1:
            sizes = np.array([self.pallet_types[int(j)].size_m for j in cands.type_index[rows]])
            dup = duplicate_of(cands.T_cam_pallet[rows], sizes)
            for k in np.flatnonzero(dup >= 0):
                first = rows[dup[k]]
                box = np.round(cands.boxes_xyxy[first]).astype(int).tolist()
                cands.reject([rows[k]], "duplicate",
                             f"duplicate: the pose occupies the space of the pose of a higher-scoring detection "
                             f"(score {cands.scores[first]:.2f}, box {box})")
        timings["fit"] = timings.get("fit", 0.0) + elapsed_ms(t)

    def _type_options(self, det: Detections) -> list[tuple[int, ...]]:
        """Each detection's type indexes: its class's types first, then those of the pallet classes that score it
        at least `type_score_ratio` of its score (where the detector's class scores are known)."""
        out = []
        for i, c in enumerate(det.class_ids):
            types = list(self._types_of_class[int(c)])
            if det.class_scores is not None and self.options.type_score_ratio < 1.0:
                row = det.class_scores[i]
                for other in sorted(self._types_of_class, key=lambda k: -row[k] if k < len(row) else 0.0):
                    if other != c and other < len(row) and row[other] >= self.options.type_score_ratio * row[c]:
                        types += [j for j in self._types_of_class[other] if j not in types]
            out.append(tuple(types))
        return out

    def _climb(self, cands: Candidates, depth_m: np.ndarray, K: np.ndarray, T_vehicle_cam: np.ndarray,
               pts_of: dict[int, np.ndarray], timings: dict[str, float]) -> None:
        """The accepted level poses climb the soft ray score (`level.climb_poses`), after the fit check has judged
        them, so the climb never turns a rejected pose into an accepted one; a moved pose's fit is computed again
        for its report. `pts_of`: each levelled row's depth points (`_level`). Its time counts as refine."""
        t = time.perf_counter()
        rows = np.flatnonzero(cands.alive)
        rows = rows[np.abs(cands.T_cam_pallet[rows, :3, 2] @ up_in_camera(T_vehicle_cam) - 1.0) < 1e-6]  # level only
        if len(rows):
            geoms = [self.pallet_types[int(j)] for j in cands.type_index[rows]]
            n_pts = self.options.level.climb_points
            pts = [pts_of[int(i)] if n_pts == 0 else self.refiner.box_points(cands.pixels[i], depth_m, K, n_pts)
                   for i in rows]
            # a pallet the levelling did not set on the floor (rack, stack, truck bed) climbs in height too
            z_vehicle_m = (T_vehicle_cam @ cands.T_cam_pallet[rows])[:, 2, 3]
            on_floor = np.abs(z_vehicle_m - np.array([g.size_m[2] / 2 for g in geoms])) < 1e-6
            T_cp = climb_poses(cands.T_cam_pallet[rows], pts, [g.boxes_m for g in geoms], self.options.level,
                               threads=self.refiner.refine_options.threads, lift=~on_floor)
            moved = rows[np.abs(T_cp - cands.T_cam_pallet[rows]).max(axis=(1, 2)) > 1e-9]
            cands.assign(rows, T_cam_pallet=T_cp)
            if len(moved):
                cands.assign(moved, fit=self.fit_check.score(cands.T_cam_pallet[moved], cands.points_cam[moved],
                                                             cands.type_index[moved], depth_m, K))
        timings["refine"] = timings.get("refine", 0.0) + elapsed_ms(t)

    def _level(self, cands: Candidates, depth_m: np.ndarray, K: np.ndarray, T_vehicle_cam: np.ndarray,
               timings: dict[str, float]) -> dict[int, np.ndarray]:
        """The alive candidates' poses levelled on the calibrated floor and refined with their tilt held
        (`level.level_poses`); a changed pose's fit is computed again by the fit check. Its time counts as refine.

        :return: each levelled row's depth points (the refiner's ICP points), for the climb."""
        t = time.perf_counter()
        rows = np.flatnonzero(cands.alive)
        pts: list[np.ndarray] = []
        if len(rows):
            geoms = [self.pallet_types[int(j)] for j in cands.type_index[rows]]
            pts = [self.refiner.box_points(cands.pixels[i], depth_m, K) for i in rows]   # the refiner's ICP points
            T_cp = level_in_camera(cands.T_cam_pallet[rows], T_vehicle_cam, geoms, self.options.level, pts,
                                   self.refiner.refine_options.threads, self.refiner.icp_grids(cands.type_index[rows]))
            moved = rows[np.abs(T_cp - cands.T_cam_pallet[rows]).max(axis=(1, 2)) > 1e-9]
            cands.assign(rows, T_cam_pallet=T_cp)
            cands.assign(moved, fit=np.full((len(moved), 3), np.nan))
        timings["refine"] = timings.get("refine", 0.0) + elapsed_ms(t)
        return dict(zip(rows.tolist(), pts))

    def _result(self, cands: Candidates, image_hw: tuple[int, int], timings: dict[str, float],
                t0: float) -> FrameResult:
        """Accepted poses and rejections in the candidates' order (highest detector score first)."""
        poses, rejected = [], []
        for i in range(len(cands)):
            pose = None
            if not np.isnan(cands.fit[i, 2]):
                g = self.pallet_types[int(cands.type_index[i])]
                pose = PalletPose(cands.T_cam_pallet[i], cands.confidence[i], cands.scores[i], cands.boxes_xyxy[i],
                                  int(cands.n_valid[i]), FitScore(*cands.fit[i]),
                                  self._class_name(int(cands.class_ids[i])), g.name)
            if cands.reason[i] == "":
                poses.append(pose)
            else:
                rejected.append(Rejection(cands.boxes_xyxy[i], cands.scores[i], cands.reason[i], cands.detail[i],
                                          int(cands.n_valid[i]), pose))
        timings["total"] = elapsed_ms(t0)
        return FrameResult(poses=poses, rejected=rejected, timings_ms=timings, image_hw=tuple(image_hw))

    def _class_name(self, class_id: int) -> str:
        classes = self.bundle.classes
        return classes[class_id] if 0 <= class_id < len(classes) else str(class_id)


def _check_T_vehicle_cam(T) -> np.ndarray | None:
    """The calibration's (4, 4) camera-to-vehicle transform as float64, or None; a clear error for anything else."""
    if T is None:
        return None
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]) \
            or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) or np.linalg.det(T[:3, :3]) < 0:
        raise ValueError(f"T_vehicle_cam must be a finite (4, 4) rigid transform (a rotation and a translation), got "
                         f"shape {T.shape}")
    return T
