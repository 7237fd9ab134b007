"""Digital tissue, part 1: voxel-grid downsampling, Draco point-cloud transport, a rate limiter that keeps its rate, and live topic statistics."""

from cps_transport.voxel_grid_command import voxel_nodelet_args, voxel_nodelet_params

__all__ = ["voxel_nodelet_args", "voxel_nodelet_params"]
