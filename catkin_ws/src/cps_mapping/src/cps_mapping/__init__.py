"""Digital twin, part 1: the multi-robot OctoMap server, map scoring against ground truth, persistence and change detection."""
