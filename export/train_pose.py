"""Pose-stage training (paper 3.1.1-3.1.5): fusion + pose networks end to end with the eq. 4 loss.

Inputs come from `train_data.build_pose_samples` (the runtime's `prepare_pose_inputs` on jittered ground-truth
boxes, mask-free point selection), so the crops, depth encoding, sampled points and feature indices are those
the runtime computes. The loss compares each per-point pose with the ground truth in the centred camera frame,
over the pallet's symmetries (`losses.pose_loss`). Every ground-truth pallet's type comes from its BOP `obj_id`
(the sim writes one obj_id and model per type), so a batch may mix types: each sample's loss uses its own
type's model points and symmetries (padded per batch). Validation measures what the runtime will report: the
symmetry-aware ADD of the most confident per-point hypothesis.

A fusion network with `sample_stride` samples its features at `choose` inside the graph; the dense one's
map is gathered at `choose` here, as the runtime does.

With a teacher (`distill`: a bundle or checkpoint whose fusion network takes the same crops), its per-point fused
features are a second target: the loss adds `distill_weight` times the mean squared difference of the two
networks' features, divided by the variance of the teacher's (so 1 means "no better than their mean"). A
smaller fusion network (`edge2-slim`) then learns to give the pose network what it was trained on.

With `negatives` (`negative_crops`: what a detector boxes in pallet-free scenes), each step also takes a few of
those crops: the teacher's features are matched there (so that a student does not drift where no pallet is), and,
with a weight for it, the pose network's confidence is taught to be low there (the runtime refuses a pose whose
confidence is under `min_confidence`). `trainable="conf"` trains the confidence head alone, every pose unchanged;
with `conf_teacher` (the starting pose network, frozen) the pallets' confidences are pulled toward that network's
own instead of DenseFusion's confidence term, so that only the negatives move: refitted to that term alone, the
head gives modest pallets confidences near `w / error`, under the runtime's floor. `trainable="verifier"` trains a
network's verifier head alone (`PoseConfig.verifier`): at the pallets' points it follows the confidence head (binary
cross-entropy), at the negatives' chosen points (the confidence head's best, as the graph reads it) it learns to be
low (or, with `verifier_target="pallet"`, at the pallets' chosen points it learns to be 1: pallet or not, whatever the
pose's error); the confidence head keeps choosing, so every pose stays as it was. After training, its output is
shifted by one constant in logit space (`calibrate_verifier`) so that the runtime's floor keeps as many validation
pallets as the confidence head kept: the floor then refuses only what the verifier ranks below those pallets.
`trainable="pose"` trains the pose network alone on the fixed fusion network's features: a sample's crops and
points are fixed when it is prepared, so its features are computed once (`PoseTrainer.cached_features`) and a step
costs the pose network's forward and backward passes only (on two CPU cores a third of a step of both or less).
Training that moves the confidence head's level (the eq. 4 loss lowers it as the poses get better) can end the same
way for the confidence head (`calibrate_floor` to a chosen share of validation pallets), since the floor was chosen
for a network whose confidences sit where the shipped one's do.
"""
from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from pallet6d.runtime.bop import BopDataset
from pallet6d.runtime.estimator import EstimatorOptions

from .calib_data import pose_input_spec
from .config import ModelConfig, get_config
from .fusion import build_fusion
from .negative_crops import NegativeCrops, load_mismatched_crops, load_negative_crops
from .losses import pad_symmetries, pose_loss, stack_model_points
from .pose import build_pose
from .train_data import (AugmentConfig, PoseSamples, build_pose_samples, load_or_build, model_points_for,
                         pallet_type_name, repeat_train, repeated_roots)
from .train_loop import (BEST, LAST, LoopSettings, autocast, conv_input, conv_layout, load_checkpoint,
                         load_init_weights, save_checkpoint, train_epochs)
from .warm_start import init_config, warm_start

__all__ = ["PoseData", "load_pose_data", "PoseTrainer", "calibrate_floor", "calibrate_verifier", "gather_points",
           "subsample_points", "train_pose"]

log = logging.getLogger(__name__)

MODEL_POINTS = 500   # DenseFusion's num_pt_mesh_small: points of the model in the loss
TRAINABLE = ("all", "fusion", "pose", "conf", "verifier")
FIXED_FUSION = ("pose", "conf", "verifier")   # trainables under which the fusion network runs fixed, in inference mode
CACHE_BATCH = 64    # samples per fusion pass when the fixed fusion network's features are computed once
VERIFIER_TARGETS = ("confidence", "pallet")
CONF_FLOOR = EstimatorOptions().min_confidence   # validation reports the share of best confidences above it


@dataclass
class PoseData:
    """Samples of several datasets, with a train/val split by frame and the models' points/symmetries.

    :ivar model_points: obj_id -> (M, 3) float32 metres. :ivar symmetries: obj_id -> (S, 4, 4).
    :ivar type_names: obj_id -> pallet type name (`sim.pallets` name; the exporter writes these types).
    """

    samples: PoseSamples
    train_idx: np.ndarray
    val_idx: np.ndarray
    model_points: dict[int, np.ndarray]
    symmetries: dict[int, np.ndarray]
    fingerprints: list[dict]
    type_names: dict[int, str]


def load_pose_data(cfg: ModelConfig, data: Sequence[str | Path], variants: int, seed: int, aug: AugmentConfig,
                   cache_dir: str | Path | None, val_fraction: float = 0.1, max_frames: int | None = None,
                   progress: bool = True) -> PoseData:
    """Prepare (or read from cache) the pose samples of every dataset and split them by frame.

    Validation uses only variant 0 (the un-jittered view) of its frames; no frame is in both splits. A dataset named
    k times in `data` is prepared and held out from once and trained k times (`train_data.repeated_roots`).
    """
    from tqdm import tqdm

    spec = pose_input_spec(cfg)
    parts, fps, model_points, syms, names = [], [], {}, {}, {}
    frame_offset = 0
    data, repeats = repeated_roots(data)
    for root, k in zip(data, repeats):
        settings = {"spec": repr(spec), "variants": variants, "seed": seed, "aug": aug.to_dict(),
                    "max_frames": max_frames}
        n = len(BopDataset(root))
        with tqdm(total=n if max_frames is None else min(n, max_frames), desc=f"prepare {Path(root).name}",
                  unit="frame", disable=not progress, leave=False) as bar:
            s, fp = load_or_build("pose", root, settings, cache_dir,
                                  lambda: build_pose_samples(root, spec, variants, seed, aug, max_frames=max_frames,
                                                             progress=bar.update))
        # frame ids unique across datasets, for the split
        parts.append(PoseSamples(*(getattr(s, f) if f != "frame" else s.frame + frame_offset
                                   for f in PoseSamples.__dataclass_fields__)))
        frame_offset += fp["frames"]
        fps.append(fp | ({"repeat": int(k)} if k > 1 else {}))
        ds = BopDataset(root)
        for obj in np.unique(s.obj_id):
            name = pallet_type_name(ds, int(obj), cfg.pallet)
            if names.setdefault(int(obj), name) != name:
                raise ValueError(f"{root}: obj_id {int(obj)} is {name!r} here but {names[int(obj)]!r} in another "
                                 "dataset; datasets trained together must number their pallet types alike")
            if int(obj) not in model_points:
                model_points[int(obj)], syms[int(obj)] = model_points_for(ds, int(obj), MODEL_POINTS, cfg.pallet)
    samples = PoseSamples.concat(parts)
    frames = np.unique(samples.frame)
    rng = np.random.default_rng(seed)
    n_val = int(round(val_fraction * len(frames))) if len(frames) > 1 else 0
    val_frames = rng.choice(frames, n_val, replace=False) if n_val else np.zeros(0, np.int64)
    is_val = np.isin(samples.frame, val_frames)
    train_idx = np.flatnonzero(~is_val)
    val_idx = np.flatnonzero(is_val & (samples.variant == 0))
    if len(val_idx) == 0:   # tiny datasets: validate on the clean views of the training frames
        val_idx = np.flatnonzero(samples.variant == 0)
    sample_root = np.repeat(np.arange(len(parts)), [len(p.frame) for p in parts])
    train_idx = repeat_train(train_idx, sample_root, repeats)
    log.info("pose samples: %d train, %d val (%d frames held out)", len(train_idx), len(val_idx), n_val)
    return PoseData(samples, train_idx, val_idx, model_points, syms, fps, names)


def gather_points(features: torch.Tensor, choose: torch.Tensor) -> torch.Tensor:
    """Torch twin of `pose_inputs.gather_features`. :param features: (B, C, h, w). :param choose: (B, N).
    :return: (B, N, C)."""
    b, c = features.shape[:2]
    flat = features.reshape(b, c, -1)
    return torch.gather(flat, 2, choose[:, None, :].expand(-1, c, -1)).transpose(1, 2)


def subsample_points(points: torch.Tensor, choose: torch.Tensor, T_gt: torch.Tensor,
                     n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The first `n` of each sample's points (a uniform random subset: they are sampled in random order),
    re-centred on their mean as the runtime centres the points it samples; the target moves with them.

    :param points: (B, N, 3) centred points. :param choose: (B, N). :param T_gt: (B, 4, 4) in the points' frame.
    :return: points (B, n, 3) with zero mean, choose (B, n), T_gt (B, 4, 4) in the new frame.
    """
    points, choose = points[:, :n], choose[:, :n]
    shift = points.mean(1)
    T_gt = T_gt.clone()
    T_gt[:, :3, 3] -= shift
    return points - shift[:, None], choose, T_gt


class PoseTrainer:
    """Fusion + pose networks, and the loss/metric on a batch of `PoseData` samples."""

    def __init__(self, cfg: ModelConfig, data: PoseData, device: str = "cpu", w: float = 0.015,
                 amp: bool = False, num_points: int | None = None, teacher: torch.nn.Module | None = None,
                 distill_weight: float = 1.0, negatives: NegativeCrops | None = None,
                 negatives_per_step: int = 4, negative_conf_weight: float = 0.0, trainable: str = "all",
                 conf_teacher: torch.nn.Module | None = None, negative_conf_top: float = 1.0,
                 verifier_target: str = "confidence") -> None:
        """:param num_points: use this many of each sample's points (fewer than prepared: the first ones, a
            uniform random subset since the points are sampled in random order), re-centred on their mean.
        :param teacher: a fusion network whose per-point features the trained one should also give (module
            docstring), taking the same inputs; frozen. :param distill_weight: that term's weight in the loss.
        :param negatives: crops without a pallet (`negative_crops`), `negatives_per_step` of them, drawn at random,
            each step: with `teacher`, their feature error is added with `distill_weight`; with
            `negative_conf_weight` > 0, the pose network's confidence there, as `negative_conf_weight` times the mean
            of -log(1 - confidence) over their points (the runtime refuses a pose whose best point's confidence
            is under its `min_confidence`). :param negative_conf_top: that mean over this fraction of each negative
            crop's points, its most confident ones (1: every point).
        :param trainable: what the training changes (the rest stays as built or loaded; `train_pose` gives the
            optimizer only those parameters): "all", "fusion" (the pose network fixed), "pose" (the fusion network
            fixed, its features on the samples computed once: `cached_features`), or "conf" (the pose network's
            confidence head alone: every point's rotation and translation stay; the fusion network runs without
            gradients in inference mode), or "verifier" (the verifier head alone, the same way; module docstring).
        :param conf_teacher: with trainable "conf", a pose network (frozen) whose confidence on the pallets is the
            target (binary cross-entropy per point) in place of the eq. 4 loss (module docstring).
        :param verifier_target: with trainable "verifier", its target on the pallets: "confidence" (the confidence
            head's, at every point) or "pallet" (1 at the chosen point: pallet or not, the pose's error aside)."""
        if trainable not in TRAINABLE:
            raise ValueError(f"trainable must be one of {TRAINABLE}, got {trainable!r}")
        if trainable == "verifier" and not cfg.pose.verifier:
            raise ValueError(f"config {cfg.name!r} has no verifier head to train (e.g. edge2-verified has)")
        if trainable == "verifier" and negative_conf_top != 1.0:
            raise ValueError("the verifier learns at each negative's chosen point: negative_conf_top does not apply")
        if verifier_target not in VERIFIER_TARGETS:
            raise ValueError(f"verifier_target must be one of {VERIFIER_TARGETS}, got {verifier_target!r}")
        if conf_teacher is not None and trainable != "conf":
            raise ValueError("a confidence teacher needs trainable='conf' (--conf-head-only): its targets hold only "
                             "for the points and features the trained network also has")
        if teacher is not None and trainable in FIXED_FUSION:
            raise ValueError(f"a teacher's features are a target for a trained fusion network; trainable "
                             f"{trainable!r} keeps the fusion network fixed")
        if negatives is not None and teacher is None and not negative_conf_weight > 0:
            raise ValueError("negative crops need a use: a teacher to distil on them (--distill) or a confidence "
                             "weight (--negative-conf-weight)")
        if not 0 < negative_conf_top <= 1:
            raise ValueError(f"negative_conf_top must be in (0, 1], got {negative_conf_top}")
        if negatives is not None and negatives_per_step < 1:
            raise ValueError(f"negatives_per_step must be >= 1, got {negatives_per_step}")
        self.cfg, self.data, self.device, self.w, self.amp = cfg, data, torch.device(device), w, amp
        prepared = data.samples.points.shape[1]
        if num_points is not None and not 0 < num_points <= prepared:
            raise ValueError(f"num_points must be in [1, {prepared}] (the points prepared per sample), got {num_points}")
        self.num_points = num_points if num_points is not None else prepared
        self.fusion = conv_layout(build_fusion(cfg.fusion).to(self.device))
        self.pose = build_pose(cfg.pose, cfg.fusion.feature_dim).to(self.device)
        # per-type geometry as tables indexed by a sample's row in `obj_ids`
        self.obj_ids = np.array(sorted(data.model_points), np.int64)
        self.type_points = stack_model_points([torch.from_numpy(data.model_points[int(o)]) for o in self.obj_ids]
                                              ).float().to(self.device)
        self.type_symmetries = pad_symmetries([torch.from_numpy(data.symmetries[int(o)]).float()
                                               for o in self.obj_ids]).to(self.device)
        self.teacher = None if teacher is None else conv_layout(teacher.to(self.device)).eval().requires_grad_(False)
        self.distill_weight = float(distill_weight)
        self.feature_error = float("nan")    # the last batch's relative feature error against the teacher
        self.last_confidence = torch.zeros(0)  # the last batch's confidence as the graph gives it (B,)
        self.negatives, self.negatives_per_step = negatives, negatives_per_step
        self.negative_conf_weight, self.trainable = float(negative_conf_weight), trainable
        self.negative_conf_top, self.verifier_target = float(negative_conf_top), verifier_target
        if negatives is not None and self.num_points < negatives.choose.shape[1]:
            pts = negatives.points[:, :self.num_points]       # a uniform random subset, re-centred (as positives)
            self.negatives = NegativeCrops(negatives.rgb_crops, negatives.depth_crops,
                                           negatives.choose[:, :self.num_points], pts - pts.mean(1, keepdims=True))
        if negatives is not None:   # every 8th crop held out to measure the student there
            every = np.arange(len(negatives))
            held = every % 8 == 7 if len(negatives) >= 16 else np.zeros(len(negatives), bool)
            self.negatives_train, self.negatives_val = every[~held], every[held]
        self.conf_teacher = None if conf_teacher is None else conf_teacher.to(self.device).eval().requires_grad_(False)
        self._feature_cache: np.ndarray | None = None

    @property
    def nets(self) -> dict[str, torch.nn.Module]:
        return {"fusion": self.fusion, "pose": self.pose}

    def forward_loss(self, idx: np.ndarray, amp: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:param amp: networks under bfloat16 autocast (the loss stays float32).
        :return: loss (scalar), d (B, N) per-point symmetric ADD (metres), conf (B, N)."""
        s = self.data.samples
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(self.device)  # noqa: E731
        rgb, depth, pts, choose = t(s.rgb_crops[idx]), t(s.depth_crops[idx]), t(s.points[idx]), t(s.choose[idx])
        T_gt, obj = t(s.T_gt[idx]), s.obj_id[idx]
        if self.num_points < pts.shape[1]:
            pts, choose, T_gt = subsample_points(pts, choose, T_gt, self.num_points)
        with autocast(self.device.type, amp):
            if self.trainable == "pose":
                point_feats = torch.from_numpy(self.cached_features()[idx].astype(np.float32)).to(self.device)
            else:
                with self._fusion_grad():
                    point_feats = self._features(self.fusion, rgb, depth, choose)
            out = self.pose(pts, point_feats)
        quat, trans, conf = (o.float() for o in out)
        rows = torch.from_numpy(np.searchsorted(self.obj_ids, obj)).to(self.device)
        loss, d = pose_loss(quat, trans, conf, pts, self.type_points[rows], T_gt, self.type_symmetries[rows], self.w)
        if self.conf_teacher is not None:     # poses fixed: the loss is the confidences' distance to the teacher's
            with torch.no_grad(), autocast(self.device.type, amp):
                target = self.conf_teacher(pts, point_feats)[2].float()
            loss = F.binary_cross_entropy(conf.clamp(1e-6, 1 - 1e-6), target)
        self.last_confidence = conf.detach().amax(1)
        if self.pose.head_v is not None:      # the graph's confidence is the verifier's at the chosen point
            with autocast(self.device.type, amp):
                verdict, _ = self.pose.verify(pts, point_feats)
            verdict = verdict.float()
            chosen = verdict.gather(1, conf.argmax(1, keepdim=True))[:, 0]
            if self.trainable == "verifier":  # poses fixed: only the verifier learns
                if self.verifier_target == "pallet":    # a pallet: 1 at the chosen point, whatever its pose's error
                    loss = -torch.log(chosen.clamp(min=1e-6)).mean()
                else:                                   # the confidence head's confidences, at every point
                    loss = F.binary_cross_entropy(verdict.clamp(1e-6, 1 - 1e-6), conf.detach())
            self.last_confidence = chosen.detach()
        if self.teacher is not None:
            with torch.no_grad(), autocast(self.device.type, amp):
                target = self._features(self.teacher, rgb, depth, choose).float()
            err = ((point_feats.float() - target) ** 2).mean() / target.var().clamp_min(1e-12)
            self.feature_error = float(err.detach())
            loss = loss + self.distill_weight * err
        return loss, d, conf

    def negative_terms(self, idx: np.ndarray, amp: bool = False) -> dict[str, torch.Tensor]:
        """On negative crops `idx`: "feat_neg", the relative feature error against the teacher (with a teacher and
        a trainable fusion network), "conf_neg", the mean of -log(1 - confidence) over their points (with
        `negative_conf_weight` > 0), and "conf_max", each crop's best confidence (B,), detached."""
        n = self.negatives.take(idx)
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(self.device)  # noqa: E731
        rgb, depth, choose, pts = t(n.rgb_crops), t(n.depth_crops), t(n.choose), t(n.points)
        out = {}
        with autocast(self.device.type, amp):
            with self._fusion_grad():
                feats = self._features(self.fusion, rgb, depth, choose)
            if self.teacher is not None and self.trainable not in FIXED_FUSION:
                with torch.no_grad():
                    target = self._features(self.teacher, rgb, depth, choose).float()
                out["feat_neg"] = ((feats.float() - target) ** 2).mean() / target.var().clamp_min(1e-12)
            if self.trainable == "verifier":    # the graph's confidence: the verifier's at the chosen point
                verdict, c = self.pose.verify(pts, feats)
                conf = verdict.float().gather(1, c.argmax(1, keepdim=True))
            else:
                conf = self.pose(pts, feats)[2].float()
        if self.negative_conf_weight > 0:
            k = max(1, round(self.negative_conf_top * conf.shape[1]))   # the runtime reads the best point alone
            top = conf.topk(k, dim=1).values if k < conf.shape[1] else conf
            out["conf_neg"] = -torch.log1p(-top.clamp(max=1 - 1e-6)).mean()
        out["conf_max"] = conf.detach().amax(1)
        return out

    def cached_features(self) -> np.ndarray:
        """The fixed fusion network's features at every sample's points (the `num_points` the trainer uses), computed
        on first use (after `--init` has loaded its weights) in inference mode: (n_samples, num_points, C) float16
        (numpy: autocast never sees it). Only for trainable "pose", whose fusion network never changes."""
        if self.trainable != "pose":
            raise RuntimeError("cached_features is for trainable 'pose' (the fusion network fixed)")
        if self._feature_cache is None:
            s, n = self.data.samples, self.num_points
            t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(self.device)  # noqa: E731
            self.fusion.eval()
            parts = []
            with torch.no_grad(), autocast(self.device.type, self.amp):
                for i in range(0, len(s.frame), CACHE_BATCH):
                    rows = slice(i, i + CACHE_BATCH)
                    feats = self._features(self.fusion, t(s.rgb_crops[rows]), t(s.depth_crops[rows]),
                                           t(s.choose[rows][:, :n]))
                    parts.append(feats.float().cpu().numpy().astype(np.float16))
            self._feature_cache = np.concatenate(parts)
            log.info("fusion features of %d samples computed once: %.0f MB", len(self._feature_cache),
                     self._feature_cache.nbytes / 1e6)
        return self._feature_cache

    def _fusion_grad(self):
        """No gradients through a fusion network that is not trained."""
        return torch.no_grad() if self.trainable in FIXED_FUSION else contextlib.nullcontext()

    def _features(self, fusion: torch.nn.Module, rgb: torch.Tensor, depth: torch.Tensor,
                  choose: torch.Tensor) -> torch.Tensor:
        """(B, N, C) fused features at the sampled pixels."""
        rgb, depth = conv_input(rgb), conv_input(depth)
        if self.cfg.fusion.sampled:
            return fusion(rgb, depth, choose)
        return gather_points(fusion(rgb, depth), choose)

    def step(self, idx: np.ndarray, rng: np.random.Generator) -> tuple[torch.Tensor, dict]:
        if self.trainable in FIXED_FUSION:
            self.fusion.eval()          # fixed: its BatchNorm on its running statistics, as the runtime runs it
        loss, d, _ = self.forward_loss(idx, amp=self.amp)
        info = {"dis": float(d.detach().mean())}
        if self.teacher is not None:
            info["feat"] = self.feature_error
        if self.negatives is not None:
            k = min(self.negatives_per_step, len(self.negatives_train))
            terms = self.negative_terms(rng.choice(self.negatives_train, k, replace=False), amp=self.amp)
            if "feat_neg" in terms:
                loss = loss + self.distill_weight * terms["feat_neg"]
                info["feat_neg"] = float(terms["feat_neg"].detach())
            if "conf_neg" in terms:
                loss = loss + self.negative_conf_weight * terms["conf_neg"]
                info["conf_neg"] = float(terms["conf_neg"].detach())
        return loss, info

    def validate(self, batch: int = 16) -> dict:
        """Mean loss, and the symmetric ADD of the most confident hypothesis (the runtime's choice)."""
        idx_all = self.data.val_idx
        losses, errs, feats, conf_all = [], [], [], []
        for i in range(0, len(idx_all), batch):
            idx = idx_all[i:i + batch]
            loss, d, conf = self.forward_loss(idx)
            losses.append(float(loss) * len(idx))
            errs.append(d.gather(1, conf.argmax(1, keepdim=True))[:, 0].cpu().numpy())
            conf_all.append(self.last_confidence.cpu().numpy())
            feats.append(self.feature_error * len(idx))
        e = np.concatenate(errs) if errs else np.zeros(0)
        n = max(len(e), 1)
        extra = {"feature_error": sum(feats) / n} if self.teacher is not None else {}
        if conf_all:        # the share of pallets whose best confidence clears the runtime's default floor
            extra["conf_pass"] = float((np.concatenate(conf_all) >= CONF_FLOOR).mean())
        if self.negatives is not None and len(self.negatives_val):
            held = self.negatives_val
            terms = [self.negative_terms(held[i:i + batch]) for i in range(0, len(held), batch)]
            if "feat_neg" in terms[0]:
                extra["negative_feature_error"] = float(np.mean([float(x["feat_neg"]) for x in terms]))
            extra["negative_conf_pass"] = float((torch.cat([x["conf_max"] for x in terms]).cpu().numpy()
                                                 >= CONF_FLOOR).mean())
        return {**extra, "metric": float(e.mean()) if len(e) else float("inf"), "loss": sum(losses) / n,
                "add_sym_mean_m": float(e.mean()) if len(e) else None,
                "add_sym_median_m": float(np.median(e)) if len(e) else None,
                "add_sym_acc_0.05": float((e < 0.05).mean()) if len(e) else None,
                "add_sym_acc_0.1": float((e < 0.1).mean()) if len(e) else None, "n": len(e)}


def _logit(p: float) -> float:
    p = min(max(p, 1e-7), 1 - 1e-7)
    return float(np.log(p / (1 - p)))


def _floor_scores(trainer: PoseTrainer, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """The graph's confidence at the chosen point and the confidence head's best, per validation pallet."""
    idx_all = trainer.data.val_idx
    if len(idx_all) == 0:
        raise ValueError("no validation samples to calibrate the confidence floor on")
    graph, best = [], []
    for net in trainer.nets.values():
        net.eval()
    with torch.no_grad():
        for i in range(0, len(idx_all), batch):
            _, _, conf = trainer.forward_loss(idx_all[i:i + batch])
            graph.append(trainer.last_confidence.cpu().numpy())
            best.append(conf.amax(1).cpu().numpy())
    return np.concatenate(graph).astype(np.float64), np.concatenate(best).astype(np.float64)


def calibrate_floor(trainer: PoseTrainer, share: float, batch: int = 16, scores: np.ndarray | None = None) -> dict:
    """Shift the output logit (the last bias) of the head the graph's confidence comes from (the verifier where the
    network has one, else the confidence head) so that the runtime's floor (`CONF_FLOOR`) keeps `share` of the
    validation pallets. One constant for every point: each pallet's chosen hypothesis and the ranking stay; only
    where the floor cuts moves. Idempotent (a second call shifts by about 0).

    :param scores: the graph's confidences of the validation pallets, if already computed.
    :return: {"logit_shift", "threshold_before" (the confidence that now maps to the floor), "pallet_share" (the
        share kept), "val_pallets"}.
    :raises ValueError: `share` outside [0, 1], or no validation samples."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"calibrate_floor: share must be in [0, 1], got {share}")
    v = np.sort(scores if scores is not None else _floor_scores(trainer, batch)[0])[::-1]
    k = int(round(share * len(v)))                              # pallets the floor must keep
    if k == 0:
        cut = _logit(v[0]) + 1e-3                               # none: every confidence goes under the floor
    elif k == len(v):
        cut = _logit(v[-1]) - 1e-3
    else:                                                       # between the k-th and (k+1)-th confidences
        cut = 0.5 * (_logit(v[k - 1]) + _logit(v[k]))
    shift = _logit(CONF_FLOOR) - cut
    head = trainer.pose.head_v if trainer.pose.head_v is not None else trainer.pose.head_c
    with torch.no_grad():
        head[-1].bias += shift
    return {"logit_shift": shift, "threshold_before": float(1 / (1 + np.exp(-cut))), "pallet_share": k / len(v),
            "val_pallets": len(v)}


def calibrate_verifier(trainer: PoseTrainer, batch: int = 16) -> dict:
    """`calibrate_floor` of the verifier head to the confidence head's share: the floor then keeps as many
    validation pallets as the confidence head's best confidences clear it, and refuses what the verifier ranks below
    them.

    :raises ValueError: the trainer's network has no verifier head, or no validation samples."""
    if trainer.pose.head_v is None:
        raise ValueError("calibrate_verifier: the pose network has no verifier head")
    graph, best = _floor_scores(trainer, batch)
    return calibrate_floor(trainer, float((best >= CONF_FLOOR).mean()), batch, scores=graph)


def _calibrate_checkpoints(trainer: PoseTrainer, run_dir: Path, share: float | None) -> None:
    """Calibrate each checkpoint the run wrote (each from its own weights): to `share` (`calibrate_floor`), or the
    verifier to the confidence head (`calibrate_verifier`) when `share` is None; recorded in its provenance."""
    key = "verifier_calibration" if share is None else "confidence_calibration"
    for name in (LAST, BEST):
        path = run_dir / name
        if not path.is_file():
            continue
        ckpt = load_checkpoint(path)
        for k, net in trainer.nets.items():
            net.load_state_dict(ckpt[k])
        record = calibrate_verifier(trainer) if share is None else calibrate_floor(trainer, share)
        ckpt["pose"] = trainer.pose.state_dict()
        ckpt["provenance"] = {**ckpt["provenance"], key: record}
        save_checkpoint(path, ckpt)
        log.info("%s: %s shifted by %.3f in logit space (%.4f -> the floor %.2f; %.1f %% of %d validation pallets "
                 "kept)", path, key.split("_")[0], record["logit_shift"], record["threshold_before"], CONF_FLOOR,
                 100 * record["pallet_share"], record["val_pallets"])


def train_pose(cfg: ModelConfig, data: Sequence[str | Path], run_dir: str | Path, settings: LoopSettings,
               variants: int = 2, aug: AugmentConfig | None = None, resume: bool = False,
               cache_dir: str | Path | None = None, val_fraction: float = 0.1, max_frames: int | None = None,
               command: str = "", progress: bool = True, init: str | Path | None = None,
               num_points: int | None = None, distill: str | Path | None = None, distill_weight: float = 1.0,
               freeze_pose: bool = False, negatives: dict | None = None, negative_conf_weight: float = 0.0,
               conf_head_only: bool = False, mismatched_frames: int = 0, keep_pallet_conf: bool = False,
               negative_conf_top: float = 1.0, verifier_only: bool = False,
               verifier_target: str = "confidence", calibrate_share: float | None = None,
               pose_only: bool = False) -> dict:
    """Train the pose stage on BOP datasets; checkpoints and the log go to `run_dir`. Returns the last log entry.

    :param num_points: points per pallet the network is trained on (default: the config's); samples are prepared
        (and cached) at the config's count and cut to a random `num_points` of them (`PoseTrainer`).
    :param distill: a bundle or checkpoint whose fusion network's features are a second target (module docstring);
        it must take the same crops as `cfg`'s. :param distill_weight: that target's weight.
    :param freeze_pose: train the fusion network alone under a fixed pose network (e.g. a smaller fusion network
        learning to serve a trained pose network, whose confidences then keep the meaning the runtime's thresholds
        were chosen for).
    :param negatives: crops without a pallet (`negative_crops`) for distillation (with `distill`) and for the
        confidence (`negative_conf_weight`; `PoseTrainer`): keyword arguments of `load_negative_crops` but `spec`
        and `cache_dir` (`detector_bundle`, `presets`, `frames`, `seed`, ...).
    :param conf_head_only: train the pose network's confidence head alone, everything else fixed (poses keep
        their rotation and translation at every point).
    :param negative_conf_top: the negatives' confidence term over this fraction of each crop's most confident
        points (`PoseTrainer`).
    :param keep_pallet_conf: with `conf_head_only`, train the pallets' confidences toward those of `init`'s pose
        network (same config) instead of the eq. 4 loss (`PoseTrainer`'s `conf_teacher`).
    :param mismatched_frames: add crops of this many training frames' pallets under depth or intrinsics that do not
        belong to the image (`negative_crops.build_mismatched_crops`, every kind) to the negatives.
    :param verifier_only: train the verifier head alone (a config with one, `PoseConfig.verifier`; `PoseTrainer`),
        everything else fixed: every pose stays. Started from a network without one (`init`), it starts as a copy
        of the confidence head. The checkpoints are then calibrated (`calibrate_verifier`).
    :param verifier_target: the verifier's target on the pallets (`PoseTrainer`).
    :param pose_only: train the pose network alone on the fixed fusion network's features, computed once per
        sample (`PoseTrainer.cached_features`): each step is the pose network's alone.
    :param calibrate_share: after training, shift the graph confidence's output logit in each checkpoint so that the
        runtime's floor keeps this share of the validation pallets (`calibrate_floor`); with `resume` on a finished
        run, only that. Not with `verifier_only`, which calibrates to the confidence head.
    """
    if calibrate_share is not None and (verifier_only or not 0.0 < calibrate_share <= 1.0):
        raise ValueError(f"--calibrate-share {calibrate_share}: a share in (0, 1], and not with --verifier-only (which "
                         "calibrates the verifier to the confidence head)")
    if sum((freeze_pose, conf_head_only, verifier_only, pose_only)) > 1:
        raise ValueError("--freeze-pose, --pose-only, --conf-head-only and --verifier-only exclude each other")
    if keep_pallet_conf and not (conf_head_only and init is not None and not resume):
        raise ValueError("--keep-pallet-conf needs --conf-head-only and --init (the network whose confidences it keeps), "
                         "without --resume")
    if keep_pallet_conf and init_config(init) != cfg.name:
        raise ValueError(f"--keep-pallet-conf: --init {init} is a {init_config(init)!r} network, not {cfg.name!r}")
    run_dir = Path(run_dir)
    aug = aug or AugmentConfig()
    torch.manual_seed(settings.seed)
    pd = load_pose_data(cfg, data, variants, settings.seed, aug, cache_dir if cache_dir is not None else run_dir / "cache",
                        val_fraction, max_frames, progress)
    teacher, distilled = (None, None) if distill is None else _teacher(distill, cfg)
    neg_parts, neg_record = [], {}
    cache = cache_dir if cache_dir is not None else run_dir / "cache"
    if negatives is not None:
        crops, neg_record["pallet_free"] = load_negative_crops(spec=pose_input_spec(cfg), cache_dir=cache, **negatives)
        neg_parts.append(crops)
    if mismatched_frames > 0:
        crops, neg_record["mismatched"] = load_mismatched_crops(data, pose_input_spec(cfg), mismatched_frames,
                                                                settings.seed, cache)
        neg_parts.append(crops)
    neg_crops = None if not neg_parts else neg_parts[0] if len(neg_parts) == 1 else NegativeCrops(
        *(np.concatenate([getattr(c, f) for c in neg_parts]) for f in ("rgb_crops", "depth_crops", "choose", "points")))
    if neg_crops is not None:
        log.info("negative crops: %s", {k: v["crops"] for k, v in neg_record.items()})
    trainable = ("conf" if conf_head_only else "verifier" if verifier_only else "fusion" if freeze_pose
                 else "pose" if pose_only else "all")
    conf_teacher = None
    if keep_pallet_conf:
        conf_teacher = build_pose(cfg.pose, cfg.fusion.feature_dim)
        load_init_weights(init, {"pose": conf_teacher})
    trainer = PoseTrainer(cfg, pd, settings.device, amp=settings.amp, num_points=num_points, teacher=teacher,
                          distill_weight=distill_weight, negatives=neg_crops,
                          negative_conf_weight=negative_conf_weight, trainable=trainable, conf_teacher=conf_teacher,
                          negative_conf_top=negative_conf_top, verifier_target=verifier_target)
    if trainable in ("fusion", "conf", "verifier"):
        trainer.pose.requires_grad_(False)
    if trainable in FIXED_FUSION:
        trainer.fusion.requires_grad_(False)
    if trainable in ("conf", "verifier"):
        (trainer.pose.head_c if trainable == "conf" else trainer.pose.head_v).requires_grad_(True)
    params = [p for net in trainer.nets.values() for p in net.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=settings.lr)
    provenance = {"stage": "pose", "config": cfg.name, "seed": settings.seed, "command": command,
                  "data": pd.fingerprints, "epochs": settings.epochs, "batch": settings.batch, "lr": settings.lr,
                  "variants": variants, "num_points": trainer.num_points, "augment": aug.to_dict(),
                  "val_fraction": val_fraction,
                  "samples": {"train": int(len(pd.train_idx)), "val": int(len(pd.val_idx))},
                  "device": settings.device, "amp": "bf16" if settings.amp else None, "torch": str(torch.__version__),
                  "pallet_types": {str(k): v for k, v in sorted(pd.type_names.items())}}
    if distilled is not None:
        provenance["distill"] = {**distilled, "weight": distill_weight}
    if neg_record:
        provenance["negatives"] = {**neg_record, "conf_weight": negative_conf_weight, "conf_top": negative_conf_top}
    if conf_head_only or verifier_only:
        provenance["trainable"] = "conf_head" if conf_head_only else "verifier_head"
    if verifier_only:
        provenance["verifier_target"] = verifier_target
    if keep_pallet_conf:
        provenance["pallet_conf_target"] = "init"
    if freeze_pose:
        provenance["freeze_pose"] = True
    if pose_only:
        provenance["trainable"] = "pose_network"
    if init is not None and not resume and init_config(init) != cfg.name:
        # another config's weights (e.g. edge2 from the edge bundle): copy what fits
        provenance["init"] = warm_start(init, trainer.nets)
        if cfg.pose.verifier and not get_config(init_config(init)).pose.verifier:
            trainer.pose.head_v.load_state_dict(trainer.pose.head_c.state_dict())
            provenance["init"]["verifier"] = "the confidence head's weights"
        init = None
    entry = train_epochs(run_dir, "pose", cfg.name, trainer.nets, optimizer, settings, len(pd.train_idx),
                         lambda idx, rng: trainer.step(pd.train_idx[idx], rng), trainer.validate, provenance,
                         resume=resume, progress=progress, init=init)
    if verifier_only or calibrate_share is not None:
        _calibrate_checkpoints(trainer, run_dir, calibrate_share)
    return entry


def _teacher(path: str | Path, cfg: ModelConfig) -> tuple[torch.nn.Module, dict]:
    """The fusion network of a bundle or checkpoint, for distillation, and what to record of it.

    :raises ValueError: it does not take the crops `cfg`'s fusion network takes (crop size, sampled or dense, feature
        dimension)."""
    t_cfg = get_config(init_config(path))
    mine, theirs = cfg.fusion, t_cfg.fusion
    if (mine.crop_hw, mine.sampled, mine.feature_dim) != (theirs.crop_hw, theirs.sampled, theirs.feature_dim):
        raise ValueError(f"--distill {path}: its fusion network ({t_cfg.name}: crop {theirs.crop_hw}, sampled "
                         f"{theirs.sampled}, {theirs.feature_dim} features) does not take and give what {cfg.name}'s "
                         f"does (crop {mine.crop_hw}, sampled {mine.sampled}, {mine.feature_dim} features)")
    teacher = build_fusion(theirs)
    record = load_init_weights(path, {"fusion": teacher})
    return teacher, {"source": record, "config": t_cfg.name}
