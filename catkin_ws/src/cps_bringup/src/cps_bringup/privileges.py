"""Nodes do not need root: only the link (ip netns, tc, entering a namespace) does.

Started as root, the supervisor runs every node through `setpriv` as an unprivileged user; the
mission folder is handed to that user so the nodes can write their logs, CSVs and the map.
"""
import glob
import grp
import os
import pwd
import shutil
import subprocess
import sys

DEFAULT_USER = "nobody"
# The map server's compiled kernels (numba), built once by the user who starts the bringup and
# copied into each mission's cache: the unprivileged nodes cannot write next to the sources, and
# compiling them at every start took the map server 20 s (70 s on a loaded machine) before its
# first insertion.
SHARED_NUMBA_CACHE = os.path.join(os.path.expanduser("~"), ".cache", "cps_numba")


class PrivilegeError(RuntimeError):
    """The nodes cannot run as the chosen user; the message says why and what to do."""


def node_user(requested):
    """The user the nodes run as: `requested`, else DEFAULT_USER when this process is root, else
    None (keep the current user). 'root' keeps root."""
    if requested == "root" or (requested is None and os.geteuid() != 0):
        return None
    return requested or DEFAULT_USER


def user_prefix(user):
    """argv that runs a command as `user` with its primary group and no supplementary groups."""
    try:
        entry = pwd.getpwnam(user)
    except KeyError as exc:
        raise PrivilegeError(f"no user named '{user}'") from exc
    group = grp.getgrgid(entry.pw_gid).gr_name
    return ["setpriv", f"--reuid={entry.pw_uid}", f"--regid={group}", "--clear-groups", "--"]


def user_env(log_dir):
    """Environment for nodes run as another user: a home and a numba cache they can write (the
    user's own home may not exist; numba caches next to the sources otherwise)."""
    return {"HOME": os.path.join(log_dir, "home"), "NUMBA_CACHE_DIR": os.path.join(log_dir, "numba_cache")}


def hand_over(user, out_dir, log_dir):
    """Give `user` the mission folder (with ROS's log folder and the `user_env` folders in it);
    PrivilegeError if it cannot reach it."""
    if os.geteuid() != 0:
        raise PrivilegeError(f"running the nodes as '{user}' needs root")
    entry = pwd.getpwnam(user)
    for folder in (log_dir, *user_env(log_dir).values()):
        os.makedirs(folder, exist_ok=True)
    try:
        copy_compiled_kernels(user_env(log_dir)["NUMBA_CACHE_DIR"])
    except (OSError, subprocess.CalledProcessError):
        pass  # a speed-up only: without it the map server compiles its kernels at its start
    for folder in (out_dir, log_dir):
        for root, dirs, files in os.walk(folder):
            for name in [root] + [os.path.join(root, f) for f in dirs + files]:
                os.chown(name, entry.pw_uid, entry.pw_gid)
    check = subprocess.run([*user_prefix(user), "test", "-w", out_dir, "-a", "-x", out_dir, "-a", "-w", log_dir],
                           capture_output=True)
    if check.returncode != 0:
        raise PrivilegeError(f"the nodes run as '{user}' (not root) but cannot write {out_dir}: a folder above it "
                             f"is closed to that user. Choose an --out that '{user}' can reach, or --run-as root")


def copy_compiled_kernels(numba_cache_dir, shared=SHARED_NUMBA_CACHE):
    """Fill `numba_cache_dir` with the map server's compiled kernels from `shared`, compiling them
    there first if they are missing or older than their source."""
    from cps_mapping import log_odds_grid

    source_mtime = os.path.getmtime(log_odds_grid.__file__)
    indexes = glob.glob(os.path.join(shared, "**", "log_odds_grid.*.nbi"), recursive=True)
    if not indexes or min(os.path.getmtime(i) for i in indexes) < source_mtime:
        subprocess.run([sys.executable, "-c", "from cps_mapping.log_odds_grid import warm_up; warm_up()"],
                       env={**os.environ, "NUMBA_CACHE_DIR": shared}, check=True, capture_output=True)
    shutil.copytree(shared, numba_cache_dir, dirs_exist_ok=True)
