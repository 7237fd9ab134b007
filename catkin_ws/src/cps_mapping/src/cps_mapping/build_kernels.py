"""Build the map server's kernels where the code is built (`make setup`, `catkin_make install`):
`python -m cps_mapping.build_kernels`. The cache mechanism itself is cps_mapping.kernel_cache;
this module only runs the map's warm-up through it, so the two do not import each other."""

import os
import shutil
import stat
import time

from cps_mapping import log_odds_grid
from cps_mapping.kernel_cache import BUILT_MARKER, MAP_KERNELS_MODULE, cache_dir


def _open_to_everyone(folder):
    """a+rX on `folder` and everything in it: the nodes (as `nobody`) read the kernels."""
    for root, dirs, files in os.walk(folder):
        for name in [root] + [os.path.join(root, n) for n in dirs + files]:
            mode = os.stat(name).st_mode
            extra = stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH
            if stat.S_ISDIR(mode):
                extra |= stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH
            os.chmod(name, mode | extra)


def build():
    """Compile the map server's kernels into their cache folder (or find them there) and mark it
    built; older keys of the same folder are removed. Returns (folder, seconds, kernels compiled)."""
    t0 = time.monotonic()
    report = log_odds_grid.warm_up()
    folder = cache_dir(log_odds_grid.__file__)
    if not os.access(folder, os.W_OK):
        raise PermissionError(f"cannot write the kernel cache {folder}")
    with open(os.path.join(folder, BUILT_MARKER), "w") as stream:
        stream.write(f"{MAP_KERNELS_MODULE}: {', '.join(report.compiled) or 'nothing'} compiled\n")
    parent = os.path.dirname(folder)
    for other in os.listdir(parent):
        if other != os.path.basename(folder):
            shutil.rmtree(os.path.join(parent, other), ignore_errors=True)
    _open_to_everyone(os.path.dirname(parent))
    return folder, time.monotonic() - t0, report.compiled


def main():
    folder, seconds, compiled = build()
    what = f"compiled {len(compiled)} kernel(s)" if compiled else "already built"
    print(f"[kernels] map server kernels {what} in {seconds:.1f} s: {folder}")


if __name__ == "__main__":
    main()
