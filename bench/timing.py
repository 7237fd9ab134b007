"""The timing loop the allocator benchmarks share, for ours and the anchor alike (bench/ only:
no runtime package times itself). Imported by scripts run as `python bench/<name>.py`, whose own
folder is first on sys.path."""

import statistics
import time


def median_max_ms(fn, repeats, warmup=False):
    """(median, max) wall time of `fn()` over `repeats` calls, ms; with `warmup` one untimed call
    first (imports, first-call caches)."""
    if warmup:
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(1000.0 * (time.perf_counter() - t0))
    return statistics.median(samples), max(samples)
