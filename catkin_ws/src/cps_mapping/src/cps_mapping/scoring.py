"""Map quality against the simulator's ground truth: precision, recall, F1, coverage, per robot.

Both the map and the ground truth are sets of voxels on OctoMap's grid (index floor(p / res)).
Every figure is given at two matching tolerances, and each is named by its tolerance:

- *exact* (`..._exact`): a map voxel matches only the ground-truth voxel with the same index;
- *within N voxels* (`..._within_1_voxel` by default): a match anywhere within N voxels in all
  26 directions (Chebyshev). A surface that lies on a voxel border (the floor at z = 0) or a
  curved one is split between two voxel layers by the sensor's last millimetre, so the exact
  figure counts some correct voxels as wrong; the tolerant one forgives a map that is one voxel
  too thick (a truth grown by one voxel scores tolerant precision 1.0). Read both.

- precision = |map ∩ truth| / |map|: how much of what the map calls occupied is real;
- recall = |map ∩ truth| / |truth|: how much of all the site's occupied voxels the map holds;
- F1 = their harmonic mean;
- coverage = |map ∩ observable| / |observable| (at the tolerance): recall restricted to the
  *observable surface*. Which surface that is, `observable_from` says:
  - "sensor poses": given by the caller, independent of the map (cps_sim.ground_truth's
    ray-cast of the truth from the mission's recorded sensor positions);
  - "scored map's free space": truth voxels with a face neighbour empty in the truth that the
    scored map knows to be free (the old definition: a map that saw less is judged against less);
  - "truth": every truth voxel with an empty face neighbour (no map, no poses).
- per robot: the occupied voxels each robot last updated (`contributions`), how many of them
  are true (precision, both tolerances), and the share of the observable surface they cover.

`scores.json` written before the exact figures existed has bare `precision`, `recall`, `f1`:
those are the within-1-voxel figures; `read_scores` names them so.
"""

import dataclasses
from typing import Callable, Dict, Optional

import numpy as np

from cps_mapping.fused_map import index_to_center, near_any, pack_index, voxel_index

_FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.int64)
OBSERVABLE_FROM_POSES = "sensor poses"
OBSERVABLE_FROM_MAP = "scored map's free space"
OBSERVABLE_FROM_TRUTH = "truth"


def tolerance_label(tolerance_voxels):
    """'exact' or 'within_N_voxel(s)': the suffix of every score key, so a figure names its tolerance."""
    n = int(tolerance_voxels)
    return "exact" if n == 0 else f"within_{n}_voxel" + ("" if n == 1 else "s")


def tolerance_text(tolerance_voxels):
    """'voxel for voxel' or 'within ±N voxel(s)', for report lines."""
    n = int(tolerance_voxels)
    return "voxel for voxel" if n == 0 else f"within ±{n} voxel" + ("" if n == 1 else "s")


@dataclasses.dataclass
class MatchScore:
    """Precision, recall and F1 at one matching tolerance (0 = exact)."""

    tolerance_voxels: int
    true_positives: int  # map voxels with a truth voxel within the tolerance
    truth_found: int  # truth voxels with a map voxel within the tolerance
    precision: float
    recall: float
    f1: float


@dataclasses.dataclass
class RobotScore:
    occupied_voxels: int
    true_positives_exact: int
    precision_exact: float
    true_positives: int  # within the score's tolerance
    precision: float  # within the score's tolerance
    coverage: float  # within the score's tolerance


@dataclasses.dataclass
class MapScore:
    resolution_m: float
    map_voxels: int
    truth_voxels: int
    observable_voxels: int
    observable_from: str  # OBSERVABLE_FROM_*: what the observable surface was computed from
    exact: MatchScore
    tolerant: MatchScore
    coverage: float  # of the observable surface, within the tolerant score's tolerance
    robots: Dict[str, RobotScore]

    # The bare names are the tolerant figures (what every score was before the exact ones existed).
    @property
    def precision(self):
        return self.tolerant.precision

    @property
    def recall(self):
        return self.tolerant.recall

    @property
    def f1(self):
        return self.tolerant.f1

    @property
    def tolerance_voxels(self):
        return self.tolerant.tolerance_voxels

    def as_dict(self):
        """Flat, every figure keyed with its tolerance (`f1_exact`, `f1_within_1_voxel`, ...)."""
        out = {
            "resolution_m": self.resolution_m,
            "tolerance_voxels": self.tolerant.tolerance_voxels,
            "map_voxels": self.map_voxels,
            "truth_voxels": self.truth_voxels,
            "observable_voxels": self.observable_voxels,
            "observable_from": self.observable_from,
        }
        for match in (self.exact, self.tolerant):
            label = tolerance_label(match.tolerance_voxels)
            for key in ("true_positives", "truth_found", "precision", "recall", "f1"):
                out[f"{key}_{label}"] = getattr(match, key)
        tolerant = tolerance_label(self.tolerant.tolerance_voxels)
        out[f"coverage_{tolerant}"] = self.coverage
        out["robots"] = {
            robot: {
                "occupied_voxels": r.occupied_voxels,
                "true_positives_exact": r.true_positives_exact,
                "precision_exact": r.precision_exact,
                f"true_positives_{tolerant}": r.true_positives,
                f"precision_{tolerant}": r.precision,
                f"coverage_{tolerant}": r.coverage,
            }
            for robot, r in self.robots.items()
        }
        return out


def read_scores(doc):
    """A scores.json document (dict) with every figure keyed by its tolerance.

    Files from before the exact figures have bare `precision`/`recall`/`f1`/`coverage` (within
    ±1 voxel, coverage against the scored map's free space): they come back under the
    `_within_1_voxel` keys, with `definition` saying so and no `_exact` keys."""
    if "f1" not in doc or any(k.startswith("f1_") for k in doc):
        return dict(doc, definition=doc.get("definition", "current"))
    out = {k: v for k, v in doc.items() if k not in ("precision", "recall", "f1", "coverage", "true_positives")}
    for key in ("precision", "recall", "f1", "coverage", "true_positives"):
        if key in doc:
            out[f"{key}_within_1_voxel"] = doc[key]
    out.setdefault("tolerance_voxels", 1)
    out.setdefault("observable_from", OBSERVABLE_FROM_MAP)
    out["definition"] = "old (before 2026-11): within ±1 voxel only, no exact figures"
    return out


def load_ground_truth(source, resolution_m=None):
    """(N x 3 voxel centres, resolution) from an .npz path (cps_sim's keys `resolution_m`,
    `occupied_centers_m`), a dict with those keys, or an array (then `resolution_m` is needed)."""
    if isinstance(source, (str, bytes)) or hasattr(source, "__fspath__"):
        with np.load(source) as data:
            return np.asarray(data["occupied_centers_m"], dtype=np.float64), float(data["resolution_m"])
    if isinstance(source, dict) or hasattr(source, "files"):
        return np.asarray(source["occupied_centers_m"], dtype=np.float64), float(source["resolution_m"])
    if resolution_m is None:
        raise ValueError("ground truth given as an array needs resolution_m")
    return np.asarray(source, dtype=np.float64).reshape(-1, 3), float(resolution_m)


def _ratio(a, b):
    return float(a) / float(b) if b else 0.0


def observable_surface(truth_index, resolution_m, is_free: Optional[Callable] = None):
    """Ground-truth voxels with a face neighbour that is empty in the truth (and free in the map)."""
    neighbours = (truth_index[:, None, :] + _FACES[None, :, :]).reshape(-1, 3)
    empty = ~np.isin(pack_index(neighbours), pack_index(truth_index))
    if is_free is not None and empty.any():
        free = np.zeros(len(neighbours), dtype=bool)
        free[empty] = is_free(index_to_center(neighbours[empty], resolution_m))
        empty &= free
    return truth_index[empty.reshape(-1, 6).any(axis=1)]


def _index(centers_m, resolution_m):
    pts = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
    return np.unique(voxel_index(pts, resolution_m), axis=0) if len(pts) else np.zeros((0, 3), np.int64)


def _match(map_index, truth_index, tolerance_voxels):
    map_true = near_any(map_index, truth_index, tolerance_voxels)
    truth_found = near_any(truth_index, map_index, tolerance_voxels)
    tp = int(map_true.sum())
    precision, recall = _ratio(tp, len(map_index)), _ratio(truth_found.sum(), len(truth_index))
    score = MatchScore(
        int(tolerance_voxels),
        tp,
        int(truth_found.sum()),
        precision,
        recall,
        _ratio(2 * precision * recall, precision + recall),
    )
    return score, truth_found


def score_map(
    occupied_centers_m,
    ground_truth,
    resolution_m=None,
    is_free: Optional[Callable] = None,
    contributions: Optional[Dict[str, np.ndarray]] = None,
    tolerance_voxels=1,
    observable_centers_m=None,
) -> MapScore:
    """Score a map's occupied voxel centres against the ground truth, exact and within
    `tolerance_voxels` (see the module docstring).

    `observable_centers_m`: the observable surface, computed without the map (ray-cast from the
    sensor poses); else `is_free(points) -> bool array`, the map's free-space test
    (FusedLogOddsMap.is_free), decides it; `contributions` maps robot -> the occupied voxel
    centres that robot last updated.
    """
    truth_centers, truth_res = load_ground_truth(ground_truth, resolution_m)
    res = float(resolution_m or truth_res)
    if abs(res - truth_res) > 1e-9:
        raise ValueError(f"map resolution {res} m differs from the ground truth's {truth_res} m")
    truth_index = _index(truth_centers, res)
    map_index = _index(occupied_centers_m, res)
    exact, _ = _match(map_index, truth_index, 0)
    tolerant, truth_found = _match(map_index, truth_index, tolerance_voxels)
    observable_mask = np.zeros(len(truth_index), dtype=bool)
    if observable_centers_m is not None:
        observable_from = OBSERVABLE_FROM_POSES
        if len(truth_index):
            observable_mask = np.isin(pack_index(truth_index), pack_index(_index(observable_centers_m, res)))
    else:
        observable_from = OBSERVABLE_FROM_MAP if is_free is not None else OBSERVABLE_FROM_TRUTH
        if len(truth_index):
            observable = observable_surface(truth_index, res, is_free)
            observable_mask = np.isin(pack_index(truth_index), pack_index(observable))
    robots = {}
    for robot, centers in (contributions or {}).items():
        idx = _index(centers, res)
        robot_exact = int(near_any(idx, truth_index, 0).sum())
        robot_tp = int(near_any(idx, truth_index, tolerance_voxels).sum())
        seen = near_any(truth_index[observable_mask], idx, tolerance_voxels).sum()
        robots[robot] = RobotScore(
            len(idx),
            robot_exact,
            _ratio(robot_exact, len(idx)),
            robot_tp,
            _ratio(robot_tp, len(idx)),
            _ratio(seen, observable_mask.sum()),
        )
    coverage = _ratio((truth_found & observable_mask).sum(), observable_mask.sum())
    return MapScore(
        resolution_m=res,
        map_voxels=len(map_index),
        truth_voxels=len(truth_index),
        observable_voxels=int(observable_mask.sum()),
        observable_from=observable_from,
        exact=exact,
        tolerant=tolerant,
        coverage=coverage,
        robots=robots,
    )


def score_fused_map(fused, ground_truth, tolerance_voxels=1, observable_centers_m=None) -> MapScore:
    """score_map for a FusedLogOddsMap, with its per-robot contributions, and its free space as the
    observable surface unless `observable_centers_m` (from the sensor poses) is given."""
    occupied = fused.occupied_index()
    contributions = {
        robot: index_to_center(index, fused.resolution_m) for robot, index in fused.contributed_index(occupied).items()
    }
    return score_map(
        index_to_center(occupied, fused.resolution_m),
        ground_truth,
        fused.resolution_m,
        is_free=fused.is_free,
        contributions=contributions,
        tolerance_voxels=tolerance_voxels,
        observable_centers_m=observable_centers_m,
    )
