"""Pose network stage: boxes -> sampled points, fusion.onnx + pose.onnx, the most confident hypothesis.

Per box: crop and encode, select the depth pixels and sample N of them (`pose_inputs.prepare_pose_inputs`,
shared with training), then the fusion and pose graphs on all boxes at once (in chunks of `graph_batch`),
then the most confident per-point hypothesis (`selection.select_poses`).

Point sampling is seeded per box from `seed` and the clamped box, so a pallet's points depend only on the
frame and its box: the same frame gives the same poses, and a pallet gets the same pose whether it is
estimated alone or with others.
"""
from __future__ import annotations

import time

import numpy as np

from .candidates import Candidates
from .deadline import Deadline, elapsed_ms
from .geometry import clamp_box
from .pose_inputs import PoseBatch, PoseInputSpec, gather_features, prepare_pose_inputs
from .selection import select_poses
from .sessions import OnnxModel

__all__ = ["GRAPH_BATCH", "PoseNetworkStage"]

# The fusion and pose graphs run on at most this many pallets at once. The fusion graph's activations for one
# 96x96 crop take about 16 MB, and the peak resident memory grows by that much per pallet of a batch, while
# larger batches save little time on two cores (about 2 ms per pallet at int8, 4 pallets: fusion + pose 43 ms in one
# batch, 51 ms one by one; docs/experiments/latency.md, "Memory").
GRAPH_BATCH = 1


class PoseNetworkStage:
    """The bundle's fusion and pose graphs with their pre- and post-processing.

    :param bundle: a loaded `Bundle`. :param precision: "fp32" or "int8". :param threads: onnxruntime threads.
    :param spec: the preprocessing (`Bundle.pose_input_spec()`, depth range possibly overridden).
    :param seed: seed of the per-box point sampling.
    :param min_valid_points: a box with fewer valid depth pixels is rejected ("too_few_points").
    """

    def __init__(self, bundle, precision: str, threads: int, spec: PoseInputSpec, seed: int,
                 min_valid_points: int) -> None:
        f, q = bundle.fusion, bundle.pose
        self.fusion_spec, self.pose_spec, self.spec = f, q, spec
        # a fusion graph that samples its features itself takes the chosen pixels as a third input
        self.choose_input = f.choose_input
        fusion_inputs = (f.rgb_input, f.depth_input) + ((self.choose_input,) if self.choose_input else ())
        self.fusion = OnnxModel(bundle.graph("fusion", precision), threads, fusion_inputs, (f.output_name,))
        self.pose = OnnxModel(bundle.graph("pose", precision), threads, (q.points_input, q.features_input),
                              (q.quat_output, q.trans_output, q.conf_output))
        self.seed = int(seed)
        self.min_valid_points = int(min_valid_points)
        self.graph_batch = GRAPH_BATCH

    def preprocess(self, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                   boxes_xyxy: np.ndarray) -> tuple[PoseBatch, list[tuple[np.ndarray, np.ndarray]]]:
        """Network inputs for (B, 4) boxes, and each box's candidate depth pixels (v, u) (`prepare_pose_inputs`),
        each box sampled with its own generator seeded by (seed, clamped box)."""
        rngs = []
        for box in np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4):
            box_i = clamp_box(box, depth_m.shape)
            rngs.append(np.random.default_rng([self.seed] + ([] if box_i is None else [int(c) for c in box_i])))
        return prepare_pose_inputs(rgb, depth_m, K, boxes_xyxy, self.spec, rngs, return_pixels=True)

    def infer(self, batch: PoseBatch, timings: dict[str, float] | None = None,
              deadline: Deadline | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Both graphs on the rows of `batch`, `graph_batch` rows at a time, in order; once `deadline` has
        expired the remaining chunks are not run.

        :return: per-point quaternions (b, N, 4), translation offsets (b, N, 3), confidences (b, N) for the
            first b rows of `batch` (b = len(batch) unless the deadline stopped it).
        """
        f, q = self.fusion_spec, self.pose_spec
        timings = {} if timings is None else timings
        outs = []
        for c in range(0, len(batch), self.graph_batch):   # see GRAPH_BATCH: bounds the graphs' memory
            if deadline is not None and deadline.expired():
                break
            part = slice(c, c + self.graph_batch)
            t = time.perf_counter()
            feeds = {f.rgb_input: batch.rgb_crops[part], f.depth_input: batch.depth_crops[part]}
            if self.choose_input:
                feeds[self.choose_input] = batch.choose[part]
            feat = self.fusion.run(feeds, [f.output_name])[f.output_name]
            timings["fusion"] = timings.get("fusion", 0.0) + elapsed_ms(t)
            t = time.perf_counter()
            if self.choose_input:   # the graph's output is already per point (B, N, C)
                emb = np.ascontiguousarray(feat, np.float32)
            else:
                emb = gather_features(feat, batch.choose[part])
            outs.append(self.pose.run({q.points_input: batch.points[part], q.features_input: emb}))
            timings["pose"] = timings.get("pose", 0.0) + elapsed_ms(t)
        if not outs:
            n = batch.points.shape[1]
            return np.zeros((0, n, 4), np.float32), np.zeros((0, n, 3), np.float32), np.zeros((0, n), np.float32)
        return tuple(np.concatenate([o[k] for o in outs]) for k in (q.quat_output, q.trans_output, q.conf_output))

    @staticmethod
    def postprocess(quat: np.ndarray, trans: np.ndarray, conf: np.ndarray,
                    batch: PoseBatch) -> tuple[np.ndarray, np.ndarray]:
        """The most confident hypothesis of each of the b rows: T_cam_pallet (b, 4, 4), confidence (b,)."""
        b = len(quat)
        T, confidence, _ = select_poses(quat, trans, conf, batch.points[:b], batch.centres[:b], "wxyz")
        return T, confidence

    def __call__(self, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, cands: Candidates,
                 timings: dict[str, float], deadline: Deadline | None = None) -> None:
        """The stage on the alive rows of `cands`: fills `n_valid`, `points_cam`, `pixels`, `T_net`,
        `T_cam_pallet`, `confidence`; rejects rows outside the image, with too few depth pixels, or left
        over when the deadline expired."""
        rows = np.flatnonzero(cands.alive)
        if deadline is not None and deadline.expired():
            cands.reject(rows, "time_budget", "the frame's time budget was spent before the pose network")
            return
        t = time.perf_counter()
        batch, pixels = self.preprocess(rgb, depth_m, K, cands.boxes_xyxy[rows])
        cands.assign(rows, n_valid=batch.n_valid, pixels=pixels,
                     points_cam=batch.points.astype(np.float64) + batch.centres[:, None])
        timings["pose_inputs"] = elapsed_ms(t)
        cands.reject(rows[~batch.box_in_image], "box_outside_image", "the box does not overlap the image")
        few = batch.box_in_image & (batch.n_valid < self.min_valid_points)
        cands.reject(rows[few], "too_few_points", [f"{int(n)} valid depth pixels in the box, need "
                                                   f"{self.min_valid_points}" for n in batch.n_valid[few]])
        go = np.flatnonzero(cands.alive[rows])
        if len(go) == 0:
            return
        sub = batch.take(go)
        quat, trans, conf = self.infer(sub, timings, deadline)
        t = time.perf_counter()
        T, confidence = self.postprocess(quat, trans, conf, sub)
        done, skipped = rows[go[:len(T)]], rows[go[len(T):]]
        cands.assign(done, T_net=T, T_cam_pallet=T, confidence=confidence)
        cands.reject(skipped, "time_budget", "the frame's time budget was spent before the pose network ran on it")
        timings["selection"] = elapsed_ms(t)
