"""Map quality against the simulator's ground truth: precision, recall, F1, coverage, per robot.

Both the map and the ground truth are sets of voxels on OctoMap's grid (index floor(p / res)).

- precision = |map ∩ truth| / |map|: how much of what the map calls occupied is real;
- recall = |map ∩ truth| / |truth|: how much of all the site's occupied voxels the map holds;
  "∩" matches within `tolerance_voxels` (Chebyshev, default 1): a surface that lies on a voxel
  border (the floor at z = 0) or a curved one is split between two voxel layers by the sensor's
  last millimetre, so an exact match would count correct voxels as wrong. 0 = exact match.
- F1 = their harmonic mean;
- coverage = |map ∩ observable| / |observable|: recall restricted to the *observable surface*,
  the ground-truth voxels that have at least one face neighbour that is empty in the ground
  truth and that the map knows to be free. Voxels inside walls and equipment, the floor under
  equipment and the outer side of the walls have no such neighbour: no sensor can see them, so
  they do not count against the map. Without the map's free space (`is_free=None`) the
  observable surface is every ground-truth voxel with an empty face neighbour.
- per robot: the occupied voxels each robot last updated (`contributions`), how many of them
  are true (precision), and the share of the observable surface they cover.
"""
import dataclasses
from typing import Callable, Dict, Optional

import numpy as np

from cps_mapping.fused_map import index_to_center, near_any, pack_index, voxel_index

_FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.int64)


@dataclasses.dataclass
class RobotScore:
    occupied_voxels: int
    true_positives: int
    precision: float
    coverage: float


@dataclasses.dataclass
class MapScore:
    resolution_m: float
    map_voxels: int
    truth_voxels: int
    observable_voxels: int
    true_positives: int
    precision: float
    recall: float
    f1: float
    coverage: float
    robots: Dict[str, RobotScore]

    def as_dict(self):
        return dataclasses.asdict(self)


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


def score_map(occupied_centers_m, ground_truth, resolution_m=None, is_free: Optional[Callable] = None,
              contributions: Optional[Dict[str, np.ndarray]] = None, tolerance_voxels=1) -> MapScore:
    """Score a map's occupied voxel centres against the ground truth (see the module docstring).

    `is_free(points) -> bool array` is the map's free-space test (FusedLogOddsMap.is_free);
    `contributions` maps robot -> the occupied voxel centres that robot last updated.
    """
    truth_centers, truth_res = load_ground_truth(ground_truth, resolution_m)
    res = float(resolution_m or truth_res)
    if abs(res - truth_res) > 1e-9:
        raise ValueError(f"map resolution {res} m differs from the ground truth's {truth_res} m")
    truth_index = np.unique(voxel_index(truth_centers, res), axis=0) if len(truth_centers) else \
        np.zeros((0, 3), np.int64)
    occupied = np.asarray(occupied_centers_m, dtype=np.float64).reshape(-1, 3)
    map_index = np.unique(voxel_index(occupied, res), axis=0) if len(occupied) else np.zeros((0, 3), np.int64)
    map_true = near_any(map_index, truth_index, tolerance_voxels)
    truth_found = near_any(truth_index, map_index, tolerance_voxels)
    observable_mask = np.zeros(len(truth_index), dtype=bool)
    if len(truth_index):
        observable = observable_surface(truth_index, res, is_free)
        observable_mask = np.isin(pack_index(truth_index), pack_index(observable))
    tp = int(map_true.sum())
    precision, recall = _ratio(tp, len(map_index)), _ratio(truth_found.sum(), len(truth_index))
    f1 = _ratio(2 * precision * recall, precision + recall)
    robots = {}
    for robot, centers in (contributions or {}).items():
        pts = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        idx = np.unique(voxel_index(pts, res), axis=0) if len(pts) else np.zeros((0, 3), np.int64)
        robot_tp = int(near_any(idx, truth_index, tolerance_voxels).sum())
        seen = near_any(truth_index[observable_mask], idx, tolerance_voxels).sum()
        robots[robot] = RobotScore(len(idx), robot_tp, _ratio(robot_tp, len(idx)), _ratio(seen, observable_mask.sum()))
    coverage = _ratio((truth_found & observable_mask).sum(), observable_mask.sum())
    return MapScore(resolution_m=res, map_voxels=len(map_index), truth_voxels=len(truth_index),
                    observable_voxels=int(observable_mask.sum()), true_positives=tp, precision=precision,
                    recall=recall, f1=f1, coverage=coverage, robots=robots)


def score_fused_map(fused, ground_truth, tolerance_voxels=1) -> MapScore:
    """score_map for a FusedLogOddsMap, with its free space and per-robot contributions."""
    occupied = fused.occupied_index()
    contributions = {robot: index_to_center(index, fused.resolution_m)
                     for robot, index in fused.contributed_index(occupied).items()}
    return score_map(index_to_center(occupied, fused.resolution_m), ground_truth, fused.resolution_m,
                     is_free=fused.is_free, contributions=contributions, tolerance_voxels=tolerance_voxels)
