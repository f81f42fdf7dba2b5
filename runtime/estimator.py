"""`PalletEstimator`: RGB-D frame -> pallet 6D poses, on a model bundle's ONNX graphs (never torch).

Pipeline (paper section 3, batched over the pallets of a frame):

    letterbox -> detector.onnx -> YOLOv8 decode + NMS (numpy)            detector.py
    -> crop / encode / select + sample N points / back-project / centre   pose_inputs.py (shared with training)
    -> fusion.onnx (B crops at once) -> gather features at the sampled pixels
    -> pose.onnx (B pallets at once) -> most confident per-point hypothesis   selection.py
    -> robust point-to-plane ICP on the box's depth, pallet as boards/blocks  refine.py
       (+ ICP from starts around the pose; the landing that fits best wins)
    -> geometric fit check against the depth image                           fit.py

`predict(...)` returns the accepted `PalletPose`s; `estimate(...)` returns the whole `FrameResult`:
accepted poses, rejected detections with their reasons, per-stage milliseconds. `estimate_boxes(...)`
starts after the detector, for a forklift that already runs a shared object detector.

Point sampling is seeded per detection from `options.seed` and the detection's clamped box, so a
result depends only on the frame and the box: the same frame gives the same poses, and a pallet gets
the same pose whether it is estimated alone or with others.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .inputs import check_nonfinite_mode
from .bundle import Bundle, BundleError, load_bundle
from .detector import Detections, decode_yolov8, letterbox, to_nchw, undo_letterbox
from .fit import fit_score
from .geometry import clamp_box
from .inputs import check_rgb, check_rgbd
from .pose_inputs import PoseBatch, gather_features, prepare_pose_inputs
from .refine import MAX_STARTS, best_landing, box_points, refine_pose
from .results import FitScore, FrameResult, PalletPose, Rejection
from .selection import select_poses
from .sessions import OnnxModel

__all__ = ["EstimatorOptions", "PalletEstimator"]

log = logging.getLogger(__name__)

# The fusion and pose graphs run on at most this many pallets at once. onnxruntime's memory arena keeps the
# largest batch it has seen: 16 pallets in one batch held about 95 MB more for good than 8 (soak, session 7),
# while batches larger than 8 save little time per pallet.
GRAPH_BATCH = 8
STAGES = ("preprocess", "detector", "decode_nms", "pose_inputs", "fusion", "pose", "selection", "refine", "fit")


@dataclass(frozen=True)
class EstimatorOptions:
    """Run-time choices (the model's own sizes and normalisation come from the bundle, never from here).

    :ivar score_threshold: detector class score a box must exceed.
    :ivar iou_threshold: NMS IoU above which the weaker box of the same class goes.
    :ivar max_pallets: at most this many detections (highest scores) go to the pose stage. Each costs about
        40 ms on 2 cores; 16 covers the fullest racks of the validation sets (18 pallets at least 10 % visible,
        35 of 200 occluded frames had more than 8, the limit before session 7).
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
        0 turns it off. The default 6 (session 10) against the 4 before: validation virtual-occluded
        79.6 -> 82.0 % within 5 cm, virtual-clean 96.8 -> 97.3 %, indoor-noisy unchanged (measured with 10; the
        last 4 of those 10 changed 1 pallet in 1815 with the session-10 networks, for half again the time of
        a frame; `benchmarks/results/refine-starts.md`).
    :ivar refine_start_points: depth points each extra start uses (an even subset of `refine_points`).
    :ivar refine_select_tol_m: tolerance of the fit score that compares landings, metres (tighter than
        `fit_tol_m`: on depth clean enough to trust ICP, 1.5 cm separates the right landing).
    :ivar refine_start_max_rms_m: a landing counts only when its ICP RMS is below this, metres. Stricter
        than `refine_max_rms_m`: on stereo-noisy depth some landings reach 3-4 mm by chance and then win
        wrongly; on clean depth most landings that help are below 3 mm.
    :ivar nonfinite_depth: "raise" on NaN/inf depth, or "as_missing".
    :ivar seed: seed of the per-detection point sampling.
    """

    score_threshold: float = 0.25
    iou_threshold: float = 0.5
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
    nonfinite_depth: str = "raise"
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.score_threshold <= 1.0:
            raise ValueError(f"score_threshold must be in [0, 1], got {self.score_threshold}")
        if not 0.0 <= self.iou_threshold <= 1.0:
            raise ValueError(f"iou_threshold must be in [0, 1], got {self.iou_threshold}")
        if int(self.max_pallets) < 1:
            raise ValueError(f"max_pallets must be >= 1, got {self.max_pallets}")
        check_nonfinite_mode(self.nonfinite_depth)   # at construction, not at the first frame with NaN depth
        if self.depth_range_m is not None and not 0.0 <= self.depth_range_m[0] < self.depth_range_m[1]:
            raise ValueError(f"depth_range_m must be (min, max) with 0 <= min < max, got {self.depth_range_m}")
        if int(self.min_valid_points) < 1:
            raise ValueError(f"min_valid_points must be >= 1, got {self.min_valid_points}")
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


class PalletEstimator:
    """Pallet 6D pose estimation on a model bundle. Not thread-safe: one estimator per thread.

    :param bundle: a loaded `Bundle`.
    :param threads: onnxruntime intra-op threads per graph.
    :param precision: "fp32" or "int8" (the bundle's quantized graphs).
    :param options: `EstimatorOptions`.
    """

    def __init__(self, bundle: Bundle, threads: int = 2, precision: str = "fp32",
                 options: EstimatorOptions | None = None) -> None:
        if precision not in ("fp32", "int8"):
            raise ValueError(f"precision must be 'fp32' or 'int8', got {precision!r}")
        self.bundle = bundle
        self.precision = precision
        self.threads = int(threads)
        self.options = options or EstimatorOptions()
        spec = bundle.pose_input_spec()
        if self.options.depth_range_m is not None:
            spec = dataclasses.replace(spec, depth_range_m=tuple(self.options.depth_range_m))
        self.spec = spec
        self._load_sessions()
        self._check_graphs_match_manifest()
        # the fit score needs the model as points (a bundle carries points, not boxes)
        self.model_points_m = bundle.pallet.points().astype(np.float64)
        self.model_size_m = np.asarray(bundle.pallet.size_m, dtype=np.float64)
        self.symmetries = np.asarray(bundle.pallet.symmetries, dtype=np.float64)
        self.model_boxes_m = bundle.pallet.boxes_m
        self.refines = bool(self.options.refine and self.options.refine_iterations > 0 and self.model_boxes_m is not None)
        if self.options.refine and self.model_boxes_m is None:
            log.warning("bundle %s has no pallet boxes_m: poses are not refined", bundle.name)
        det = bundle.detector
        names = [c.lower() for c in bundle.classes]
        # a detector from another toolchain may know more classes than pallets: use the pallet ones
        self._pallet_class_ids = tuple(i for i, c in enumerate(names) if "pallet" in c) or tuple(range(len(names)))
        # reused across frames: the letterboxed image and the detector's input tensor
        self._lb_buf = np.empty((*det.input_hw, 3), np.uint8)
        self._det_in = np.empty((1, 3, *det.input_hw), np.float32)

    @classmethod
    def from_bundle(cls, path: str | Path, threads: int = 2, precision: str = "fp32",
                    **options) -> "PalletEstimator":
        """Load a bundle folder and build the sessions once. Keyword options go to `EstimatorOptions`."""
        return cls(load_bundle(path), threads=threads, precision=precision, options=EstimatorOptions(**options))

    # -- setup ----------------------------------------------------------------------------------
    def _load_sessions(self) -> None:
        b, p = self.bundle, self.precision
        d, f, q = b.detector, b.fusion, b.pose
        self.detector = OnnxModel(b.graph("detector", p), self.threads, (d.input_name,), (d.output_name,))
        self.fusion = OnnxModel(b.graph("fusion", p), self.threads, (f.rgb_input, f.depth_input), (f.output_name,))
        self.pose = OnnxModel(b.graph("pose", p), self.threads, (q.points_input, q.features_input),
                              (q.quat_output, q.trans_output, q.conf_output))

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

        expect(self.detector, d.input_name, 2, d.input_hw[0], "detector.input_hw[0]")
        expect(self.detector, d.input_name, 3, d.input_hw[1], "detector.input_hw[1]")
        expect(self.fusion, f.rgb_input, 2, f.crop_hw[0], "fusion.crop_hw[0]")
        expect(self.fusion, f.rgb_input, 3, f.crop_hw[1], "fusion.crop_hw[1]")
        expect(self.pose, q.points_input, 1, q.num_points, "pose.num_points")
        expect(self.pose, q.features_input, 2, f.feature_dim, "fusion.feature_dim")
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

    def detect(self, rgb: np.ndarray) -> Detections:
        """The detector stage alone: boxes (image pixels, xyxy), scores and class ids after NMS, highest score
        first, at most `max_pallets` (as `decode_yolov8` returns them). :param rgb: (H, W, 3) uint8 RGB."""
        return self._detect(check_rgb(rgb), {})

    def estimate(self, rgb, depth=None, K=None, depth_scale=None) -> FrameResult:
        """Like `predict`, but the whole `FrameResult` (accepted, rejected, timings)."""
        t0 = time.perf_counter()
        rgb, depth_m, K = self._inputs(rgb, depth, K, depth_scale)
        timings: dict[str, float] = {}
        detections = self._detect(rgb, timings)
        return self._estimate_from_detections(rgb, depth_m, K, detections, timings, t0)

    def estimate_boxes(self, rgb, depth=None, K=None, depth_scale=None, boxes_xyxy=None,
                       scores=None) -> FrameResult:
        """The pose stage on boxes from elsewhere (a shared detector): (n, 4) image pixels, (n,) scores."""
        t0 = time.perf_counter()
        rgb, depth_m, K = self._inputs(rgb, depth, K, depth_scale)
        if boxes_xyxy is None:
            raise ValueError("estimate_boxes needs boxes_xyxy (n, 4)")
        boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
        scores = np.ones(len(boxes)) if scores is None else np.asarray(scores, dtype=np.float64).reshape(-1)
        if len(scores) != len(boxes):
            raise ValueError(f"{len(boxes)} boxes but {len(scores)} scores")
        det = Detections(boxes, scores, np.full(len(boxes), self._pallet_class_ids[0]))
        return self._estimate_from_detections(rgb, depth_m, K, det, {}, t0)

    def _class_name(self, class_id: int) -> str:
        classes = self.bundle.classes
        return classes[class_id] if 0 <= class_id < len(classes) else str(class_id)

    # -- stages ---------------------------------------------------------------------------------
    def _inputs(self, rgb, depth, K, depth_scale):
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

    def _detect(self, rgb: np.ndarray, timings: dict[str, float]) -> Detections:
        t = time.perf_counter()
        d = self.bundle.detector
        img, lb = letterbox(rgb, d.input_hw, d.letterbox_pad_value, out=self._lb_buf)
        to_nchw(img, d.rgb_mean, d.rgb_std, d.pixel_scale, d.channel_order == "BGR", out=self._det_in)
        timings["preprocess"] = _ms(t)
        t = time.perf_counter()
        out = self.detector.run({d.input_name: self._det_in}, [d.output_name])[d.output_name]
        timings["detector"] = _ms(t)
        t = time.perf_counter()
        o = self.options
        det = decode_yolov8(out, o.score_threshold, o.iou_threshold, self._pallet_class_ids, o.max_pallets)
        det = Detections(undo_letterbox(det.boxes_xyxy, lb), det.scores, det.class_ids)
        timings["decode_nms"] = _ms(t)
        return det

    def _pose_inputs(self, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, boxes: np.ndarray) -> PoseBatch:
        """`prepare_pose_inputs` box by box, each with its own generator seeded by (seed, clamped box)."""
        rows = []
        for box in boxes:
            box_i = clamp_box(box, depth_m.shape)
            key = [int(self.options.seed)] + ([] if box_i is None else [int(c) for c in box_i])
            rows.append(prepare_pose_inputs(rgb, depth_m, K, box[None], self.spec, np.random.default_rng(key)))
        if not rows:
            return prepare_pose_inputs(rgb, depth_m, K, np.zeros((0, 4)), self.spec, np.random.default_rng(0))
        fields = [f.name for f in dataclasses.fields(PoseBatch)]
        return PoseBatch(*(np.concatenate([getattr(r, f) for r in rows]) for f in fields))

    def _estimate_from_detections(self, rgb, depth_m, K, det: Detections, timings: dict[str, float],
                                  t0: float) -> FrameResult:
        o = self.options
        hw = depth_m.shape
        for s in STAGES:
            timings.setdefault(s, 0.0)
        order = np.argsort(-det.scores, kind="stable")[:o.max_pallets]
        det = det.take(order)
        if len(det) == 0:
            timings["total"] = _ms(t0)
            return FrameResult.empty(hw, timings)

        t = time.perf_counter()
        batch = self._pose_inputs(rgb, depth_m, K, det.boxes_xyxy)
        timings["pose_inputs"] = _ms(t)
        rejected: list[tuple[int, Rejection]] = []
        go = []
        for i in range(len(det)):
            if not batch.box_in_image[i]:
                rejected.append((i, Rejection(det.boxes_xyxy[i], det.scores[i], "box_outside_image",
                                              "the box does not overlap the image")))
            elif batch.n_valid[i] < o.min_valid_points:
                rejected.append((i, Rejection(det.boxes_xyxy[i], det.scores[i], "too_few_points",
                                              f"{int(batch.n_valid[i])} valid depth pixels in the box, "
                                              f"need {o.min_valid_points}", int(batch.n_valid[i]))))
            else:
                go.append(i)
        accepted: list[tuple[int, PalletPose]] = []
        if go:
            sub = batch.take(np.asarray(go))
            f, q = self.bundle.fusion, self.bundle.pose
            outs = []
            for c in range(0, len(go), GRAPH_BATCH):   # see GRAPH_BATCH: bounds the graphs' memory
                part = slice(c, c + GRAPH_BATCH)
                t = time.perf_counter()
                feat = self.fusion.run({f.rgb_input: sub.rgb_crops[part], f.depth_input: sub.depth_crops[part]},
                                       [f.output_name])[f.output_name]
                timings["fusion"] += _ms(t)
                t = time.perf_counter()
                emb = gather_features(feat, sub.choose[part])
                outs.append(self.pose.run({q.points_input: sub.points[part], q.features_input: emb}))
                timings["pose"] += _ms(t)
            t = time.perf_counter()
            quat, trans, conf_pts = (np.concatenate([o[k] for o in outs])
                                     for k in (q.quat_output, q.trans_output, q.conf_output))
            T, conf, _ = select_poses(quat, trans, conf_pts, sub.points, sub.centres, "wxyz")
            timings["selection"] = _ms(t)
            t = time.perf_counter()
            T_net = T.copy()
            fits: list[FitScore | None] = [None] * len(go)
            if self.refines:
                for k, i in enumerate(go):
                    box_obs = box_points(depth_m, K, det.boxes_xyxy[i], o.refine_points, self.spec.depth_range_m)
                    obs = sub.points[k].astype(np.float64) + sub.centres[k]
                    T[k], fits[k] = self._refine(T_net[k], obs, box_obs, depth_m, K)
            timings["refine"] = _ms(t)
            t = time.perf_counter()
            for k, i in enumerate(go):
                fit = fits[k]
                if fit is None:
                    obs = sub.points[k].astype(np.float64) + sub.centres[k]
                    fit = fit_score(T[k], obs, self.model_points_m, depth_m, K, o.fit_tol_m)
                pose = PalletPose(T[k], conf[k], det.scores[i], det.boxes_xyxy[i], int(sub.n_valid[k]), fit,
                                  self._class_name(int(det.class_ids[i])))
                if conf[k] < o.min_confidence:
                    rejected.append((i, Rejection(det.boxes_xyxy[i], det.scores[i], "low_confidence",
                                                  f"confidence {conf[k]:.3f} < {o.min_confidence}",
                                                  pose.n_valid_points, pose)))
                elif fit.score < o.min_fit:
                    rejected.append((i, Rejection(det.boxes_xyxy[i], det.scores[i], "poor_fit",
                                                  f"fit {fit.score:.3f} < {o.min_fit} (inliers "
                                                  f"{fit.inlier_fraction:.2f}, free-space violation "
                                                  f"{fit.free_space_violation:.2f})", pose.n_valid_points, pose)))
                else:
                    accepted.append((i, pose))
            timings["fit"] = _ms(t)
        timings["total"] = _ms(t0)
        return FrameResult(poses=[p for _, p in sorted(accepted, key=lambda x: x[0])],
                           rejected=[r for _, r in sorted(rejected, key=lambda x: x[0])],
                           timings_ms=timings, image_hw=hw)

    def _refine(self, T_net: np.ndarray, obs_cam: np.ndarray, box_obs_cam: np.ndarray, depth_m: np.ndarray,
                K: np.ndarray) -> tuple[np.ndarray, FitScore | None]:
        """One detection's pose after refinement, and its fit score when already computed (else None).

        :param T_net: (4, 4) the network's pose. :param obs_cam: (n, 3) the sampled points of the detection
        (the fit score's), camera frame. :param box_obs_cam: (m, 3) the box's depth points for ICP.
        """
        o = self.options
        T, fit = T_net, None
        res = refine_pose(T_net, box_obs_cam, self.model_boxes_m, iterations=o.refine_iterations)
        # noisy depth pulls ICP off: its residual tells whether the depth is clean enough to trust it, and
        # then it must explain the depth at least as well as the network's pose
        if np.isfinite(res.rms_m) and res.rms_m < o.refine_max_rms_m:
            fit_icp = fit_score(res.T_cam_pallet, obs_cam, self.model_points_m, depth_m, K, o.fit_tol_m)
            fit_net = fit_score(T_net, obs_cam, self.model_points_m, depth_m, K, o.fit_tol_m)
            keep_icp = fit_icp.score >= fit_net.score + o.refine_margin
            T, fit = (res.T_cam_pallet, fit_icp) if keep_icp else (T_net, fit_net)
        if o.refine_starts > 0:
            # the network's larger errors lie outside ICP's basin: ICP from starts around the pose, and a
            # trusted landing that explains the depth better at a tight tolerance replaces it
            T_best, j = best_landing(T, box_obs_cam, self.model_boxes_m, o.refine_starts, o.refine_start_points,
                                     lambda T_: fit_score(T_, box_obs_cam, self.model_points_m, depth_m, K,
                                                          o.refine_select_tol_m, self.model_boxes_m).score,
                                     o.refine_start_max_rms_m, o.refine_iterations)
            if j >= 0:
                T, fit = T_best, None
        return T, fit


def _ms(t: float) -> float:
    return (time.perf_counter() - t) * 1000.0
