"""OctoMap files that are valid but too large for the map's grid limit, for the tests."""

import numpy as np
import octomap

from cps_mapping.fused_map import BT_HEADER

# A tree whose root has one occupied child: one pruned leaf of 2^15 voxels a side (3.3 km at 0.1 m).
COARSE_LEAF_BT = BT_HEADER + b"\n#\nid OcTree\nsize 2\nres 0.1\ndata\n" + bytes([0b01, 0])


def far_apart_bt(path, resolution_m=0.1):
    """Write a .bt of two occupied voxels 6 km apart on every axis; returns `path`."""
    tree = octomap.OcTree(resolution_m)
    for corner in ((-3000.0, -3000.0, -3000.0), (3000.0, 3000.0, 3000.0)):
        tree.updateNode(np.array(corner), True)
    assert tree.writeBinary(str(path).encode())
    return path
