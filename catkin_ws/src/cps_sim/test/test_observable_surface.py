"""The observable surface ray-cast from sensor positions: what a wall hides is not observable,
what is out of range is not, and the result depends only on the truth and the positions."""

import numpy as np

from cps_sim.ground_truth import observable_from_positions, positions_every

RES = 0.1


def _slab(x_index, y_range, z_range):
    """Voxel centres of a one-voxel-thick wall at x index `x_index`."""
    ys, zs = np.meshgrid(np.arange(*y_range), np.arange(*z_range), indexing="ij")
    index = np.stack([np.full(ys.size, x_index), ys.ravel(), zs.ravel()], axis=1)
    return (index + 0.5) * RES


def test_a_wall_hides_what_is_behind_it():
    near_wall = _slab(10, (-10, 10), (0, 10))  # x = 1.0 m, 2 m wide, 1 m high
    far_wall = _slab(20, (-5, 5), (2, 8))  # x = 2.0 m, entirely behind it
    truth = np.vstack([near_wall, far_wall])
    seen = observable_from_positions(truth, RES, [[0.0, 0.0, 0.5]], max_range_m=5.0)
    seen_x = np.round(seen[:, 0], 2)
    assert (seen_x == 1.05).sum() == len(near_wall)
    assert not (seen_x == 2.05).any()


def test_range_limits_and_the_other_side():
    wall = _slab(10, (-3, 3), (0, 5))
    assert len(observable_from_positions(wall, RES, [[0.0, 0.0, 0.2]], max_range_m=0.5)) == 0
    both_sides = observable_from_positions(wall, RES, [[0.0, 0.0, 0.2], [2.0, 0.0, 0.2]], max_range_m=3.0)
    assert len(both_sides) == len(wall)


def test_positions_are_thinned_by_distance():
    path = np.array([[0.0, 0, 0], [0.3, 0, 0], [1.1, 0, 0], [1.5, 0, 0], [np.nan, 0, 0], [2.2, 0, 0]])
    assert positions_every(path, 1.0).tolist() == [[0.0, 0, 0], [1.1, 0, 0], [2.2, 0, 0]]
