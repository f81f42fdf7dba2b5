"""Fit check stage: does each posed pallet agree with the depth image (`fit.py`) and show a pallet's structure
there (`structure.py`)? Then the acceptance gates."""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from .candidates import Candidates
from .deadline import elapsed_ms
from .fit import fit_score
from .registration import RegistrationScore
from .stage_geometry import PalletGeometry
from .stage_refine import fit_array
from .structure import StructureParams, frame_registration, frame_size_rule, registration_verdict, structure_check
from .weak_boxes import WeakBoxes, weak_box_failures

__all__ = ["FitCheckStage", "StartedRegistration"]

# the registration test started on a frame's boxes: (the boxes (n, 4), its future (score, refused))
StartedRegistration = tuple[np.ndarray, "Future[tuple[RegistrationScore, bool]]"]


class FitCheckStage:
    """Fit scores of the candidates' poses against the depth, with each candidate's own pallet model.

    :param geometries: the pallet types (a candidate's `type_index` points into them).
    :param tol_m: distance tolerance of the fit score, metres.
    :param min_fit: a pose whose fit score is below this is rejected ("poor_fit").
    :param min_confidence: a pose whose network confidence is below this is rejected ("low_confidence").
    :param structure: thresholds of the structure check, or None to skip it; a pose that fails it is rejected
        with the check's own reason where the inputs do not belong together ("size_mismatch": the detector's box
        has the wrong metric size at the depth; "depth_image_mismatch": the depth's edges are not the image's),
        else "no_pallet_structure". Types without boxes are not structure-checked. Two tests judge the whole frame:
        the registration test (`min_registration_peak`: the frame's depth edges against the image's, at zero shift
        and shifted) rejects every candidate as "depth_image_mismatch"; candidates failing the metric size reject
        every candidate as "size_mismatch" when they are at least as many as the whole boxes that pass every test
        in a frame without a vehicle calibration (`frame_size_vouched`), outnumber the whole boxes that pass the
        size test (`frame_size_majority`) or reach `frame_size_veto`. The registration test needs only the depth,
        the image and the boxes, so `start_registration` runs it on a worker thread while the networks run
        (`close` stops that thread).
    :param weak: what a weak detection's pose must show besides (`weak_boxes.py`); the rows the caller marks weak
        are rejected ("no_pallet_structure") where it is not shown, or where no structure check can judge them.
    """

    def __init__(self, geometries: tuple[PalletGeometry, ...], tol_m: float, min_fit: float,
                 min_confidence: float, structure: StructureParams | None = StructureParams(),
                 weak: WeakBoxes = WeakBoxes()) -> None:
        self.geometries = tuple(geometries)
        self.tol_m, self.min_fit, self.min_confidence = float(tol_m), float(min_fit), float(min_confidence)
        self.structure = structure
        self.weak = weak
        self._pool: ThreadPoolExecutor | None = None

    def close(self) -> None:
        """Stop the registration test's worker thread (the stage still works afterwards)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def start_registration(self, boxes_xyxy: np.ndarray, depth_m: np.ndarray,
                           rgb: np.ndarray | None) -> StartedRegistration | None:
        """Start the frame-level registration test on `boxes_xyxy` (n, 4) on the worker thread, for the structure
        check to take (`__call__(..., registration=)`) if the candidates it judges are exactly these boxes;
        otherwise it runs the test again on its own. The caller must wait for it before `depth_m` or `rgb` change.
        :return: None where the test would not run (no structure check, no image, test off, no boxes)."""
        p = self.structure
        if p is None or rgb is None or p.min_registration_peak <= 0 or len(boxes_xyxy) == 0:
            return None
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="pallet6d-registration")
        boxes = np.array(boxes_xyxy, dtype=np.float64, copy=True)
        return boxes, self._pool.submit(frame_registration, depth_m, rgb, boxes, p)

    def check_structure(self, cands: Candidates, rows: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                        rgb: np.ndarray | None = None, up_cam: np.ndarray | None = None,
                        registration: StartedRegistration | None = None, weak: np.ndarray | None = None,
                        from_depth: np.ndarray | None = None) -> None:
        """The structure check on `rows` of `cands`: first the frame-level registration test over the detector's
        boxes among them, then one batched call per pallet type, then the frame's size rules (`frame_size_rule`);
        failures are rejected.
        :param rgb: the colour image registered to `depth_m`, for the edge and registration tests (None skips
            them). :param up_cam: (3,) the vehicle's up in the camera frame, for the tilt test (None skips it).
        :param registration: the test started on the frame's boxes (`start_registration`), used when those are
            the boxes it tests. :param weak: (n,) bool over all rows of `cands`: weak detections (`weak_boxes.py`),
            or None. :param from_depth: (n,) bool: rows whose box the depth proposed (`depth_proposals.py`), or None;
            the registration test leaves them out (a box drawn from the depth says nothing of where the image's
            edges lie), and its refusal refuses them too, except where it found the depth flat around the others'
            boxes: a proposal stands where the depth is not."""
        p = self.structure
        weak = np.zeros(len(cands), bool) if weak is None else weak
        tested = rows if from_depth is None else rows[~from_depth[rows]]
        if rgb is not None and p.min_registration_peak > 0 and len(tested):
            boxes = cands.boxes_xyxy[tested]
            if registration is not None and np.array_equal(registration[0], boxes):
                reg, refused = registration[1].result()
            else:
                reg, refused = frame_registration(depth_m, rgb, boxes, p)
            if refused:
                # only flat around the detections' boxes: those are refused, the depth's proposals judged on
                verdict = registration_verdict(reg, p)
                every = verdict == "mismatch"
                cands.reject(rows if every else tested, "depth_image_mismatch", _registration_detail(reg, p, verdict))
                rows = rows[:0] if every else np.setdiff1d(rows, tested)
                if not len(rows):
                    return
        unjudged = np.array([i for i in rows if weak[i] and self.geometries[int(cands.type_index[i])].boxes_m is None],
                            dtype=np.int64)
        cands.reject(unjudged, "no_pallet_structure",
                     [self._weak_detail(cands, i, "its type has no boards to judge") for i in unjudged])
        scores_all = []
        for j, geom in enumerate(self.geometries):
            mine = rows[cands.type_index[rows] == j]
            if len(mine) == 0 or geom.boxes_m is None:
                continue
            scores = structure_check(cands.T_cam_pallet[mine], geom.boxes_m, depth_m, K, cands.boxes_xyxy[mine],
                                     self.structure, up_cam=up_cam, rgb=rgb)
            scores_all += scores
            for reason in ("size_mismatch", "depth_image_mismatch", "no_pallet_structure"):
                bad = [k for k, sc in enumerate(scores) if not sc.ok and _rejection_reason(sc.reason) == reason]
                cands.reject(mine[bad], reason, [_structure_detail(scores[k]) for k in bad])
            judged = [k for k, sc in enumerate(scores) if sc.ok and weak[mine[k]]]
            why = weak_box_failures([scores[k].agreement for k in judged], [scores[k].open_fraction for k in judged],
                                    self.weak, [scores[k].box_cut for k in judged])
            short = [(mine[k], w) for k, w in zip(judged, why) if w]
            cands.reject(np.array([i for i, _ in short], dtype=np.int64), "no_pallet_structure",
                         [self._weak_detail(cands, i, w) for i, w in short])
        rule = frame_size_rule(scores_all, p, calibrated=up_cam is not None)
        if rule:
            n_size = sum(sc.reason == "size_mismatch" for sc in scores_all)
            cands.reject(rows[cands.alive[rows]], "size_mismatch",
                         f"size_mismatch: {n_size} of the frame's {len(rows)} candidates have no pallet's metric "
                         f"size at the depth ({rule}): depth scale or focal length off?")

    def _weak_detail(self, cands: Candidates, i: int, why: str) -> str:
        score, conf = cands.scores[i], cands.confidence[i]
        if conf < self.min_confidence:
            what = f"a pose of network confidence {conf:.2f}"
        else:
            what = "a depth proposal" if score == 0.0 else f"a weak detection (score {score:.2f})"   # depth_proposals.py
        return f"no_pallet_structure: {what} is kept only with clear structure: {why}"

    def score(self, T_cam_pallet: np.ndarray, obs_cam: np.ndarray, type_index: np.ndarray, depth_m: np.ndarray,
              K: np.ndarray) -> np.ndarray:
        """Fit of n poses. :param T_cam_pallet: (n, 4, 4). :param obs_cam: (n, N, 3) observed points, camera
        frame, metres. :param type_index: (n,). :return: (n, 3) inlier fraction, free-space violation, score."""
        out = np.zeros((len(T_cam_pallet), 3))
        for k, (T, obs, j) in enumerate(zip(T_cam_pallet, obs_cam, type_index)):
            out[k] = fit_array(fit_score(T, obs, self.geometries[int(j)].points_m, depth_m, K, self.tol_m))
        return out

    def __call__(self, cands: Candidates, depth_m: np.ndarray, K: np.ndarray, timings: dict[str, float],
                 rgb: np.ndarray | None = None, up_cam: np.ndarray | None = None,
                 registration: StartedRegistration | None = None, weak: np.ndarray | None = None,
                 from_depth: np.ndarray | None = None, confidence_floor: np.ndarray | None = None) -> None:
        """The stage on the alive rows of `cands`: the fit where no earlier stage computed it, then the gates.
        :param rgb: the frame's colour image, for the structure check's edge test (None skips that test).
        :param up_cam: the vehicle's up in the camera frame, for the structure check's tilt test (None skips it).
        :param registration, weak, from_depth: see `check_structure`.
        :param confidence_floor: (n,) the network confidence each row needs (the estimator's, which lets a confident
            detection's unsure pose go on as a weak one), or None: `min_confidence` for every row."""
        t = time.perf_counter()
        rows = np.flatnonzero(cands.alive)
        todo = rows[np.isnan(cands.fit[rows, 2])]
        cands.assign(todo, fit=self.score(cands.T_cam_pallet[todo], cands.points_cam[todo], cands.type_index[todo],
                                          depth_m, K))
        conf, fit = cands.confidence[rows], cands.fit[rows]
        floor = np.full(len(rows), self.min_confidence) if confidence_floor is None else confidence_floor[rows]
        low = conf < floor
        poor = ~low & (fit[:, 2] < self.min_fit)
        cands.reject(rows[low], "low_confidence", [f"confidence {c:.3f} < {f}" for c, f in zip(conf[low], floor[low])])
        cands.reject(rows[poor], "poor_fit", [f"fit {s:.3f} < {self.min_fit} (inliers {i:.2f}, free-space violation "
                                              f"{v:.2f})" for i, v, s in fit[poor]])
        rest = rows[~low & ~poor]
        if self.structure is not None:
            self.check_structure(cands, rest, depth_m, K, rgb, up_cam, registration, weak, from_depth)
        elif weak is not None:
            unjudged = rest[weak[rest]]
            cands.reject(unjudged, "no_pallet_structure",
                         [self._weak_detail(cands, i, "the structure check is off") for i in unjudged])
        timings["fit"] = elapsed_ms(t)


def _rejection_reason(structure_reason: str) -> str:
    """The candidates' rejection reason of a failed structure test: the tests that say the inputs do not belong
    together keep their own, the others are "no_pallet_structure"."""
    return structure_reason if structure_reason in ("size_mismatch", "depth_image_mismatch") else "no_pallet_structure"


def _registration_detail(reg, p: StructureParams, verdict: str) -> str:
    """Why the registration test refused the frame (`registration_verdict`'s `verdict`)."""
    if verdict == "flat":
        pairs = reg.jump_pairs + reg.other_pairs
        return (f"depth_image_mismatch: the frame's depth is flat around its candidates ({reg.jump_pairs} of {pairs} "
                f"pixel pairs step, fewer than {100 * p.registration_min_jump_fraction:g} %) where the image shows "
                f"{reg.colour_edge_pairs} edges: a wall's depth or one stuck at one value, or not this image's?")
    need = f"{p.min_registration_peak:g}" if reg.peak < p.min_registration_peak else \
        f"{2.0 * p.min_registration_peak:g}, twice the threshold at an AUC below {p.registration_weak_edge_auc:g}"
    return (f"depth_image_mismatch: the frame's depth edges agree with the image's at AUC {reg.auc_0:.2f}, and "
            f"almost as well with the depth shifted {p.registration_shift_px} px (AUC {reg.auc_shifted:.2f}, peak "
            f"{reg.peak:.3f} < {need}): depth of another frame, or not registered to the colour image?")


def _structure_detail(s) -> str:
    if s.reason == "size_mismatch":
        whole = "" if s.box_cut or np.isnan(s.whole_height_m) else \
            f", {s.whole_height_m:.3f} m tall at the pallet's depth (not cut by the image's edge)"
        return (f"size_mismatch: the detector's box spans {s.box_size_m[0]:.2f} x {s.box_size_m[1]:.2f} m at the depth "
                f"inside it{whole}, not a pallet of this type (depth scale or focal length off?)")
    if s.reason == "see_through_cut":
        return (f"see_through_cut: the image's edge cuts the box, and {s.see_through} of the {s.solid + s.see_through} "
                "rays that meet the posed pallet's boards see through them (no pallet there, or focal length off?)")
    if s.reason == "see_through_beyond_box":
        return (f"see_through_beyond_box: {s.see_through_beyond} of the {s.solid + s.see_through} rays that meet the "
                "posed pallet's boards see through them outside the detector's box, which the image's edge does not "
                "cut (the pose is larger than the pallet seen: focal length off?)")
    if s.reason == "depth_image_mismatch":
        return (f"depth_image_mismatch: depth edges agree with the image's at AUC {s.edge_auc:.2f} (0.5 = chance; "
                "depth of another frame, or not registered to the colour image?)")
    return (f"{s.reason}: agreement {s.agreement:.2f}, openings open {s.open_fraction:.2f} ({s.open + s.closed} rays), "
            f"most open pocket {s.pocket_open:.2f}, box cover {s.box_cover:.2f}, box solid {s.box_solid:.2f}, "
            f"seen IoU {s.seen_iou:.2f}")
