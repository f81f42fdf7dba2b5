"""Type choice stage: which of the pallet types it may be is each candidate? (numpy only)

A detector trained on photographs that carry no type label has one class, "pallet", for every type of the
bundle; a detector with a class per type can still be unsure between look-alike types (its runner-up classes,
`EstimatorOptions.type_score_ratio`). The depth then tells the types apart, as their sizes and boards differ
(0.8 x 0.6 m to 1.22 x 1.02 m, blocks, stringers, legs, runners, closed decks). The pose network poses every type
in the same frame (the centre of its bounding box, x along the length, z up), so per candidate that may be of
several types (`Candidates.type_options`):

1. every such type is scored at the network's pose (a type smaller than the first also laid flush with the first
   type's faces, `face_starts`, its best placement counting and refined in step 2): its fit to the candidate's
   sampled points (`fit.fit_scores`:
   inlier fraction times one minus the free-space violation) times the structure check's agreement with its
   boards and openings (`structure.structure_check`: rays that find a board where the type has one or see into
   an opening where it has one). The fit alone cannot tell types apart: a solid-deck or wider model explains an
   EPAL's front face as well as the EPAL does; the rays into its fork pockets tell. The rays are cast only for the
   candidate's first type and the `RANK_BY_FIT` best others by fit, since the fit rules out types of another size;
2. the best `keep` of them are refined (`RefinerStage.refine`, each with its own boards and starts), and the
   type whose refined pose scores best the same way wins, with that pose and fit: the refiner stage then leaves
   the row as it is. Types without boards, or refinement off: step 1's best type wins, unrefined.

In both steps every type but the candidate's first option (its class's first type) has `margin` taken off its score,
so a look-alike type must fit clearly better to replace the common one (`margin_levelled` where the types are judged
levelled, below: each has then been placed on the floor in its own right). In step 2 another type must also show clear
structure at its refined pose (`StructureParams.replace_min_agreement`, `replace_min_open_fraction`): a carton stack
that no type explains is otherwise given the look-alike that explains it least badly. Where no kept type qualifies,
the candidate keeps its first type, and the refiner stage refines it.

Without a calibration and with `first_enough`, step 2's refinement of each candidate's first type comes first: where
that type scores `first_enough` or more at its refined pose it wins, and the candidate's other types are neither ranked
nor refined (they are tried where the first type fits poorly; its refinement is not repeated for them).

With the camera's calibration (`EstimatorOptions.level`), `keep_levelled` types are kept, the candidate's first type
always among them, and each is levelled on the floor and searched and refined in yaw and position (`level.level_poses`,
as the estimator levels every pose) before it is judged: the first type from its refined pose, the others from the
network's (the levelling's search does what the refinement's starts would). Where the refinement moved the first
type's pose (depth exact enough to trust it), it can have moved it off the pallet, beyond the search's slides: the first
type is then levelled from the network's pose too, and the better of the two competes (EPAL pocket targets on exact
depth 88.3 -> 90.0 %; on stereo depth the refinement rarely moves a pose and nothing changes). The winner keeps that
pose, the one the fit check will see. On stereo depth the six-degree refinement is rarely trusted, so without this a
look-alike type would be judged at the network's pose, often 10-30 cm off, and lose to the first type, which was then
levelled alone.
Where every type of a candidate is kept (and refined), ranking them is skipped. The ranking at the network's pose is
a poor guide: levelling a candidate's every type finds about a tenth more of the forklift's pallets within 5 cm than
levelling its four best-ranked ones (docs/experiments/pallet-types.md). The other types are levelled on fewer points
(`OTHER_SEARCH_POINTS` for the search of turns and slides): they must find the pallet's place well enough to tell its
type, and on those validation frames the fewer points gave as many pallets within 5 cm as the full levelling (165
against 163); their ICP keeps its points (150 of 600 lost 11 pallets).

Cost: a fit score per type and the structure agreement of four of them (none where every type is kept), and one
refinement (levelled: one levelling) and structure agreement per kept type, instead of one refinement per candidate;
the agreements of all candidates and types go in one pass (`structure.structure_agreement`, its rays in the compiled
kernel).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .candidates import Candidates
from .deadline import Deadline, elapsed_ms
from .fit import fit_scores
from .level import LevelParams, level_in_camera
from .stage_geometry import PalletGeometry
from .stage_refine import RefinerStage
from .structure import BoxSets, StructureParams, structure_agreement

__all__ = ["TypeChoiceStage", "RANK_BY_FIT", "OTHER_SEARCH_POINTS", "face_starts"]


def face_starts(first_size_m, size_m, min_m: float = 0.02) -> np.ndarray:
    """Pallet-frame slides that lay a type smaller than the first type flush with one of the first type's faces:
    half the difference of the lengths along x, of the widths along y, each way. The network poses every pallet about
    the first type's size, so a smaller pallet's pose is that much off along its length or width wherever the face it
    shows is not the one the network centred it behind (a EUR 6 posed as an EPAL: 0.2 m along x, 0.1 m along y).

    :param first_size_m, size_m: (3,) length, width, height, metres. :param min_m: smaller differences are none.
    :return: (k, 4, 4) pallet-frame offsets, k = 0, 2 or 4.
    """
    out = []
    for axis in (0, 1):
        d = 0.5 * (float(first_size_m[axis]) - float(size_m[axis]))
        if d >= min_m:
            for sign in (1.0, -1.0):
                T = np.eye(4)
                T[axis, 3] = sign * d
                out.append(T)
    return np.array(out).reshape(-1, 4, 4)


RANK_BY_FIT = 3   # types besides a candidate's first whose structure is looked at when ranking (the best by fit)
OTHER_SEARCH_POINTS = 40    # levelled, a candidate's other types: the search's points (`LevelParams.search_points`)


class TypeChoiceStage:
    """Picks the pallet type of candidates that may be of several types.

    :param geometries: the bundle's pallet types. :param types_of_class: detector class -> its type indexes.
    :param refiner: the estimator's `RefinerStage` (its refinement decides between the kept types).
    :param tol_m: tolerance of the fit score that ranks the types at the network's pose, metres.
    :param keep: how many of a candidate's best-ranked types are refined (>= 1).
    :param structure: the structure check's ray parameters for the agreement.
    :param margin: how much better (score 0-1) another type must be than the candidate's first option.
    :param level: how the estimator levels poses on a calibrated camera's floor (`EstimatorOptions.level`); with a
        calibration the kept types are judged at their levelled poses. None: never levelled.
    :param keep_levelled: how many types are kept where they are levelled (>= 1; default `keep`).
    :param margin_levelled: `margin` where they are levelled (default `margin`).
    :param first_enough: not levelled, a candidate whose first type scores at least this at its refined pose (fit
        times structure agreement) keeps it, and no other type is ranked or refined. None: every candidate's types
        are compared.
    """

    def __init__(self, geometries: tuple[PalletGeometry, ...], types_of_class: dict[int, tuple[int, ...]],
                 refiner: RefinerStage, tol_m: float, keep: int, structure: StructureParams = StructureParams(),
                 margin: float = 0.0, level: LevelParams | None = None, keep_levelled: int | None = None,
                 margin_levelled: float | None = None, first_enough: float | None = None) -> None:
        keep_levelled = keep if keep_levelled is None else keep_levelled
        if int(keep) < 1 or int(keep_levelled) < 1:
            raise ValueError(f"keep and keep_levelled must be >= 1, got {keep}, {keep_levelled}")
        self.geometries = tuple(geometries)
        self.types_of_class = {int(c): tuple(int(j) for j in t) for c, t in types_of_class.items()}
        self.refiner = refiner
        self.tol_m, self.keep, self.keep_levelled = float(tol_m), int(keep), int(keep_levelled)
        self.structure = structure
        self.margin = float(margin)
        self.margin_levelled = self.margin if margin_levelled is None else float(margin_levelled)
        if first_enough is not None and not 0.0 < first_enough <= 1.0:
            raise ValueError(f"first_enough must be in (0, 1], got {first_enough}")
        self.first_enough = first_enough
        self.level = level
        self.level_other = None if level is None else replace(
            level, search_points=min(level.search_points, OTHER_SEARCH_POINTS))
        # the types with boards, laid out once for `structure_agreement`; _box_set: type -> its set (-1: none)
        boxed = [j for j, g in enumerate(self.geometries) if g.boxes_m is not None]
        self._box_sets = BoxSets([self.geometries[j].boxes_m for j in boxed]) if boxed else None
        self._box_set = np.full(len(self.geometries), -1, np.int64)
        self._box_set[boxed] = np.arange(len(boxed))
        # [first type][type]: the type's slides flush with the first type's faces (`face_starts`), once per bundle
        self._face_offsets = [[face_starts(f.size_m, g.size_m) for g in self.geometries] for f in self.geometries]

    @property
    def needed(self) -> bool:
        """Whether any detector class reports more than one type."""
        return any(len(t) > 1 for t in self.types_of_class.values())

    def placed_fit(self, cands: Candidates, rows: np.ndarray, depth_m: np.ndarray, K: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Each type's fit score where it is best placed: at the network's pose of each row, and for a type smaller
        than the row's first also laid flush with the first type's faces (`face_starts`), the best counting (-inf for
        the types not among the row's options).
        :return: fit (len(rows), number of types), and the pose of each (len(rows), types, 4, 4)."""
        n_types = len(self.geometries)
        fit = np.full((len(rows), n_types), -np.inf)
        first = np.array([o[0] for o in cands.type_options[rows]], int)
        start = np.repeat(cands.T_net[rows][:, None], n_types, axis=1)
        for j, g in enumerate(self.geometries):
            mine = np.flatnonzero([j in o for o in cands.type_options[rows]])
            if not len(mine):
                continue
            fit[mine, j] = fit_scores(cands.T_net[rows[mine]], cands.points_cam[rows[mine]], None, g.points_m,
                                      depth_m, K, self.tol_m, model_boxes_m=g.boxes_m)[2]
            for f_type in np.unique(first[mine]):
                offsets = self._face_offsets[f_type][j]
                if not len(offsets):
                    continue
                at = mine[first[mine] == f_type]
                # every row's every placement in one call: (len(at), k) poses, the first best of a row's k counting
                T_face = cands.T_net[rows[at]][:, None] @ offsets[None]
                f = fit_scores(T_face.reshape(-1, 4, 4), np.repeat(cands.points_cam[rows[at]], len(offsets), axis=0),
                               None, g.points_m, depth_m, K, self.tol_m,
                               model_boxes_m=g.boxes_m)[2].reshape(len(at), len(offsets))
                pick = f.argmax(axis=1)
                f_best, T_best = f[np.arange(len(at)), pick], T_face[np.arange(len(at)), pick]
                better = f_best > fit[at, j]
                fit[at[better], j], start[at[better], j] = f_best[better], T_best[better]
        return fit, start

    def rank(self, cands: Candidates, rows: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
             others: int = RANK_BY_FIT, margin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Fit score times structure agreement of each type where it is best placed (`placed_fit`: the network's
        pose, or a smaller type laid flush with the first type's faces). The agreement is computed for the row's
        first type and its `others` best others by fit alone; the rest keep -inf. Most of a bundle's types are ruled
        out by their size, which the fit sees; the rays tell the look-alikes apart. :param margin: taken off the
        other types' scores (default `margin`).
        :return: scores (len(rows), number of types), and the pose each was scored at (len(rows), types, 4, 4)."""
        fit, start = self.placed_fit(cands, rows, depth_m, K)
        first = np.array([o[0] for o in cands.type_options[rows]], int)
        rest = fit.copy()
        rest[np.arange(len(rows)), first] = -np.inf
        ranked = np.argsort(-rest, axis=1, kind="stable")[:, :others]
        scored = np.zeros_like(fit, bool)
        scored[np.arange(len(rows)), first] = True
        scored[np.arange(len(rows))[:, None], ranked] = True
        scored &= np.isfinite(fit)
        k, j = np.nonzero(scored)
        score = np.full_like(fit, -np.inf)
        score[k, j] = fit[k, j] * self.evidence(start[k, j], j, depth_m, K)[0] \
            - (self.margin if margin is None else margin) * (j != first[k])
        return score, start

    def evidence(self, T: np.ndarray, type_index: np.ndarray, depth_m: np.ndarray, K: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The structure check's agreement of each pose with its own type's boards and openings (rays that find
        a board where the type has one, or see into an opening where it has one), and its open fraction (1, 1 for a
        type without boards): every pose in one pass (`structure.structure_agreement`). :return: (n,), (n,)."""
        agreement, open_fraction = np.ones(len(T)), np.ones(len(T))
        which = self._box_set[np.asarray(type_index, np.int64)]
        boxed = np.flatnonzero(which >= 0)
        if len(boxed):
            agreement[boxed], open_fraction[boxed] = structure_agreement(T[boxed], self._box_sets, which[boxed],
                                                                         depth_m, K, self.structure)
        return agreement, open_fraction

    def choose(self, cands: Candidates, rows: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
               T_vehicle_cam: np.ndarray | None = None) -> None:
        """Set `type_index` of `rows`, and their refined pose and fit where the winner was refined.
        :param T_vehicle_cam: (4, 4) the camera's calibration: the kept types are judged levelled (with `level`)."""
        levelled = T_vehicle_cam is not None and self.level is not None
        keep, margin = (self.keep_levelled, self.margin_levelled) if levelled else (self.keep, self.margin)
        refines = np.asarray(self.refiner.refines_type, bool)
        settled, box_obs = {}, {}   # row -> its first type's refined pose, fit, agreement; row -> its ICP points
        if not levelled and self.first_enough is not None:
            rows, settled, box_obs = self._settle_first(cands, rows, depth_m, K, refines)
            if not len(rows):
                return
        if keep >= max(len(cands.type_options[i]) for i in rows) \
                and all(refines[j] for i in rows for j in cands.type_options[i]):
            # every type is kept and refined: nothing to rank (the first type is the row's type until one is chosen)
            order = [[j for j in cands.type_options[i] if refines[j]] for i in rows]
            best = np.array([cands.type_options[i][0] for i in rows], np.int64)
            score = np.zeros((len(rows), len(self.geometries)))
            start = np.repeat(cands.T_net[rows][:, None], len(self.geometries), axis=1)
        else:
            score, start = self.rank(cands, rows, depth_m, K, max(RANK_BY_FIT, keep - 1), margin)
            order = np.argsort(-score, axis=1, kind="stable")[:, :keep]
            best = order[:, 0]
        pair_row, pair_type = [], []
        for k, types in enumerate(order):
            kept = [int(j) for j in types if np.isfinite(score[k, j]) and refines[j]]
            first_type = cands.type_options[rows[k]][0]
            if levelled and refines[first_type] and first_type not in kept:
                kept.append(first_type)     # levelled, the row keeps the pose judged here: its first type's too
            pair_row += [k] * len(kept)
            pair_type += kept
        cands.assign(rows, type_index=best)
        if not pair_row:
            return
        pair_row, pair_type = np.asarray(pair_row), np.asarray(pair_type)
        src = rows[pair_row]
        for i in np.unique(src):
            if int(i) not in box_obs:
                box_obs[int(i)] = self.refiner.box_points(cands.pixels[i], depth_m, K)
        first = np.array([cands.type_options[i][0] for i in src])
        # levelled, the other types start from the network's pose: the levelling's own search of yaw and position
        # takes the place of the six-degree refinement, which stereo depth rarely lets count anyway
        six = np.flatnonzero(pair_type == first) if levelled else np.arange(len(src))
        T_start = start[pair_row, pair_type]      # the network's pose, or a smaller type's laid flush with a face
        T, fit = T_start.copy(), np.full((len(src), 3), np.nan)
        known = np.array([int(i) in settled and t == f for i, t, f in zip(src, pair_type, first)], bool)
        for k in np.flatnonzero(known):           # the first type refined already (from the network's pose too)
            T[k], fit[k] = settled[int(src[k])][:2]
        six = six[~known[six]]
        if len(six):
            T[six], fit[six] = self.refiner.refine(T_start[six], cands.points_cam[src[six]],
                                                   [box_obs[int(i)] for i in src[six]], pair_type[six], depth_m, K)
        if levelled:
            # where the refinement moved the first type's pose (depth exact enough to trust it), it may have moved it
            # off the pallet beyond the levelling's search: the network's pose is levelled too, and the better competes
            moved = six[np.abs(T[six] - cands.T_net[src[six]]).max(axis=(1, 2)) > 1e-9]
            T = np.concatenate([T, cands.T_net[src[moved]]])
            pair_row, pair_type, src, first, known = (np.concatenate([a, a[moved]])
                                                      for a in (pair_row, pair_type, src, first, known))
            alike = np.flatnonzero(pair_type != first)
            for idx, params in ((np.flatnonzero(pair_type == first), self.level), (alike, self.level_other)):
                if len(idx):
                    T[idx] = level_in_camera(T[idx], T_vehicle_cam, [self.geometries[j] for j in pair_type[idx]],
                                             params, [box_obs[int(i)] for i in src[idx]],
                                             self.refiner.refine_options.threads,
                                             self.refiner.icp_grids(pair_type[idx]))
            fit = self.refiner.fit(T, cands.points_cam[src], pair_type, depth_m, K)
        agreement, open_fraction = np.ones(len(T)), np.ones(len(T))
        agreement[~known], open_fraction[~known] = self.evidence(T[~known], pair_type[~known], depth_m, K)
        for k in np.flatnonzero(known):
            agreement[k], open_fraction[k] = settled[int(src[k])][2:]
        other = pair_type != first
        select = fit[:, 2] * agreement - margin * other
        s = self.structure
        unclear = (agreement < s.replace_min_agreement) | (open_fraction < s.replace_min_open_fraction)
        select[other & unclear] = -np.inf
        for k in np.unique(pair_row):
            mine = np.flatnonzero(pair_row == k)
            win = mine[int(np.argmax(select[mine]))]
            if np.isfinite(select[win]):
                cands.assign([rows[k]], type_index=[pair_type[win]], T_cam_pallet=T[win][None], fit=fit[win][None])
            else:       # no other type qualifies, and the first was not refined: the refiner stage refines it
                cands.assign([rows[k]], type_index=[first[win]])

    def _settle_first(self, cands: Candidates, rows: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                      refines: np.ndarray) -> tuple[np.ndarray, dict, dict]:
        """Refine each row's first type from the network's pose; a row whose score there (fit times agreement) is at
        least `first_enough` is given that type, pose and fit. :return: the rows left to compare, and for those of
        them whose first type was refined: row -> (T_cam_pallet (4, 4), fit (3,), agreement, open fraction), and
        row -> its depth points for ICP."""
        first = np.array([cands.type_options[i][0] for i in rows], np.int64)
        mine = np.flatnonzero(refines[first])
        if not len(mine):
            return rows, {}, {}
        src = rows[mine]
        box_obs = {int(i): self.refiner.box_points(cands.pixels[i], depth_m, K) for i in src}
        T, fit = self.refiner.refine(cands.T_net[src], cands.points_cam[src], [box_obs[int(i)] for i in src],
                                     first[mine], depth_m, K)
        agreement, open_fraction = self.evidence(T, first[mine], depth_m, K)
        done = fit[:, 2] * agreement >= self.first_enough
        cands.assign(src[done], type_index=first[mine][done], T_cam_pallet=T[done], fit=fit[done])
        left = np.flatnonzero(~done)
        settled = {int(src[k]): (T[k], fit[k], agreement[k], open_fraction[k]) for k in left}
        return rows[~np.isin(rows, src[done])], settled, box_obs

    def __call__(self, cands: Candidates, depth_m: np.ndarray, K: np.ndarray, timings: dict[str, float],
                 deadline: Deadline | None = None, T_vehicle_cam: np.ndarray | None = None) -> None:
        """The stage on the alive rows with several type options. Its time counts as refinement. Under a time
        budget the rows go `refiner.budget_chunk` at a time, highest score first; those left when it expires keep
        their first type, unrefined (the refiner stage then rejects them for the budget)."""
        multi = np.array([len(o) > 1 for o in cands.type_options], bool)
        rows = np.flatnonzero(cands.alive & multi)
        if len(rows) == 0:
            return
        t = time.perf_counter()
        budget = deadline is not None and deadline.budget_ms is not None
        step = self.refiner.budget_chunk if budget else max(len(rows), 1)
        for k in range(0, len(rows), step):
            if deadline is not None and deadline.expired():
                break
            self.choose(cands, rows[k:k + step], depth_m, K, T_vehicle_cam)
        timings["refine"] = timings.get("refine", 0.0) + elapsed_ms(t)
