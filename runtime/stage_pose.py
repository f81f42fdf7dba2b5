"""Pose network stage: boxes -> sampled points, fusion.onnx + pose.onnx, the most confident hypothesis.

Per box: crop and encode, select the depth pixels and sample N of them (`pose_inputs.prepare_pose_inputs`,
shared with training), then the fusion and pose graphs on all boxes (in chunks of `graph_batch`), then the most
confident per-point hypothesis (`selection.select_poses`, or the graph's own choice: `selection.chosen_poses`).

With two or more chunks and `lanes` > 1, the chunks run side by side, `lanes` at a time, each on a one-thread copy
of the two graphs: graphs this small hardly use a second intra-op thread (one pallet, int8: 10 ms on 2 threads,
14 ms on 1), so two pallets on one core each finish sooner than two pallets one after the other on both (four
pallets, int8, 2 cores: 42 -> 29 ms; `docs/experiments/latency.md`, "Pallets side by side"). A single chunk keeps
the graphs' `threads`-thread copy. The one-thread copy is made on the first frame that needs it; with it and each
lane's activations the peak resident memory grows by about 60 MB (int8), which is why the estimator's default is
one lane. onnxruntime runs one session from several threads at once, and releases the GIL while it runs.

Point sampling is seeded per box from `seed` and the clamped box, so a pallet's points depend only on the
frame and its box: the same frame gives the same poses, and a pallet gets the same pose whether it is
estimated alone or with others.
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .candidates import Candidates
from .deadline import Deadline, elapsed_ms
from .geometry import clamp_box
from .pose_inputs import PoseBatch, PoseInputSpec, gather_features, prepare_pose_inputs
from .selection import chosen_poses, select_poses
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
    :param lanes: chunks run side by side, each on one thread (1: one after the other on `threads` threads).
    """

    def __init__(self, bundle, precision: str, threads: int, spec: PoseInputSpec, seed: int,
                 min_valid_points: int, lanes: int = 1) -> None:
        if int(lanes) < 1:
            raise ValueError(f"lanes must be >= 1, got {lanes}")
        f, q = bundle.fusion, bundle.pose
        self.fusion_spec, self.pose_spec, self.spec = f, q, spec
        # a fusion graph that samples its features itself takes the chosen pixels as a third input
        self.choose_input = f.choose_input
        self._graphs = (bundle.graph("fusion", precision), bundle.graph("pose", precision))
        self.fusion, self.pose = self._open(threads)
        self.seed = int(seed)
        self.min_valid_points = int(min_valid_points)
        self.graph_batch = GRAPH_BATCH
        self.lanes = int(lanes)
        self._lane_graphs: tuple[OnnxModel, OnnxModel] | None = None
        self._pool: ThreadPoolExecutor | None = None

    def _open(self, threads: int) -> tuple[OnnxModel, OnnxModel]:
        """The fusion and pose graphs as sessions of `threads` intra-op threads."""
        f, q = self.fusion_spec, self.pose_spec
        fusion_inputs = (f.rgb_input, f.depth_input) + ((self.choose_input,) if self.choose_input else ())
        return (OnnxModel(self._graphs[0], threads, fusion_inputs, (f.output_name,)),
                OnnxModel(self._graphs[1], threads, (q.points_input, q.features_input),
                          (q.quat_output, q.trans_output, q.conf_output)))

    def close(self) -> None:
        """Stop the lanes' worker threads (the stage still runs afterwards, starting them again if needed)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

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
        """Both graphs on the rows of `batch`, `graph_batch` rows at a time, taken in order (side by side in
        `lanes` when there are several chunks); once `deadline` has expired no further chunk is taken, so the
        rows run are always the first b.

        :return: the pose graph's outputs for the first b rows of `batch` (b = len(batch) unless the deadline
            stopped it): per-point quaternions (b, N, 4), translation offsets (b, N, 3), confidences (b, N); or, from
            a graph that picks the most confident hypothesis (`PoseSpec.hypotheses`), (b, 4), (b, 3), (b,).
        """
        q = self.pose_spec
        timings = {} if timings is None else timings
        chunks = [slice(c, c + self.graph_batch) for c in range(0, len(batch), self.graph_batch)]
        if self.lanes > 1 and len(chunks) > 1:
            outs = self._run_lanes(batch, chunks, timings, deadline)
        else:
            outs = []
            for part in chunks:   # see GRAPH_BATCH: bounds the graphs' memory
                if deadline is not None and deadline.expired():
                    break
                outs.append(self._run_chunk(self.fusion, self.pose, batch, part, timings))
        if not outs:
            per_point = (batch.points.shape[1],) if q.hypotheses == "per_point" else ()
            return tuple(np.zeros((0, *per_point, *k), np.float32) for k in ((4,), (3,), ()))
        return tuple(np.concatenate([o[k] for o in outs]) for k in (q.quat_output, q.trans_output, q.conf_output))

    def _run_chunk(self, fusion: OnnxModel, pose: OnnxModel, batch: PoseBatch, part: slice,
                   timings: dict[str, float]) -> dict[str, np.ndarray]:
        """The fusion then the pose graph on rows `part`; adds their times to `timings`."""
        f, q = self.fusion_spec, self.pose_spec
        t = time.perf_counter()
        feeds = {f.rgb_input: batch.rgb_crops[part], f.depth_input: batch.depth_crops[part]}
        if self.choose_input:
            feeds[self.choose_input] = batch.choose[part]
        feat = fusion.run(feeds, [f.output_name])[f.output_name]
        t_pose = time.perf_counter()
        if self.choose_input:   # the graph's output is already per point (B, N, C)
            emb = np.ascontiguousarray(feat, np.float32)
        else:
            emb = gather_features(feat, batch.choose[part])
        out = pose.run({q.points_input: batch.points[part], q.features_input: emb})
        timings["fusion"] = timings.get("fusion", 0.0) + (t_pose - t) * 1000.0
        timings["pose"] = timings.get("pose", 0.0) + elapsed_ms(t_pose)
        return out

    def _run_lanes(self, batch: PoseBatch, chunks: list[slice], timings: dict[str, float],
                   deadline: Deadline | None) -> list[dict[str, np.ndarray]]:
        """`chunks` on `lanes` worker threads sharing one one-thread copy of the graphs; each worker takes the next
        chunk until none is left or the deadline has expired. Timings: the section's wall time, split between
        fusion and pose in proportion to their summed times."""
        if self._lane_graphs is None:
            self._lane_graphs = self._open(1)
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.lanes, thread_name_prefix="pallet6d-lane")
        fusion, pose = self._lane_graphs
        results: list[dict[str, np.ndarray] | None] = [None] * len(chunks)
        taken = iter(range(len(chunks)))
        lock = threading.Lock()
        lane_times: list[dict[str, float]] = [{} for _ in range(self.lanes)]

        def work(lane: int) -> None:
            while True:
                with lock:   # chunks are taken in order, so the chunks run are always the first ones
                    if deadline is not None and deadline.expired():
                        return
                    k = next(taken, None)
                if k is None:
                    return
                results[k] = self._run_chunk(fusion, pose, batch, chunks[k], lane_times[lane])

        t = time.perf_counter()
        for job in [self._pool.submit(work, lane) for lane in range(self.lanes)]:
            job.result()   # re-raises a lane's error here
        wall = elapsed_ms(t)
        spent = {s: sum(lt.get(s, 0.0) for lt in lane_times) for s in ("fusion", "pose")}
        total = spent["fusion"] + spent["pose"]
        for s in ("fusion", "pose"):
            timings[s] = timings.get(s, 0.0) + (wall * spent[s] / total if total > 0 else 0.0)
        return [r for r in results if r is not None]

    def postprocess(self, quat: np.ndarray, trans: np.ndarray, conf: np.ndarray,
                    batch: PoseBatch) -> tuple[np.ndarray, np.ndarray]:
        """The most confident hypothesis of each of the b rows: T_cam_pallet (b, 4, 4), confidence (b,)."""
        b = len(quat)
        if self.pose_spec.hypotheses == "most_confident":
            return chosen_poses(quat, trans, conf, batch.centres[:b])
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
