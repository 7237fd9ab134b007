"""What a monitoring mission saw again of the baseline (no rospy): an inspector must tell "nothing
changed here" from "no robot looked here again".

A baseline voxel is *re-observed* when the new mission can confirm or deny it under the change
rules (cps_mapping.change_detection.ChangeRules): the new map holds an occupied voxel within
`tolerance_voxels` of it (still there), or its rays passed through it at least
`disappeared_min_misses` times net of hits (gone). A place that is neither can hide a change that
no rule could report. Robots' swept volume is left out, as in the detection.

`reobserved` gives that per baseline voxel; `coverage` the fraction per named region (the site's
equipment and areas, from the caller), so that the report can list what to send a robot to.
"""

import dataclasses
from typing import Callable, Dict, Optional

import numpy as np

from cps_mapping.change_detection import misses_probability, near_any
from cps_mapping.fused_map import index_to_center, voxel_index

# A region with less than this fraction of its baseline voxels re-observed is "not re-observed".
REOBSERVED_FRACTION = 0.5


@dataclasses.dataclass(frozen=True)
class Coverage:
    """One region's baseline voxels and how many of them the new mission re-observed."""

    name: str
    voxels: int
    reobserved: int

    @property
    def fraction(self):
        return self.reobserved / self.voxels if self.voxels else float("nan")

    @property
    def seen_again(self):
        """Re-observed well enough to confirm or deny a change there."""
        return self.voxels > 0 and self.fraction >= REOBSERVED_FRACTION


def reobserved(baseline_map, current_map, rules, swept=None, current_misses=None):
    """(index (N, 3), centres (N, 3), re-observed (N,) bool) of the baseline's occupied voxels
    outside `swept`. `current_misses` (change_detection.VoxelLevels): the new mission's misses at
    the baseline's voxels when the new map was read from a .bt (its log-odds are not kept)."""
    res = baseline_map.resolution_m
    index = np.unique(voxel_index(baseline_map.occupied_centers(), res), axis=0).reshape(-1, 3)
    if swept is not None and len(swept):
        index = index[~swept.contains(index)]
    centers = index_to_center(index, res)
    current = voxel_index(current_map.occupied_centers(), res).reshape(-1, 3)
    present = near_any(index, current, rules.tolerance_voxels)
    if current_misses is not None:
        gone = current_misses.at_least(centers, res, rules.disappeared_min_misses)
    else:
        miss = current_map.sensor_model.miss if hasattr(current_map, "sensor_model") else 0.4
        gone = current_map.is_free(centers, max_probability=misses_probability(rules.disappeared_min_misses, miss))
    return index, centers, present | gone


def coverage(centers, seen, regions: Dict[str, Callable], rest: Optional[str] = None):
    """[Coverage] of each region (name -> mask of the points it holds), and of the voxels no region
    holds under the name `rest` (if given), from `reobserved`'s centres and mask."""
    out, claimed = [], np.zeros(len(centers), dtype=bool)
    for name, holds in regions.items():
        inside = holds(centers) if len(centers) else np.zeros(0, dtype=bool)
        claimed |= inside
        out.append(Coverage(name, int(inside.sum()), int((inside & seen).sum())))
    if rest is not None:
        out.append(Coverage(rest, int((~claimed).sum()), int((~claimed & seen).sum())))
    return out
