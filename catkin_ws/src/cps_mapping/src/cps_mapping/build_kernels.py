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


def seed_from(package_folder):
    """Copy the kernels another copy of this package built (`package_folder`: e.g. the source tree,
    where `make setup` built them) when they are complete and of this source's content: `catkin_make
    install` then compiles nothing (20-70 s otherwise). Returns whether it copied."""
    mine = cache_dir(log_odds_grid.__file__)
    theirs = cache_dir(os.path.join(package_folder, os.path.basename(log_odds_grid.__file__)))
    if os.path.basename(theirs) != os.path.basename(mine) or os.path.exists(os.path.join(mine, BUILT_MARKER)):
        return False
    if not os.path.exists(os.path.join(theirs, BUILT_MARKER)) or os.path.abspath(theirs) == os.path.abspath(mine):
        return False
    shutil.rmtree(mine, ignore_errors=True)
    shutil.copytree(theirs, mine)
    return True


def main(argv=None):
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--seed-from",
        metavar="PACKAGE_FOLDER",
        help="another copy of cps_mapping's source folder whose built kernels to reuse if they match",
    )
    args = parser.parse_args(argv)
    if args.seed_from and seed_from(args.seed_from):
        print(f"[kernels] map server kernels copied from {args.seed_from}")
    folder, seconds, compiled = build()
    what = f"compiled {len(compiled)} kernel(s)" if compiled else "already built"
    print(f"[kernels] map server kernels {what} in {seconds:.1f} s: {folder}")


if __name__ == "__main__":
    main()
