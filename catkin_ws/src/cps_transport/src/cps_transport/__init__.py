"""Digital tissue, part 1: voxel-grid downsampling, Draco point-cloud transport, a rate limiter that keeps its rate, and live topic statistics."""
