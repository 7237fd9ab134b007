"""Maps built as the fleet builds them (fleet.yaml's `mapping.sensor_model`), for the tests."""

from cps_fleet.fleet import load_fleet
from cps_mapping.fused_map import FusedLogOddsMap, new_octree

MAPPING = load_fleet().mapping


def new_map(resolution_m, exact_free_space=True, **kwargs):
    """A FusedLogOddsMap with the fleet's sensor model; exact insertion unless told otherwise, as
    the tests compare it with plain OctoMap insertion."""
    return FusedLogOddsMap(resolution_m, MAPPING.sensor_model, exact_free_space=exact_free_space, **kwargs)


def plain_tree(resolution_m):
    """Plain OctoMap (octomap-python's OcTree) with the fleet's sensor model."""
    return new_octree(resolution_m, MAPPING.sensor_model)
