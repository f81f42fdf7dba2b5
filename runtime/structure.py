"""Pallet structure check: does the depth show a pallet of this type where the pose puts it? (numpy; the rays in
the compiled kernel where it is built)

The fit score (`fit.py`) asks whether the observed points lie on the posed model's surface. A pallet's face is
mostly a plane, so a wall, a carton face or the floor can pass it. This check looks for what only a pallet shows,
by casting rays through a grid of pixels over the posed model's projected silhouette against the model's boxes
(boards, blocks, runners, legs) and comparing with the observed depth:

- a ray that hits a box expects a surface at that depth: *solid* when the observed depth is within the tolerance,
  *see-through* when it lies behind (the camera saw through wood), no evidence when it lies in front (something
  occludes the pallet) or is missing;
- a ray that enters the pallet's bounding box but hits no box passes through an opening (a fork pocket, a gap
  between boards): *open* when the observed depth lies behind the entry point by more than the tolerance,
  *closed* when a surface sits at the entry (a wall or a carton face where the pocket should be), no evidence
  when it lies in front or is missing. A ray that enters through an opening and meets a board or block deeper inside
  (a pocket seen a little from below or aside) is evidence about that opening's mouth: *open* when the depth lies
  behind the entry, *closed* when a surface sits at the entry (a carton face where the pallet's front should be).

A pose is accepted when the evidence agrees with the model (solid + open against see-through + closed), the
openings it can see are mostly open, the detector's box lies inside the posed model's silhouette, and, when the
caller knows which way is up (a calibrated camera), the pallet stands upright.

Two tests ask whether the depth belongs to the image at all (they fail as "size_mismatch" and
"depth_image_mismatch", which the fit-check stage reports as rejection reasons of their own):

- metric size: the detector's box, at the median depth inside it and the focal length, spans a metric height and
  width; a pallet's visible face is at least about its own height tall and at most its diameter across. A depth
  scale 10x too small (or a focal length far too long) shrinks that size by the same factor, 10x too large grows it.
  A box that the image's top or bottom edge does not cut shows the pallet's whole height, so there the bound is
  tight enough to catch a focal length 2x too long;
- edge agreement: where the observed depth jumps between neighbouring rays of the grid, the colour image should
  change too (a surface ends there). The rank statistic (AUC) of the colour differences across depth jumps against
  those elsewhere is about 0.5 when the depth comes from another frame or is not registered to the image, and
  0.6-0.99 (median 0.86) on the validation frames, whose depth belongs to the image.

Before these per-pallet tests the fit-check stage runs the frame-level registration test (`registration.py`, with
this check's `StructureParams`): the frame's depth edges, pooled over all candidates, must lie on the image's at
zero shift and not as well with the depth shifted, and the depth must step somewhere around them (it is not flat);
else every candidate is "depth_image_mismatch" (a flat depth: the detector's candidates, not the depth's proposals).

Mismatched inputs fail it: depth of a flat wall (openings closed), another frame's depth (nothing agrees, edges
elsewhere), a depth scale or a focal length that is off (the box's metric size, or the posed model's boards
project where the image has none). The tolerance grows with range like stereo depth noise:
`tol_m + tol_quad_per_m * z**2`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .geometry import check_K
from .registration import RegistrationScore, registration_score

__all__ = ["BoxSets", "StructureParams", "StructureScore", "structure_check", "structure_agreement", "cast_rays_boxes",
           "box_metric_size", "edge_agreement", "frame_registration", "frame_size_rule",
           "registration_verdict"]

_BIG = 1e12


@dataclass(frozen=True)
class StructureParams:
    """Thresholds of the structure check (lengths in metres).

    :ivar grid: rays per side of the grid over the posed model's projected bounding box.
    :ivar tol_m: depth tolerance at zero range.
    :ivar tol_quad_per_m: tolerance growth with range, metres per metre squared (stereo noise grows with z**2).
    :ivar min_evidence: fewer rays with evidence (solid, see-through, open, closed) -> "structure_unseen".
    :ivar min_agreement: (solid + open) / all evidence below this -> "structure_mismatch".
    :ivar min_agreement_levelled: the same with a calibration (`up_cam` given): the estimator has then levelled the
        poses and searched their yaw and position (`level.py`), which finds a pose that agrees fairly well on some
        things that are no pallet too (a load over a gap: 0.63). On 80 validation forklift views (D435-like and
        ToF-like depth, detector boxes) 0.65 refused 7 of the 104 poses not within 5 cm of a pallet and 1 of the
        123 within (0.7: 16 and 3; `docs/experiments/forklift.md`).
    :ivar min_opening_evidence: openings are judged only with at least this many open + closed rays through them,
        or as many judging their mouths (a flat wall under a pallet cut by the image's edge showed 11 closed rays and
        no open one on the validation frames; correct poses there pass with as few as 4; a few of each kind on a
        pallet mostly hidden or cut by the image's edge are no verdict).
    :ivar min_open_fraction: the open fraction (`StructureScore.open_fraction`: the rays through the openings and
        those judging their mouths) below this -> "openings_closed". Poses of carton faces on pallet-free frames
        with the loads standing on the floor show 0.15-0.24; 0.25 refuses most of them but also far, mostly hidden
        pallets of the occluded preset (ADD-sym within 5 cm 77.3 -> 76.3 %; 0.15: 76.9 %), so a site with many
        carton stacks may raise it (`docs/experiments/structure-check.md`).
    :ivar min_pocket_evidence: a pocket (each half of a side face of the model's bounding box: an opening and its
        blocks on an EPAL's faces) is judged with at least this many rays through it or at its mouth (a correct pose
        of a pallet cut by the image's edge showed one pocket with 8 rays, all closed; 8-16 refuse the same carton
        poses).
    :ivar min_pocket_open_fraction: the open fraction of the most open pocket judged (`StructureScore.pocket_open`)
        below this -> "pockets_closed": a pallet shows at least one open pocket, also with an obstacle in the other,
        while a carton stack's bottom posed as a pallet closes them all, though a few rays between its cartons or
        through the top make its overall open fraction pass. Pallet-free frames with the loads standing on the floor
        (400 frames): 7 of the 22 poses accepted there refused; correct poses (within 5 cm) refused: 0 of 541 on the
        test frames, 1 of 351 on the validation frames (a ToF-like view at 5 m); 0.4 refuses one more carton pose
        and 2 of the 351 (`docs/experiments/structure-check.md`).
    :ivar max_pocket_range_m: pockets are judged only on pallets at most this far from the camera. Farther, a pocket
        is a few pixels and the depth tolerance (`tol_quad_per_m`: 16 cm at 6 m) nears a block's depth: the correct
        poses refused on the occluded test preset without it were 6.3 and 7.8 m away, a third and half visible.
        A forklift picks within a few metres.
    :ivar min_box_cover: fraction of the detector's box inside the posed model's projected box; below ->
        "box_mismatch".
    :ivar min_box_solid: of the rays inside the detector's box that hit the posed model and find a surface at it
        or behind it, the fraction that find its surface; below -> "box_mismatch" (the box shows something behind
        the pose).
    :ivar min_seen_iou: IoU of the detector's box with the box around the rays that found the pallet's surface;
        below -> "box_mismatch" (the pose explains depth elsewhere than where the detector saw the pallet).
    :ivar max_see_through_cut: a box that the image's edge cuts and whose size cannot show a focal length 2x too long
        (cut at the top or bottom, or cut aside and less than twice `min_whole_box_height_of_type` tall) must not
        see through the pose's boards: where more than this fraction of the rays that meet a board find the depth
        behind it (see-through / (solid + see-through)) -> "see_through_cut". A focal length 2x too long halves the
        scene across the image, and the network fits a pallet to the squeezed points of a cut pallet whose boards
        then overhang them: such poses see through 0.13-0.40 of their boards, correct poses of cut pallets rarely
        more than 0.2 (docs/structure-check.md); 1 turns it off.
    :ivar max_see_through_beyond_box: a box that the image's edge does not cut holds the whole pallet the detector
        saw, so the posed pallet must not stand where the depth is free beyond it: of the rays that meet the pose's
        boards (solid + see-through), the fraction outside the detector's box widened by
        `beyond_box_margin` on each side that see through them above this -> "see_through_beyond_box". A focal
        length 2x too long draws the pose twice the size of the pallet in the image, past a box the pallet fills;
        an occluded pallet's box is smaller than the pose too, but the rays beyond it meet the occluder in front,
        not free space. Correct poses of whole boxes on the validation frames stay at or under 0.031 (presets) and
        0.089 (calibrated forklift views, one pose over 0.05); 1 turns it off (docs/structure-check.md).
    :ivar beyond_box_margin: the detector's box is widened by this fraction of its width and height on each side
        for `max_see_through_beyond_box` (a box a few pixels tight is no evidence).
    :ivar max_tilt_deg: with an up vector, the pallet's z axis may lean at most this much from it -> "tilted".
    :ivar min_box_height_of_type: the detector's box height times the median depth inside it over fy (its metric
        height) below this fraction of the type's height (its smallest side) -> "size_mismatch" (depth scale too
        small, focal length too long). A loose bound that holds for a box the image's top or bottom edge cuts;
        0 turns it off.
    :ivar min_whole_box_height_of_type: a box that neither the top nor the bottom edge of the image cuts shows the
        pallet's whole height (a face seen from the front is the type's height tall, seen from above taller): its
        height at the median depth of the rays that found the posed pallet's surface below this fraction of the
        type's height -> "size_mismatch". Tighter than `min_box_height_of_type`, it catches a focal length 2x too
        long (the box then spans half the height). On the validation frames correct poses' whole boxes span at
        least 0.99 of the type's height; 0 with `whole_box_edge_px` inf turns the whole-height test off.
    :ivar whole_box_edge_px: a whole box is held to the type's whole height less this many of the box's pixels
        (its edges are a pixel or two off), and never to less than `min_whole_box_height_of_type`: a 60 px tall box
        to 0.95 of the height, a 15 px one to 0.8. inf leaves `min_whole_box_height_of_type` alone. On the
        validation frames correct poses' whole boxes pass at 3 px while a focal length 2x too long no longer
        keeps a pose there (docs/experiments/structure-check.md).
    :ivar border_px: a box edge within this many pixels of the image's edge is cut by it.
    :ivar max_box_size_of_diameter: the box's metric width or height above this multiple of the type's diameter
        -> "size_mismatch" (depth scale too large, focal length too short).
    :ivar min_edge_auc: with the colour image, the AUC of colour differences across depth jumps of the grid against
        colour differences elsewhere, below this -> "depth_image_mismatch" (the depth is not this image's); 0 turns
        it off, the default: on stereo-noisy depth (D435-like, 3-5 m) true pallets' depth edges are too ragged,
        and 0.58 rejected 4 of 100 correct poses of the indoor-noisy test set (0.52: 1). With clean registered
        depth, 0.58 refuses most poses on another frame's depth (docs/structure-check.md).
    :ivar min_edge_pairs: the edge test needs at least this many neighbour pairs with a depth jump and as many
        without (else no evidence either way).
    :ivar min_registration_peak: with the colour image, the frame-level registration test (`registration.py`): over
        the frame's candidates' boxes, the edge AUC of the depth as given (AUC(0)) minus the largest edge AUC of the
        depth shifted by `registration_shift_px` along rows and columns. Below this, with AUC(0) below
        `registered_edge_auc`, every candidate of the frame -> "depth_image_mismatch" (another frame's depth, depth
        not registered to the image). Over ground-truth boxes of the validation and test frames a frame's own depth
        peaks at 0.06 or more (median about 0.2), another frame's at about -0.03 (median); 0.03 keeps twice the
        margin to the lowest own-depth peak (docs/structure-check.md); 0 turns it off.
    :ivar registered_edge_auc: a frame whose AUC(0) is at least this counts as registered whatever its peak (the
        depth's edges lie on the image's so clearly that a repeating scene, similar at the shift, cannot explain it).
    :ivar registration_weak_edge_auc: a frame whose AUC(0) is below this (its depth's edges barely follow the
        image's; 0.5 is chance) needs twice `min_registration_peak`. Another frame's depth from a scene much like
        this one (a row of pallets on a rack beam at the same range) can peak just above the threshold; a frame's
        own depth had AUC(0) of at least 0.646 over the candidates of the validation and forklift test frames
        (docs/structure-check.md); 0 turns it off.
    :ivar registration_min_jump_fraction: a frame whose pairs with valid depth around its candidates (at least
        `registration_min_pairs` of them, with as many colour edges) jump in fewer than this fraction -> the
        candidates tested "depth_image_mismatch": the depth is flat where the image shows a scene (a wall's depth, a
        depth stuck at one value; the depth's proposals are not tested and stand where it is not flat). The frame's
        own depth jumps in at least 0.0043 of its pairs on the validation and test frames; 0 turns it off.
    :ivar registration_shift_px: the depth's shift against the image for the registration peak, pixels (well beyond
        the few pixels by which stereo depth edges stray from the image's).
    :ivar registration_pair_px: pixels between the two pixels of a pair in the registration test.
    :ivar registration_blur_px: the registration test box-filters the colour image over this many pixels first, so
        sensor noise on a dark image does not drown weak edges (1: not at all).
    :ivar registration_margin_of_box: each candidate's box is dilated by this fraction of its width and height on each
        side for the registration test (the pallet's outline and its surroundings hold the depth edges).
    :ivar registration_samples: the registration test reads a grid of at most about this many pixels (its cost).
    :ivar registration_min_pairs: the registration test needs at least this many jumping pairs, as many other pairs
        and as many colour edges (else no evidence either way: no depth, a flat scene, a constant or dark image).
    :ivar registration_colour_edge: a pair whose colour difference (sum of absolute RGB differences, 0-765) is at
        least this is a colour edge.
    :ivar replace_min_agreement: with several pallet types, a type other than a detection's first replaces it only
        when its refined pose's agreement is at least this (`stage_type.py`): carton stacks that no pallet type
        explains well are otherwise given the look-alike type that explains them least badly (closed decks,
        blocks). Chosen with `replace_min_open_fraction` on the pallet-free frames of seeds 9100 and 9200 and
        forklift-approach frames of seed 8014 (docs/experiments/pallet-types.md); 0 turns it off.
    :ivar replace_min_open_fraction: the same for the pose's open fraction (a pallet shows its pockets open).
    :ivar frame_size_veto: when at least this many candidates of a frame fail the metric-size test, every candidate
        of the frame -> "size_mismatch" (the depth scale or the focal length is the frame's, so wrong for all of
        them); 0 turns it off, the default.
    :ivar frame_size_majority: when the candidates of a frame that fail the metric-size test outnumber those whose
        whole box (cut by neither the image's top nor its bottom edge) passes it, every candidate of the frame ->
        "size_mismatch". A box cut by the image's edge cannot show a wrong focal length by its height, but the
        frame's other pallets can. Off by default: a detector that often boxes what is no pallet (on real
        photographs about 4 boxes in 10) makes frames whose false boxes, failing the size test, outnumber the
        true pallets, which would then lose their poses too.
    :ivar frame_size_vouched: when candidates of a frame fail the metric-size test and are at least as many as those
        whose whole box passes the whole structure check (the pallets that vouch for the frame's depth scale and
        focal length), every candidate of the frame -> "size_mismatch". Stricter than `frame_size_majority`: a box
        that fails the structure check vouches for nothing, and a tie refuses. A focal length 2x too long leaves
        pallets cut by the image's edge or seen from above, whose size cannot show it, beside others that fail
        the size test; in a correct frame a box failing the size test (a thin false box, a pallet under a
        low-hanging load) stands beside more pallets that pass. Frames with a vehicle calibration are left to the
        floor check, which sees a wrong scale or focal length as a floor at the wrong height
        (`calibration.CalibrationMonitor`): in the forklift's views rack beams in striped or chequered paint are
        boxed in thin strips that fail the size test, as many as the pallets beside them (docs/structure-check.md).
        False turns it off.
    """

    grid: int = 32
    tol_m: float = 0.02
    tol_quad_per_m: float = 0.004
    min_evidence: int = 40
    min_agreement: float = 0.6
    min_agreement_levelled: float = 0.65
    min_opening_evidence: int = 8
    min_open_fraction: float = 0.15
    min_pocket_evidence: int = 12
    min_pocket_open_fraction: float = 0.3
    max_pocket_range_m: float = 6.0
    min_box_cover: float = 0.6
    min_box_solid: float = 0.3
    min_seen_iou: float = 0.1
    max_see_through_cut: float = 0.2
    max_see_through_beyond_box: float = 0.05
    beyond_box_margin: float = 0.1
    max_tilt_deg: float = 25.0
    min_box_height_of_type: float = 0.4
    min_whole_box_height_of_type: float = 0.8
    whole_box_edge_px: float = 3.0
    border_px: float = 3.0
    max_box_size_of_diameter: float = 3.0
    min_edge_auc: float = 0.0
    min_edge_pairs: int = 5
    min_registration_peak: float = 0.03
    registered_edge_auc: float = 0.85
    registration_weak_edge_auc: float = 0.65
    registration_min_jump_fraction: float = 0.001
    registration_shift_px: int = 24
    registration_pair_px: int = 3
    registration_blur_px: int = 3
    registration_margin_of_box: float = 0.5
    registration_samples: int = 16384
    registration_min_pairs: int = 50
    registration_colour_edge: int = 30
    replace_min_agreement: float = 0.7
    replace_min_open_fraction: float = 0.6
    frame_size_veto: int = 0
    frame_size_majority: bool = False
    frame_size_vouched: bool = True

    def __post_init__(self) -> None:
        if int(self.grid) < 4:
            raise ValueError(f"grid must be >= 4, got {self.grid}")
        for name in ("tol_m", "tol_quad_per_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.tol_m > 0:
            raise ValueError(f"tol_m must be positive, got {self.tol_m}")
        for name in ("min_agreement", "min_agreement_levelled", "min_open_fraction", "min_pocket_open_fraction",
                     "min_box_cover", "min_box_solid",
                     "min_seen_iou", "max_see_through_cut", "max_see_through_beyond_box", "min_edge_auc",
                     "min_box_height_of_type",
                     "min_whole_box_height_of_type",
                     "replace_min_agreement", "replace_min_open_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not self.beyond_box_margin >= 0:
            raise ValueError(f"beyond_box_margin must be >= 0, got {self.beyond_box_margin}")
        if int(self.min_evidence) < 1 or int(self.min_opening_evidence) < 1 or int(self.min_pocket_evidence) < 1:
            raise ValueError("min_evidence, min_opening_evidence and min_pocket_evidence must be >= 1")
        if not self.max_pocket_range_m >= 0:
            raise ValueError(f"max_pocket_range_m must be >= 0, got {self.max_pocket_range_m}")
        if not self.max_box_size_of_diameter > 0:
            raise ValueError(f"max_box_size_of_diameter must be positive, got {self.max_box_size_of_diameter}")
        if not self.border_px >= 0:
            raise ValueError(f"border_px must be >= 0, got {self.border_px}")
        if not self.whole_box_edge_px >= 0:
            raise ValueError(f"whole_box_edge_px must be >= 0 (inf: off), got {self.whole_box_edge_px}")
        if int(self.min_edge_pairs) < 1:
            raise ValueError(f"min_edge_pairs must be >= 1, got {self.min_edge_pairs}")
        if not 0.0 < self.max_tilt_deg <= 180.0:
            raise ValueError(f"max_tilt_deg must be in (0, 180], got {self.max_tilt_deg}")
        for name in ("min_registration_peak", "registered_edge_auc", "registration_weak_edge_auc",
                     "registration_min_jump_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("registration_shift_px", "registration_pair_px", "registration_blur_px", "registration_samples",
                     "registration_min_pairs"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.registration_margin_of_box >= 0:
            raise ValueError(f"registration_margin_of_box must be >= 0, got {self.registration_margin_of_box}")
        if not 0 <= int(self.registration_colour_edge) <= 765:
            raise ValueError(f"registration_colour_edge must be in [0, 765], got {self.registration_colour_edge}")
        if int(self.frame_size_veto) < 0:
            raise ValueError(f"frame_size_veto must be >= 0 (0: off), got {self.frame_size_veto}")


@dataclass(frozen=True)
class StructureScore:
    """Structure evidence of one posed pallet (counts are rays of the grid).

    :ivar solid: rays where the model expects a surface and the depth has one there.
    :ivar see_through: rays where the model expects a surface and the depth lies behind it.
    :ivar open: rays through an opening of the model whose depth lies behind the entry.
    :ivar closed: rays through an opening with a surface at the entry.
    :ivar agreement: (solid + open) / (solid + see_through + open + closed), 0 without evidence.
    :ivar open_fraction: (open + mouth_open) / (open + closed + mouth_open + mouth_closed), 1 without openings in
        view.
    :ivar box_cover: fraction of the detector's box inside the posed model's projected box.
    :ivar box_solid: of the rays inside the detector's box that hit the model and find a surface at it or behind
        it, the fraction that find its surface (NaN when there are none: no evidence either way).
    :ivar seen_iou: IoU of the detector's box with the box around the rays that found the pallet's surface (NaN
        when none did).
    :ivar tilt_deg: angle between the pallet's z axis and the up vector (NaN without one).
    :ivar box_size_m: (width, height) of the detector's box in metres at the median depth inside it (NaN without
        depth there).
    :ivar box_cut: the image's top or bottom edge cuts the detector's box (its height is then not the pallet's).
    :ivar whole_height_m: the height of a box that is not cut, in metres at the median depth of the rays that found
        the posed pallet's surface (NaN for a cut box or without such rays).
    :ivar edge_auc: AUC of colour differences across depth jumps against those elsewhere (NaN without a colour image
        or too few pairs).
    :ivar reason: "" when accepted, else one of "size_mismatch", "depth_image_mismatch", "structure_unseen",
        "structure_mismatch", "see_through_cut", "see_through_beyond_box", "openings_closed", "pockets_closed",
        "box_mismatch", "tilted".
    :ivar mouth_open: rays that enter through an opening and meet a board or block deeper inside, whose depth lies
        behind the entry.
    :ivar mouth_closed: such rays with a surface at the entry.
    :ivar pocket_open: the open fraction of the most open pocket with enough evidence (`pocket_open_fractions`;
        NaN when no pocket has, or the pallet is farther than `StructureParams.max_pocket_range_m`).
    :ivar see_through_beyond: see-through rays outside the detector's box widened by
        `StructureParams.beyond_box_margin` (`max_see_through_beyond_box`).
    """

    solid: int
    see_through: int
    open: int
    closed: int
    agreement: float
    open_fraction: float
    box_cover: float
    box_solid: float
    seen_iou: float
    tilt_deg: float
    box_size_m: tuple[float, float]
    edge_auc: float
    reason: str
    box_cut: bool = False
    whole_height_m: float = float("nan")
    mouth_open: int = 0
    mouth_closed: int = 0
    pocket_open: float = float("nan")
    see_through_beyond: int = 0

    @property
    def ok(self) -> bool:
        return self.reason == ""


def cast_rays_boxes(origin: np.ndarray, dirs: np.ndarray, boxes_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays with a union of axis-aligned boxes, and where they enter the boxes' bounding box.

    Rays are `origin + s * dirs[i]`, s > 0; with `dirs` scaled to unit camera z, s is the camera depth.

    :param origin: (n, 3) ray origins, one per batch item, in the boxes' frame.
    :param dirs: (n, r, 3) ray directions in the same frame.
    :param boxes_m: (k, 2, 3) min/max corners.
    :return: (n, r) parameter of the first box hit (inf when none) and (n, r) parameter where the ray enters the
        boxes' bounding box (inf when it misses it).
    """
    boxes = np.asarray(boxes_m, dtype=np.float64)
    o = np.asarray(origin, dtype=np.float64)                                    # (n, 3)
    d = np.asarray(dirs, dtype=np.float64)                                      # (n, r, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(np.abs(d) > 1e-12, 1.0 / d, _BIG)

    def slab(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """(n, r) entry parameter of the rays into the first of (k, 3) boxes lo..hi (inf: none hit)."""
        # arrays are (n, k, r) and the three axes are combined one by one: numpy reduces slowly over a short
        # last axis (3 axes, 20 boxes), and quickly over a middle one
        near = far = None
        for c in range(3):
            inv_c = inv[:, None, :, c]                                          # (n, 1, r)
            t1 = (lo[None, :, c, None] - o[:, None, None, c]) * inv_c           # (n, k, r)
            t2 = (hi[None, :, c, None] - o[:, None, None, c]) * inv_c
            lo_t, hi_t = np.minimum(t1, t2), np.maximum(t1, t2)
            near = lo_t if near is None else np.maximum(near, lo_t, out=near)
            far = hi_t if far is None else np.minimum(far, hi_t, out=far)
        hit = (near <= far) & (far > 0)
        return np.where(hit, np.maximum(near, 0.0), np.inf).min(1)

    t_box = slab(boxes[:, 0], boxes[:, 1])                                     # (n, r)
    t_bbox = slab(boxes[:, 0].min(0, keepdims=True), boxes[:, 1].max(0, keepdims=True))   # (n, r)
    return t_box, t_bbox


def pocket_open_fractions(origin: np.ndarray, dirs: np.ndarray, t_bbox: np.ndarray, boxes_m: np.ndarray,
                          open_rays: np.ndarray, closed_rays: np.ndarray, min_evidence: int) -> np.ndarray:
    """Per pose, the open fraction of its most open pocket: the rays' entry points into the model's bounding box,
    on its four side faces, each face cut in two at its centre (a pocket and its blocks, on a pallet with two
    entries per side); the top and bottom faces are no pocket.

    :param origin: (n, 3) camera centre in each pose's pallet frame. :param dirs: (n, r, 3) the rays, scaled so
        the parameter is the camera depth. :param t_bbox: (n, r) where each ray enters the bounding box (inf: never).
    :param boxes_m: (k, 2, 3) the model's boxes. :param open_rays, closed_rays: (n, r) bool, rays judging an opening
        or a mouth open / closed.
    :param min_evidence: (>= 1) pockets with fewer open + closed rays are not judged.
    :return: (n,) the largest open fraction among the judged pockets, NaN where none is judged.
    """
    boxes = np.asarray(boxes_m, dtype=np.float64)
    lo, hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
    centre = (lo + hi) / 2
    judged = open_rays | closed_rays
    entry = origin[:, None, :] + np.where(judged, t_bbox, 0.0)[..., None] * dirs   # (n, r, 3); judged: t_bbox finite
    # the face each ray enters through: the nearest of the six planes (-x, +x, -y, +y, -z, +z)
    face = np.abs(np.concatenate([entry - lo, entry - hi], -1))[..., [0, 3, 1, 4, 2, 5]].argmin(-1)
    lateral = np.where(face < 2, entry[..., 1] - centre[1], entry[..., 0] - centre[0])
    cell = np.where(face < 4, 2 * face + (lateral >= 0), -1)                  # 8 pockets, -1: top or bottom face
    use = judged & (cell >= 0)
    n = len(entry)
    index = (np.arange(n)[:, None] * 8 + cell)[use]
    n_open = np.bincount(index, weights=open_rays[use], minlength=8 * n).reshape(n, 8)
    n_all = np.bincount(index, minlength=8 * n).reshape(n, 8)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(n_all >= int(min_evidence), n_open / n_all, -1.0)
    best = frac.max(1) if n else np.zeros(0)
    return np.where(best >= 0, best, np.nan)


def projected_bounds(T_cam_pallet: np.ndarray, lo: np.ndarray, hi: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n, 4) xyxy image box of each pose's model bounding box lo..hi ((n, 3) each; corners behind the camera
    dropped)."""
    pick = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], bool)       # (8, 3): hi where True
    corners = np.where(pick[None], hi[:, None, :], lo[:, None, :])                          # (n, 8, 3)
    pc = corners @ T_cam_pallet[:, :3, :3].transpose(0, 2, 1) + T_cam_pallet[:, None, :3, 3]   # (n, 8, 3)
    z = pc[..., 2]
    front = z > 1e-3
    zs = np.where(front, z, 1.0)
    u = np.where(front, K[0, 0] * pc[..., 0] / zs + K[0, 2], np.nan)
    v = np.where(front, K[1, 1] * pc[..., 1] / zs + K[1, 2], np.nan)
    with np.errstate(invalid="ignore"):
        out = np.stack([np.nanmin(u, 1), np.nanmin(v, 1), np.nanmax(u, 1), np.nanmax(v, 1)], 1)
    return out


@dataclass(frozen=True)
class _Rays:
    """The grid of rays over each posed model's projected bounding box, and what the depth shows along them.

    proj (n, 4) the projected box, valid_proj (n,) whether it is in the image; u, v (n, R) the rays' pixel
    positions, ui, vi (n, R) the pixels read; z_obs (n, R) their depth; origin (n, 3) and dirs (n, R, 3) the rays
    in the pallet frame (parameter = camera depth); t_box, t_bbox (n, R) where they hit a box / enter the bounding
    box; the ray classes (n, R) bool: solid, see_through, opened, closed, mouth_open, mouth_closed.
    """

    proj: np.ndarray
    valid_proj: np.ndarray
    u: np.ndarray
    v: np.ndarray
    ui: np.ndarray
    vi: np.ndarray
    z_obs: np.ndarray
    origin: np.ndarray
    dirs: np.ndarray
    t_box: np.ndarray
    t_bbox: np.ndarray
    solid: np.ndarray
    see_through: np.ndarray
    opened: np.ndarray
    closed: np.ndarray
    mouth_open: np.ndarray
    mouth_closed: np.ndarray

    def agreement(self) -> tuple[np.ndarray, np.ndarray]:
        """(n,) agreement: (solid + open) / (solid + see-through + open + closed), 0 without evidence; (n,) open
        fraction of the openings and mouths judged, 1 when none is."""
        s, st, op, cl, mo, mc = (m.sum(1) for m in (self.solid, self.see_through, self.opened, self.closed,
                                                     self.mouth_open, self.mouth_closed))
        evidence, judged = s + st + op + cl, op + cl + mo + mc
        agreement = np.where(evidence > 0, (s + op) / np.maximum(evidence, 1), 0.0)
        open_fraction = np.where(judged > 0, (op + mo) / np.maximum(judged, 1), 1.0)
        return agreement, open_fraction


class BoxSets:
    """The boards and blocks of several pallet types, checked and laid out once (a type choice casts rays against
    them twice a frame): per set its (k, 2, 3) min / max corners (`sets`), its bounding box (`lo`, `hi`, (t, 3)) and
    its place in one concatenated (K, 2, 3) array (`flat[start[j]:start[j] + count[j]]`), the compiled kernel's form.

    :param box_sets: per pallet type, its (k, 2, 3) boxes, pallet frame, metres (finite, k >= 1).
    """

    def __init__(self, box_sets) -> None:
        self.sets = tuple(_check_box_set(b, f"box_sets[{i}]") for i, b in enumerate(box_sets))
        if not self.sets:
            raise ValueError("box_sets must hold at least one set of boxes")
        self.lo = np.stack([b[:, 0].min(0) for b in self.sets])
        self.hi = np.stack([b[:, 1].max(0) for b in self.sets])
        self.count = np.array([len(b) for b in self.sets], dtype=np.int64)
        self.start = np.concatenate([[0], np.cumsum(self.count)[:-1]]).astype(np.int64)
        self.flat = np.ascontiguousarray(np.concatenate(self.sets))

    def __len__(self) -> int:
        return len(self.sets)


def _cast(origin: np.ndarray, dirs: np.ndarray, sets: BoxSets, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`cast_rays_boxes` of poses each with the boxes `sets.sets[which[i]]`: in the compiled kernel where it is
    built, else in numpy one box set at a time (the same values)."""
    if kernels.available() and sets.count.max() <= kernels.MAX_BOXES:
        return kernels.cast_rays(origin, dirs, sets.flat, sets.start[which], sets.count[which])
    t_box, t_bbox = np.empty(dirs.shape[:2]), np.empty(dirs.shape[:2])
    for j in np.unique(which):
        mine = which == j
        t_box[mine], t_bbox[mine] = cast_rays_boxes(origin[mine], dirs[mine], sets.sets[int(j)])
    return t_box, t_bbox


def _cast_grid(T: np.ndarray, sets: BoxSets, which: np.ndarray, depth: np.ndarray, K: np.ndarray,
               params: StructureParams) -> _Rays:
    """The structure check's rays for poses T (n, 4, 4), pose i with the boxes `sets.sets[which[i]]`, and their
    classes (the module's docstring)."""
    h, w = depth.shape
    n = len(T)
    proj = projected_bounds(T, sets.lo[which], sets.hi[which], K)
    clip = np.stack([np.clip(proj[:, 0], 0, w - 1), np.clip(proj[:, 1], 0, h - 1),
                     np.clip(proj[:, 2], 0, w - 1), np.clip(proj[:, 3], 0, h - 1)], 1)
    valid_proj = np.all(np.isfinite(proj), 1) & (clip[:, 2] > clip[:, 0]) & (clip[:, 3] > clip[:, 1])
    clip = np.where(valid_proj[:, None], clip, 0.0)

    # a grid of pixel centres over each projected box (clipped to the image)
    g = (np.arange(params.grid) + 0.5) / params.grid
    gu = clip[:, 0:1] + g[None] * (clip[:, 2:3] - clip[:, 0:1])                 # (n, G)
    gv = clip[:, 1:2] + g[None] * (clip[:, 3:4] - clip[:, 1:2])
    u = np.repeat(gu[:, None, :], params.grid, 1).reshape(n, -1)                # (n, G*G)
    v = np.repeat(gv[:, :, None], params.grid, 2).reshape(n, -1)
    ui = np.clip(np.round(u).astype(np.int64), 0, w - 1)
    vi = np.clip(np.round(v).astype(np.int64), 0, h - 1)
    z_obs = depth[vi, ui].astype(np.float64)                                    # (n, R)

    # rays in the pallet frame, scaled so the parameter is the camera depth
    # through the centres of the pixels whose depth is read
    d_cam = np.stack([(ui - K[0, 2]) / K[0, 0], (vi - K[1, 2]) / K[1, 1], np.ones(ui.shape)], -1)
    R = T[:, :3, :3]
    dirs = d_cam @ R                                    # R^T d for each ray: (n, R, 3)
    origin = -np.einsum("nji,nj->ni", R, T[:, :3, 3])   # camera centre in the pallet frame
    t_box, t_bbox = _cast(origin, dirs, sets, which)

    known = z_obs > 0
    z_ref = np.where(np.isfinite(t_box), t_box, t_bbox)
    tol = params.tol_m + params.tol_quad_per_m * np.where(np.isfinite(z_ref), z_ref, 0.0) ** 2
    hit = np.isfinite(t_box) & known
    gap = ~np.isfinite(t_box) & np.isfinite(t_bbox) & known
    # entered through an opening, a board or block deeper in: the ray judges the opening's mouth (seen from a little
    # below or aside, a pocket's rays meet the blocks and bottom boards inside; a carton face where the pallet's front
    # should be closes every mouth)
    mouth = hit & (t_box > t_bbox + 2 * tol)
    return _Rays(proj, valid_proj, u, v, ui, vi, z_obs, origin, dirs, t_box, t_bbox,
                 solid=hit & (np.abs(z_obs - t_box) <= tol), see_through=hit & (z_obs > t_box + tol),
                 opened=gap & (z_obs > t_bbox + tol), closed=gap & (np.abs(z_obs - t_bbox) <= tol),
                 mouth_open=mouth & (z_obs > t_bbox + tol), mouth_closed=mouth & (np.abs(z_obs - t_bbox) <= tol))


def _check_box_set(boxes_m: np.ndarray, name: str = "boxes_m") -> np.ndarray:
    boxes = np.asarray(boxes_m, dtype=np.float64)
    if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or len(boxes) == 0 or not np.all(np.isfinite(boxes)):
        raise ValueError(f"{name} must be a finite (k, 2, 3) array with k >= 1, got shape {boxes.shape}")
    return boxes


def structure_agreement(T_cam_pallet: np.ndarray, box_sets: BoxSets | list[np.ndarray] | tuple[np.ndarray, ...],
                        which: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                        params: StructureParams = StructureParams()) -> tuple[np.ndarray, np.ndarray]:
    """The structure check's agreement and open fraction (`StructureScore.agreement`, `.open_fraction`) of poses of
    several pallet types in one pass, without its other tests: what the type choice compares.

    :param T_cam_pallet: (n, 4, 4) poses, metres. :param box_sets: per pallet type, its (k, 2, 3) boards and blocks,
        pallet frame, metres (or a `BoxSets` of them, prepared once). :param which: (n,) each pose's type (an index
        into `box_sets`).
    :param depth_m: (H, W) float metres, 0 = no data. :param K: 3x3 intrinsics. :param params: the ray grid and
        tolerances.
    :return: (n,) agreement, (n,) open fraction: the values `structure_check` gives each pose with its type's boxes.
    """
    K = check_K(K)
    T = np.asarray(T_cam_pallet, dtype=np.float64).reshape(-1, 4, 4)
    sets = box_sets if isinstance(box_sets, BoxSets) else BoxSets(box_sets)
    which = np.asarray(which, dtype=np.int64).reshape(-1)
    if len(which) != len(T):
        raise ValueError(f"{len(T)} poses but {len(which)} type indexes")
    if len(T) and (which.min() < 0 or which.max() >= len(sets)):
        raise ValueError(f"which must index the {len(sets)} box sets, got {which.min()}..{which.max()}")
    if not np.all(np.isfinite(T)):
        raise ValueError("T_cam_pallet must be finite")
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth.shape}")
    if len(T) == 0:
        return np.zeros(0), np.zeros(0)
    return _cast_grid(T, sets, which, depth, K, params).agreement()


def box_metric_size(boxes_xyxy: np.ndarray, depth_m: np.ndarray, K: np.ndarray, samples: int = 16) -> np.ndarray:
    """Metric (width, height) of detector boxes at the median depth inside each (a grid of samples x samples pixels).

    :param boxes_xyxy: (n, 4) image pixels. :param depth_m: (H, W) metres, 0 = no data. :param K: 3x3.
    :return: (n, 2) metres; NaN where the box holds no valid depth.
    """
    h, w = depth_m.shape
    det = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    g = (np.arange(samples) + 0.5) / samples
    u = np.clip(np.round(det[:, 0:1] + g[None] * (det[:, 2:3] - det[:, 0:1])), 0, w - 1).astype(np.int64)
    v = np.clip(np.round(det[:, 1:2] + g[None] * (det[:, 3:4] - det[:, 1:2])), 0, h - 1).astype(np.int64)
    z = depth_m[v[:, :, None], u[:, None, :]].reshape(len(det), -1).astype(np.float64)   # (n, samples**2)
    z_med = np.full(len(det), np.nan)
    for i, zi in enumerate(z):
        zi = zi[zi > 0]
        if len(zi):
            z_med[i] = np.median(zi)
    return np.stack([(det[:, 2] - det[:, 0]) * z_med / K[0, 0], (det[:, 3] - det[:, 1]) * z_med / K[1, 1]], 1)


def _auc(values: np.ndarray, positive: np.ndarray) -> float:
    """Probability that a positive's value exceeds a negative's (ties count half): the Mann-Whitney AUC."""
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    _, inverse, counts = np.unique(values, return_inverse=True, return_counts=True)
    midrank = np.cumsum(counts) - (counts - 1) / 2.0                  # 1-based mean rank of each distinct value
    return float((midrank[inverse][positive].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def edge_agreement(z_obs: np.ndarray, colour: np.ndarray, tol: np.ndarray, min_pairs: int) -> np.ndarray:
    """Do the depth's jumps coincide with the colour image's edges? One AUC per pose over a grid of rays.

    Neighbouring rays (along rows and columns of the grid) with valid depth form pairs; a pair *jumps* when the
    depths differ by more than twice the larger tolerance. The AUC compares the colour differences (sum of absolute
    RGB differences) of jumping pairs with those of the other pairs. Where the grid is finer than the image's pixels
    (a small or far pallet), neighbours read the same pixel: such pairs never jump and differ by 0, which lifts the
    AUC above 0.5 even on unrelated images, so the test is less strict on small pallets.

    :param z_obs: (n, G, G) observed depth at the rays, metres, 0 = no data.
    :param colour: (n, G, G, 3) colour at the same pixels.
    :param tol: (n, G, G) depth tolerance per ray, metres.
    :param min_pairs: fewer jumping or fewer other pairs -> NaN (no evidence).
    :return: (n,) AUC in [0, 1] or NaN.
    """
    colour = colour.astype(np.float64)
    out = np.full(len(z_obs), np.nan)
    pairs = []
    for a, b in (((slice(None), slice(None), slice(1, None)), (slice(None), slice(None), slice(None, -1))),
                 ((slice(None), slice(1, None)), (slice(None), slice(None, -1)))):
        valid = (z_obs[a] > 0) & (z_obs[b] > 0)
        jump = np.abs(z_obs[a] - z_obs[b]) > 2.0 * np.maximum(tol[a], tol[b])
        diff = np.abs(colour[a] - colour[b]).sum(-1)
        pairs.append((valid.reshape(len(z_obs), -1), jump.reshape(len(z_obs), -1), diff.reshape(len(z_obs), -1)))
    valid, jump, diff = (np.concatenate(x, 1) for x in zip(*pairs))
    for i in range(len(z_obs)):
        d, j = diff[i][valid[i]], jump[i][valid[i]]
        if j.sum() >= min_pairs and (~j).sum() >= min_pairs:
            out[i] = _auc(d, j)
    return out


def structure_check(T_cam_pallet: np.ndarray, boxes_m: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                    boxes_xyxy: np.ndarray, params: StructureParams = StructureParams(),
                    up_cam: np.ndarray | None = None, rgb: np.ndarray | None = None) -> list[StructureScore]:
    """Structure evidence for posed pallets of one type in one frame.

    :param T_cam_pallet: (n, 4, 4) poses, metres.
    :param boxes_m: (k, 2, 3) the type's boards/blocks as min/max corners, pallet frame, metres.
    :param depth_m: (H, W) float metres, 0 = no data.
    :param K: 3x3 intrinsics.
    :param boxes_xyxy: (n, 4) the detector's boxes, image pixels.
    :param params: thresholds.
    :param up_cam: optional (3,) unit up direction in the camera frame (from a calibration); None skips the tilt test.
    :param rgb: optional (H, W, 3) colour image registered to `depth_m`; None skips the edge test.
    :return: one `StructureScore` per pose.
    """
    K = check_K(K)
    T = np.asarray(T_cam_pallet, dtype=np.float64).reshape(-1, 4, 4)
    boxes = _check_box_set(boxes_m)
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (H, W), got shape {depth.shape}")
    det = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    if len(det) != len(T):
        raise ValueError(f"{len(T)} poses but {len(det)} boxes")
    if not np.all(np.isfinite(T)):
        raise ValueError("T_cam_pallet must be finite")
    if rgb is not None and (np.ndim(rgb) != 3 or np.shape(rgb)[:2] != depth.shape or np.shape(rgb)[2] != 3):
        raise ValueError(f"rgb must be (H, W, 3) like depth_m {depth.shape}, got shape {np.shape(rgb)}")
    if len(T) == 0:
        return []
    h = depth.shape[0]

    rays = _cast_grid(T, BoxSets([boxes]), np.zeros(len(T), np.int64), depth, K, params)
    proj, valid_proj, u, v, ui, vi, z_obs = rays.proj, rays.valid_proj, rays.u, rays.v, rays.ui, rays.vi, rays.z_obs
    origin, dirs, t_bbox, R = rays.origin, rays.dirs, rays.t_bbox, T[:, :3, :3]
    solid, see_through, opened, closed = rays.solid, rays.see_through, rays.opened, rays.closed
    mouth_open, mouth_closed = rays.mouth_open, rays.mouth_closed

    pocket_open = pocket_open_fractions(origin, dirs, t_bbox, boxes, opened | mouth_open, closed | mouth_closed,
                                        int(params.min_pocket_evidence))
    pocket_open[np.linalg.norm(T[:, :3, 3], axis=1) > params.max_pocket_range_m] = np.nan     # not judged

    # does the depth belong to the image? the box's metric size, the depth's edges against the colour's
    extent = boxes[:, 1].max(0) - boxes[:, 0].min(0)
    size_m = box_metric_size(det, depth, K)
    # a whole box (not cut by the image's top or bottom edge) at the depth where the rays found the posed pallet's
    # surface (an occluder nearer than the pallet inside the box does not shrink it): the pallet's whole height
    box_cut = (det[:, 1] < params.border_px) | (det[:, 3] > h - 1 - params.border_px)
    n_solid = solid.sum(1)
    z_solid = np.array([np.median(z_obs[i][solid[i]]) if n_solid[i] else np.nan for i in range(len(T))])
    whole_height_m = np.where(box_cut, np.nan, (det[:, 3] - det[:, 1]) * z_solid / K[1, 1])
    # the fraction of the type's height a whole box must span: all of it less a few of the box's pixels
    box_h_px = np.maximum(det[:, 3] - det[:, 1], 1e-9)
    whole_fraction = np.maximum(params.min_whole_box_height_of_type, 1.0 - params.whole_box_edge_px / box_h_px)
    # a box cut by the image's edge whose size cannot show a focal length 2x too long (cut at the top or bottom, or
    # cut aside and less than twice the whole height's bound tall): its pose must not see through its own boards
    cut_aside = (det[:, 0] < params.border_px) | (det[:, 2] > depth.shape[1] - 1 - params.border_px)
    with np.errstate(invalid="ignore"):
        size_unsure = box_cut | (cut_aside & (whole_height_m < 2.0 * params.min_whole_box_height_of_type
                                              * extent.min()))
        wrong_size = (size_m[:, 1] < params.min_box_height_of_type * extent.min()) \
            | (size_m.max(1) > params.max_box_size_of_diameter * np.linalg.norm(extent)) \
            | (whole_height_m < whole_fraction * extent.min())
    g2 = (len(T), params.grid, params.grid)
    if rgb is None:
        edge_auc = np.full(len(T), np.nan)
    else:
        tol_obs = params.tol_m + params.tol_quad_per_m * z_obs ** 2
        edge_auc = edge_agreement(z_obs.reshape(g2), np.asarray(rgb)[vi, ui].reshape(*g2, 3), tol_obs.reshape(g2),
                                  int(params.min_edge_pairs))

    # a whole box (no side cut by the image's edge) holds the whole pallet seen: the pose must not stand in free
    # space beyond it
    mu = params.beyond_box_margin * (det[:, 2:3] - det[:, 0:1])
    mv = params.beyond_box_margin * (det[:, 3:4] - det[:, 1:2])
    beyond = (u < det[:, 0:1] - mu) | (u > det[:, 2:3] + mu) | (v < det[:, 1:2] - mv) | (v > det[:, 3:4] + mv)
    st_beyond = (see_through & beyond).sum(1)
    whole_box = ~box_cut & ~cut_aside

    in_box = (u >= det[:, 0:1]) & (u <= det[:, 2:3]) & (v >= det[:, 1:2]) & (v <= det[:, 3:4])
    box_hits = ((solid | see_through) & in_box).sum(1)       # an occluder in front is no evidence either way
    box_solid = np.where(box_hits > 0, (solid & in_box).sum(1) / np.maximum(box_hits, 1), np.nan)

    # the box around the rays that found the pallet's surface, against the detector's box
    su0 = np.where(solid, u, np.inf).min(1)
    sv0 = np.where(solid, v, np.inf).min(1)
    su1 = np.where(solid, u, -np.inf).max(1)
    sv1 = np.where(solid, v, -np.inf).max(1)
    iw = np.maximum(0.0, np.minimum(det[:, 2], su1) - np.maximum(det[:, 0], su0))
    ih = np.maximum(0.0, np.minimum(det[:, 3], sv1) - np.maximum(det[:, 1], sv0))
    with np.errstate(invalid="ignore"):
        s_area = np.where(np.isfinite(su0), (su1 - su0) * (sv1 - sv0), 0.0)
        seen_iou = np.where(np.isfinite(su0), iw * ih / (s_area + (det[:, 2] - det[:, 0]) * (det[:, 3] - det[:, 1])
                                                         - iw * ih), np.nan)

    inter_w = np.maximum(0.0, np.minimum(det[:, 2], proj[:, 2]) - np.maximum(det[:, 0], proj[:, 0]))
    inter_h = np.maximum(0.0, np.minimum(det[:, 3], proj[:, 3]) - np.maximum(det[:, 1], proj[:, 1]))
    det_area = np.maximum((det[:, 2] - det[:, 0]) * (det[:, 3] - det[:, 1]), 1e-9)
    cover = np.where(valid_proj, np.nan_to_num(inter_w * inter_h) / det_area, 0.0)

    if up_cam is not None:
        up = np.asarray(up_cam, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-9:
            raise ValueError(f"up_cam must be a finite non-zero 3-vector, got {up_cam}")
        up = up / np.linalg.norm(up)
        # a symmetric pallet may come back upside down (z down): the face is as vertical either way
        tilt = np.degrees(np.arccos(np.clip(np.abs(R[:, :, 2] @ up), -1.0, 1.0)))
    else:
        tilt = np.full(len(T), np.nan)

    out = []
    for i in range(len(T)):
        s, st, op, cl = int(solid[i].sum()), int(see_through[i].sum()), int(opened[i].sum()), int(closed[i].sum())
        mo, mc = int(mouth_open[i].sum()), int(mouth_closed[i].sum())
        evidence = s + st + op + cl
        agreement = (s + op) / evidence if evidence else 0.0
        open_fraction = (op + mo) / (op + cl + mo + mc) if op + cl + mo + mc else 1.0
        if wrong_size[i]:
            reason = "size_mismatch"
        elif edge_auc[i] < params.min_edge_auc:     # NaN (no colour, too few pairs) compares False
            reason = "depth_image_mismatch"
        elif not valid_proj[i] or cover[i] < params.min_box_cover or box_solid[i] < params.min_box_solid \
                or seen_iou[i] < params.min_seen_iou:
            # NaN (no depth on the pallet at all) compares False: then the evidence count below decides
            reason = "box_mismatch"
        elif np.isfinite(tilt[i]) and tilt[i] > params.max_tilt_deg:
            reason = "tilted"
        elif evidence < params.min_evidence:
            reason = "structure_unseen"
        elif agreement < (params.min_agreement if up_cam is None else params.min_agreement_levelled):
            reason = "structure_mismatch"
        elif size_unsure[i] and st > params.max_see_through_cut * (s + st):
            reason = "see_through_cut"
        elif whole_box[i] and st_beyond[i] > params.max_see_through_beyond_box * (s + st):
            reason = "see_through_beyond_box"
        elif max(op + cl, mo + mc) >= params.min_opening_evidence and open_fraction < params.min_open_fraction:
            reason = "openings_closed"
        elif pocket_open[i] < params.min_pocket_open_fraction:     # NaN (no pocket judged) compares False
            reason = "pockets_closed"
        else:
            reason = ""
        out.append(StructureScore(s, st, op, cl, float(agreement), float(open_fraction), float(cover[i]),
                                  float(box_solid[i]), float(seen_iou[i]),
                                  float(tilt[i]), (float(size_m[i, 0]), float(size_m[i, 1])),
                                  float(edge_auc[i]), reason, bool(box_cut[i]),
                                  float(whole_height_m[i]), mo, mc, float(pocket_open[i]), int(st_beyond[i])))
    return out


def frame_size_rule(scores: list[StructureScore], params: StructureParams = StructureParams(),
                    calibrated: bool = False) -> str | None:
    """The frame-level size rule that refuses every candidate of a frame, given all its candidates' structure
    scores: "frame_size_veto" (at least `frame_size_veto` fail the metric-size test), "frame_size_majority" (those
    failing outnumber the whole boxes that pass it), "frame_size_vouched" (some fail it, and no fewer than the whole
    boxes that pass the whole check; only in a frame without a vehicle calibration, `calibrated` False), or None."""
    n_size = sum(sc.reason == "size_mismatch" for sc in scores)
    n_whole_sized = sum(sc.reason != "size_mismatch" and not sc.box_cut for sc in scores)
    n_whole_ok = sum(sc.ok and not sc.box_cut for sc in scores)
    if params.frame_size_veto > 0 and n_size >= params.frame_size_veto:
        return "frame_size_veto"
    if params.frame_size_majority and n_size > n_whole_sized:
        return "frame_size_majority"
    if params.frame_size_vouched and not calibrated and n_size > 0 and n_size >= n_whole_ok:
        return "frame_size_vouched"
    return None


def frame_registration(depth_m: np.ndarray, rgb: np.ndarray, boxes_xyxy: np.ndarray,
                       params: StructureParams = StructureParams()) -> tuple[RegistrationScore, bool]:
    """The frame-level registration test (`registration.py`) with the thresholds of `params`.

    :param depth_m: (H, W) metres, 0 = no data. :param rgb: (H, W, 3) uint8, the frame's colour image.
    :param boxes_xyxy: (n, 4) the boxes of all the frame's candidates, image pixels.
    :return: the frame's score and whether its depth is refused as not this image's (every candidate of the frame
        -> "depth_image_mismatch"; a flat depth only the candidates tested: `registration_verdict`); never refused
        without enough evidence or with `min_registration_peak` 0.
    """
    score = registration_score(depth_m, rgb, boxes_xyxy, shift_px=int(params.registration_shift_px),
                               pair_px=int(params.registration_pair_px),
                               margin_of_box=float(params.registration_margin_of_box),
                               max_samples=int(params.registration_samples), tol_m=params.tol_m,
                               tol_quad_per_m=params.tol_quad_per_m, min_pairs=int(params.registration_min_pairs),
                               colour_edge=int(params.registration_colour_edge),
                               blur_px=int(params.registration_blur_px))
    return score, bool(registration_verdict(score, params))


def registration_verdict(score: RegistrationScore, params: StructureParams = StructureParams()) -> str:
    """Why a frame's registration score refuses its depth with the thresholds of `params`: "mismatch" (the depth's
    edges do not lie on the image's: `RegistrationScore.mismatch`; every candidate is refused), "flat" (no step
    around the candidates tested: `RegistrationScore.flat`; those candidates are refused), or "" (not refused)."""
    if score.mismatch(params.min_registration_peak, params.registered_edge_auc, params.registration_weak_edge_auc):
        return "mismatch"
    if params.min_registration_peak > 0 \
            and score.flat(int(params.registration_min_pairs), params.registration_min_jump_fraction):
        return "flat"
    return ""
