"""Losses: the pose loss of eq. 4 (symmetry-aware), and YOLOv8's detector loss (task-aligned assigner,
CIoU + DFL box regression, BCE classification)."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .detector import YoloDetector, make_anchors

__all__ = ["quat_to_rot", "pose_loss", "pad_symmetries", "stack_model_points", "bbox_ciou", "DetectorLoss",
           "detector_distill_loss"]


# ----------------------------------------------------------------------------------------------- pose


def quat_to_rot(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions (w, x, y, z), normalised here -> (..., 3, 3) rotation matrices."""
    q = F.normalize(q, dim=-1, eps=1e-8)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def pose_loss(quat: torch.Tensor, trans: torch.Tensor, conf: torch.Tensor, points: torch.Tensor,
              model_points: torch.Tensor, T_gt: torch.Tensor, symmetries: torch.Tensor | None = None,
              w: float = 0.015) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 4 per point: L = mean_i (d_i c_i - w log c_i), with d_i = mean_m ||T_i p_m - T_gt p_m||.

    T_i = (R(quat_i), points_i + trans_i) is point i's pose prediction; with `symmetries` (S, 4, 4)
    d_i is the minimum over the ground truth composed with each symmetry, T_gt S_s, so a pallet turned
    by one of its symmetries is not penalised. A batch of several pallet types passes each sample's own
    geometry: `model_points` (B, M, 3) and `symmetries` (B, S, 4, 4) (`stack_model_points`, `pad_symmetries`).

    :param quat: (B, N, 4) wxyz. :param trans: (B, N, 3) offsets from `points`. :param conf: (B, N) in (0, 1).
    :param points: (B, N, 3) centred camera-frame points (metres).
    :param model_points: (M, 3) or (B, M, 3) pallet-frame model points (metres).
    :param T_gt: (B, 4, 4) ground-truth pose in the same (centred) camera frame as `points`.
    :param symmetries: (S, 4, 4) pallet-frame symmetry transforms, identity first, shared by the batch; or
        (B, S, 4, 4) per sample (padded with identities); or None.
    :param w: confidence regulariser (DenseFusion: 0.015).
    :return: scalar loss, and (B, N) distances d_i (metres) for monitoring.
    """
    b, n, _ = quat.shape
    pm = model_points if model_points.dim() == 3 else model_points.unsqueeze(0).expand(b, -1, -1)
    if T_gt.shape != (b, 4, 4) or points.shape != (b, n, 3) or trans.shape != (b, n, 3) or conf.shape != (b, n):
        raise ValueError(f"pose_loss: shapes quat {tuple(quat.shape)}, trans {tuple(trans.shape)}, conf "
                         f"{tuple(conf.shape)}, points {tuple(points.shape)}, T_gt {tuple(T_gt.shape)} do not agree")
    R = quat_to_rot(quat)                                                      # (B, N, 3, 3)
    t = points + trans                                                         # (B, N, 3)
    pred = torch.einsum("bnij,bmj->bnmi", R, pm) + t[:, :, None, :]           # (B, N, M, 3)
    sym = torch.eye(4, dtype=T_gt.dtype, device=T_gt.device)[None] if symmetries is None else symmetries.to(T_gt)
    if sym.dim() == 3:
        sym = sym[None]
    if sym.dim() != 4 or sym.shape[0] not in (1, b) or sym.shape[-2:] != (4, 4):
        raise ValueError(f"pose_loss: symmetries must be (S, 4, 4) or ({b}, S, 4, 4), got {tuple(sym.shape)}")
    if pm.shape[0] != b or pm.shape[-1] != 3:
        raise ValueError(f"pose_loss: model_points must be (M, 3) or ({b}, M, 3), got {tuple(model_points.shape)}")
    T_sym = T_gt[:, None] @ sym                                                # (B, S, 4, 4)
    target = torch.einsum("bsij,bmj->bsmi", T_sym[..., :3, :3], pm) + T_sym[:, :, None, :3, 3]   # (B, S, M, 3)
    dist = (pred[:, :, None] - target[:, None]).norm(dim=-1).mean(-1)          # (B, N, S)
    d = dist.min(-1).values
    c = conf.clamp(1e-6, 1.0)
    return (d * c - w * torch.log(c)).mean(), d


def pad_symmetries(symmetries: list[torch.Tensor]) -> torch.Tensor:
    """Per-sample symmetry sets (S_i, 4, 4) -> (B, max S_i, 4, 4), each padded with identities.

    A repeated identity changes nothing in `pose_loss`'s minimum over symmetries.
    """
    if not symmetries:
        raise ValueError("pad_symmetries: no symmetry sets")
    s_max = max(len(s) for s in symmetries)
    out = torch.eye(4, dtype=symmetries[0].dtype, device=symmetries[0].device).repeat(len(symmetries), s_max, 1, 1)
    for i, s in enumerate(symmetries):
        if s.dim() != 3 or s.shape[1:] != (4, 4) or len(s) < 1:
            raise ValueError(f"pad_symmetries: set {i} must be (S, 4, 4) with S >= 1, got {tuple(s.shape)}")
        out[i, :len(s)] = s
    return out


def stack_model_points(points: list[torch.Tensor]) -> torch.Tensor:
    """Per-sample model points (M_i, 3) -> (B, max M_i, 3); a shorter set repeats its points cyclically (its
    mean distance in `pose_loss` stays that of its own surface, reweighted by at most one repeat)."""
    if not points:
        raise ValueError("stack_model_points: no point sets")
    m = max(len(p) for p in points)
    rows = []
    for i, p in enumerate(points):
        if p.dim() != 2 or p.shape[1] != 3 or len(p) < 1:
            raise ValueError(f"stack_model_points: set {i} must be (M, 3) with M >= 1, got {tuple(p.shape)}")
        rows.append(p[torch.arange(m, device=p.device) % len(p)])
    return torch.stack(rows)


# ------------------------------------------------------------------------------------------- detector


def bbox_ciou(b1: torch.Tensor, b2: torch.Tensor, eps: float = 1e-7) -> torch.Tensor:
    """Complete IoU of matching boxes (..., 4) xyxy -> (...)."""
    w1, h1 = (b1[..., 2] - b1[..., 0]).clamp(min=eps), (b1[..., 3] - b1[..., 1]).clamp(min=eps)
    w2, h2 = (b2[..., 2] - b2[..., 0]).clamp(min=eps), (b2[..., 3] - b2[..., 1]).clamp(min=eps)
    inter = ((torch.minimum(b1[..., 2], b2[..., 2]) - torch.maximum(b1[..., 0], b2[..., 0])).clamp(min=0) *
             (torch.minimum(b1[..., 3], b2[..., 3]) - torch.maximum(b1[..., 1], b2[..., 1])).clamp(min=0))
    iou = inter / (w1 * h1 + w2 * h2 - inter + eps)
    cw = torch.maximum(b1[..., 2], b2[..., 2]) - torch.minimum(b1[..., 0], b2[..., 0])
    ch = torch.maximum(b1[..., 3], b2[..., 3]) - torch.minimum(b1[..., 1], b2[..., 1])
    c2 = cw ** 2 + ch ** 2 + eps
    rho2 = ((b2[..., 0] + b2[..., 2] - b1[..., 0] - b1[..., 2]) ** 2 +
            (b2[..., 1] + b2[..., 3] - b1[..., 1] - b1[..., 3]) ** 2) / 4
    v = (4 / math.pi ** 2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)) ** 2
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)


def _box_iou_pairwise(gt: torch.Tensor, pred: torch.Tensor, eps: float = 1e-9) -> torch.Tensor:
    """gt (B, G, 4), pred (B, A, 4) xyxy -> (B, G, A) IoU."""
    g, p = gt[:, :, None], pred[:, None]
    inter = ((torch.minimum(g[..., 2], p[..., 2]) - torch.maximum(g[..., 0], p[..., 0])).clamp(min=0) *
             (torch.minimum(g[..., 3], p[..., 3]) - torch.maximum(g[..., 1], p[..., 1])).clamp(min=0))
    area = lambda b: (b[..., 2] - b[..., 0]).clamp(min=0) * (b[..., 3] - b[..., 1]).clamp(min=0)  # noqa: E731
    return inter / (area(g) + area(p) - inter + eps)


def detector_distill_loss(student: list[torch.Tensor], teacher: list[torch.Tensor],
                          reg_max: int) -> tuple[torch.Tensor, torch.Tensor]:
    """How far a detector's raw maps are from a teacher's (the same layout, `YoloDetector.forward_raw`): every
    anchor's class scores by the Bernoulli KL divergence from the teacher's probabilities, its box sides by the KL
    divergence of their DFL bin distributions, weighted by the teacher's best class probability (its boxes count
    where it sees a pallet). Both sums are divided by the teacher's total best probability, as YOLOv8 divides by
    its target scores: zero where the student computes what the teacher does.

    :param student, teacher: per level (B, 4 * reg_max + nc, H_l, W_l). :return: (class term, box term).
    """
    s = torch.cat([r.flatten(2) for r in student], 2).float()          # (B, 4 * reg_max + nc, A)
    t = torch.cat([r.flatten(2) for r in teacher], 2).float()
    nb = 4 * reg_max
    p_t = t[:, nb:].sigmoid()
    cls = (F.binary_cross_entropy_with_logits(s[:, nb:], p_t, reduction="none")
           - F.binary_cross_entropy_with_logits(t[:, nb:], p_t, reduction="none"))
    weight = p_t.amax(1)                                                # (B, A)
    norm = weight.sum().clamp(min=1.0)
    b, _, a = s.shape
    log_s = s[:, :nb].reshape(b, 4, reg_max, a).log_softmax(2)
    log_t = t[:, :nb].reshape(b, 4, reg_max, a).log_softmax(2)
    kl_box = (log_t.exp() * (log_t - log_s)).sum(2).mean(1)            # (B, A)
    return cls.sum() / norm, (kl_box * weight).sum() / norm


class DetectorLoss:
    """YOLOv8 detection loss: TAL assignment (top-k by score^alpha * IoU^beta among anchors inside the box),
    BCE on soft (alignment-normalised) class targets, CIoU and DFL on the assigned anchors.

    A target of class -1 is a pallet of unknown type (real photographs carry no type): it supervises the box and
    "is a pallet", the class-agnostic maximum over the type scores. Its anchors are assigned by that maximum, and
    their class loss is taken on the highest-scoring type alone (the other types are left free); on anchors that
    no box claims every type is pushed to 0, as for typed targets. With one class it is the same as class 0.

    :param targets (in `__call__`): list of B tensors (n_i, 5) = class (-1: any pallet type), x1, y1, x2, y2 in
        input pixels.
    """

    def __init__(self, model: YoloDetector, topk: int = 10, alpha: float = 0.5, beta: float = 6.0,
                 box_gain: float = 7.5, cls_gain: float = 0.5, dfl_gain: float = 1.5) -> None:
        self.nc, self.reg_max = model.head.nc, model.head.reg_max
        self.topk, self.alpha, self.beta = topk, alpha, beta
        self.gains = (box_gain, cls_gain, dfl_gain)

    def _assign(self, scores, pred_boxes, anchors, gt_labels, gt_boxes, gt_mask, strides=None):
        """All in pixels. scores (B, A, nc) sigmoid; gt_* padded to (B, G, ...), label -1 = any type; strides (A, 1)
        each anchor's stride (None: every anchor is a candidate for the boxes it lies in).
        Returns target boxes, target scores, fg mask (B, A) and the class-loss mask (B, A, nc).

        A candidate anchor lies inside the box and, given `strides`, can reach its edges: the distance bins span
        reg_max - 1 strides, so a fine level cannot draw a large box. Without that rule a level whose scores fell
        early is never picked again (TAL ranks by score) and large boxes go to anchors that can only draw them too
        small; a box that no anchor can reach keeps every anchor inside it."""
        b, a, _ = scores.shape
        g = gt_boxes.shape[1]
        if g == 0:
            return (torch.zeros_like(pred_boxes), torch.zeros_like(scores),
                    torch.zeros(b, a, dtype=torch.bool, device=scores.device), torch.ones_like(scores))
        lt = anchors[None, None] - gt_boxes[:, :, None, :2]
        rb = gt_boxes[:, :, None, 2:] - anchors[None, None]
        ltrb = torch.cat((lt, rb), -1)
        in_gt = ltrb.amin(-1) > 1e-9                                                      # (B, G, A)
        if strides is not None:
            reaches = in_gt & (ltrb.amax(-1) <= (self.reg_max - 1) * strides[:, 0])
            in_gt = torch.where(reaches.any(-1, keepdim=True), reaches, in_gt)
        valid = in_gt & gt_mask[:, :, None]
        overlaps = _box_iou_pairwise(gt_boxes, pred_boxes) * valid
        untyped = gt_labels < 0                                                           # (B, G)
        cls_idx = gt_labels.long().clamp(0, self.nc - 1)
        box_scores = torch.gather(scores.transpose(1, 2), 1, cls_idx[:, :, None].expand(-1, -1, a))
        box_scores = torch.where(untyped[:, :, None], scores.amax(-1)[:, None, :], box_scores) * valid
        metric = box_scores.pow(self.alpha) * overlaps.pow(self.beta)
        k = min(self.topk, a)
        top = metric.topk(k, dim=-1).indices
        mask_top = torch.zeros_like(metric).scatter_(-1, top, 1.0).bool()
        mask_pos = mask_top & valid                                                       # (B, G, A)
        multi = mask_pos.sum(1) > 1                                                       # anchor claimed twice
        if multi.any():
            best = F.one_hot(overlaps.argmax(1), g).transpose(1, 2).bool()                # (B, G, A)
            mask_pos = torch.where(multi[:, None], best & valid, mask_pos)
        fg = mask_pos.any(1)                                                              # (B, A)
        gt_idx = mask_pos.float().argmax(1)                                               # (B, A)
        t_boxes = torch.gather(gt_boxes, 1, gt_idx[..., None].expand(-1, -1, 4))
        t_untyped = torch.gather(untyped, 1, gt_idx) & fg                                 # (B, A)
        t_labels = torch.where(t_untyped, scores.argmax(-1), torch.gather(cls_idx, 1, gt_idx))
        cls_mask = torch.where(t_untyped[..., None], F.one_hot(t_labels, self.nc).to(scores.dtype),
                               torch.ones_like(scores))
        metric = metric * mask_pos
        pos_metric = metric.amax(-1, keepdim=True)
        pos_overlap = (overlaps * mask_pos).amax(-1, keepdim=True)
        norm = (metric * pos_overlap / (pos_metric + 1e-9)).amax(1)                       # (B, A)
        t_scores = F.one_hot(t_labels, self.nc).float() * (norm * fg)[..., None]
        return t_boxes, t_scores, fg, cls_mask

    def __call__(self, raw: list[torch.Tensor], targets: list[torch.Tensor]) -> tuple[torch.Tensor, dict]:
        b = raw[0].shape[0]
        if len(targets) != b:
            raise ValueError(f"DetectorLoss: {len(targets)} target lists for a batch of {b}")
        anchors, strides = make_anchors([tuple(x.shape[2:]) for x in raw], device=raw[0].device)
        x = torch.cat([r.flatten(2) for r in raw], 2).transpose(1, 2)                     # (B, A, 4R + nc)
        pred_dist, pred_logits = x.split((4 * self.reg_max, self.nc), -1)
        bins = torch.arange(self.reg_max, dtype=x.dtype, device=x.device)
        ltrb = (pred_dist.view(b, -1, 4, self.reg_max).softmax(-1) * bins).sum(-1)        # grid units
        pred_boxes = torch.cat((anchors - ltrb[..., :2], anchors + ltrb[..., 2:]), -1)    # (B, A, 4) grid units
        g = max((len(t) for t in targets), default=0)
        gt = torch.zeros(b, g, 5, device=x.device)
        gt_mask = torch.zeros(b, g, dtype=torch.bool, device=x.device)
        for i, t in enumerate(targets):
            if len(t):
                gt[i, :len(t)] = t
                gt_mask[i, :len(t)] = True
        t_boxes, t_scores, fg, cls_mask = self._assign(pred_logits.detach().sigmoid(),
                                                       pred_boxes.detach() * strides, anchors * strides,
                                                       gt[..., 0], gt[..., 1:], gt_mask, strides)
        t_sum = t_scores.sum().clamp(min=1.0)
        loss_cls = (F.binary_cross_entropy_with_logits(pred_logits, t_scores, reduction="none") * cls_mask).sum() \
            / t_sum
        loss_box = loss_dfl = x.new_zeros(())
        if fg.any():
            weight = t_scores.sum(-1)[fg]
            t_grid = t_boxes / strides
            loss_box = ((1.0 - bbox_ciou(pred_boxes[fg], t_grid[fg])) * weight).sum() / t_sum
            a = anchors[None].expand(b, -1, -1)[fg]
            t_ltrb = torch.cat((a - t_grid[fg][:, :2], t_grid[fg][:, 2:] - a), -1).clamp(0, self.reg_max - 1 - 0.01)
            left = t_ltrb.floor().long()
            wl = left + 1 - t_ltrb
            logits = pred_dist[fg].view(-1, self.reg_max)
            dfl = (F.cross_entropy(logits, left.view(-1), reduction="none").view(-1, 4) * wl +
                   F.cross_entropy(logits, (left + 1).view(-1), reduction="none").view(-1, 4) * (1 - wl))
            loss_dfl = (dfl.mean(-1) * weight).sum() / t_sum
        gb, gc, gd = self.gains
        total = gb * loss_box + gc * loss_cls + gd * loss_dfl
        return total, {"box": float(loss_box.detach()), "cls": float(loss_cls.detach()),
                       "dfl": float(loss_dfl.detach()), "fg": int(fg.sum())}
