"""Nodes do not need root: only the link (ip netns, tc, entering a namespace) does.

Started as root, the supervisor runs every node through `setpriv` as an unprivileged user; the
mission folder is handed to that user so the nodes can write their logs, CSVs and the map, and the
code (with the map server's kernels, built before the mission: `ensure_map_kernels`) must be
readable by it (`check_code_readable`).
"""

import grp
import os
import pwd
import subprocess
import sys

DEFAULT_USER = "nobody"


class PrivilegeError(RuntimeError):
    """The nodes cannot run as the chosen user; the message says why and what to do."""


def node_user(requested):
    """The user the nodes run as: `requested`, else DEFAULT_USER when this process is root, else
    None (keep the current user). 'root' keeps root."""
    if requested == "root" or (requested is None and os.geteuid() != 0):
        return None
    return requested or DEFAULT_USER


def user_prefix(user):
    """argv that runs a command as `user` with its primary group and no supplementary groups. The
    kernel clears a process's die-with-parent signal when its uid changes: `--pdeathsig keep` sets
    it again, or a node would outlive a bringup that was killed."""
    try:
        entry = pwd.getpwnam(user)
    except KeyError as exc:
        raise PrivilegeError(f"no user named '{user}'") from exc
    group = grp.getgrgid(entry.pw_gid).gr_name
    return ["setpriv", f"--reuid={entry.pw_uid}", f"--regid={group}", "--clear-groups", "--pdeathsig", "keep", "--"]


def user_env(log_dir):
    """Environment for nodes run as another user: a home they can write (the user's own home may
    not exist)."""
    return {"HOME": os.path.join(log_dir, "home")}


def hand_over(user, out_dir, log_dir):
    """Give `user` the mission folder (with ROS's log folder and the `user_env` folders in it);
    PrivilegeError if it cannot reach it."""
    if os.geteuid() != 0:
        raise PrivilegeError(f"running the nodes as '{user}' needs root")
    entry = pwd.getpwnam(user)
    for folder in (log_dir, *user_env(log_dir).values()):
        os.makedirs(folder, exist_ok=True)
    for folder in (out_dir, log_dir):
        for root, dirs, files in os.walk(folder):
            for name in [root] + [os.path.join(root, f) for f in dirs + files]:
                os.chown(name, entry.pw_uid, entry.pw_gid)
    check = subprocess.run(
        [*user_prefix(user), "test", "-w", out_dir, "-a", "-x", out_dir, "-a", "-w", log_dir], capture_output=True
    )
    if check.returncode != 0:
        raise PrivilegeError(
            f"the nodes run as '{user}' (not root) but cannot write {out_dir}: a folder above it "
            f"is closed to that user. Choose an --out that '{user}' can reach, or --run-as root"
        )


def check_code_readable(user, specs):
    """PrivilegeError naming the first file of the code (a node's program, the python, the map
    server's kernels) or input (a file parameter) that `user` cannot read: a folder above it is
    closed to that user, and the node would only fail later with an exit code."""
    from cps_mapping import kernel_cache

    kernels = kernel_cache.cache_dir(kernel_cache.map_kernels_file())
    paths = [sys.executable, kernel_cache.map_kernels_file(), *([kernels] if os.path.isdir(kernels) else [])]
    paths += [arg for spec in specs for arg in spec.argv if os.path.isabs(arg) and os.path.isfile(arg)]
    # Files the nodes are given as parameters (_name:=/a/file: a video trace, site changes, a baseline).
    values = [arg.split(":=", 1)[1] for spec in specs for arg in spec.argv if arg.startswith("_") and ":=" in arg]
    inputs = [v for v in values if os.path.isabs(v) and os.path.isfile(v)]
    paths = list(dict.fromkeys(paths + inputs))
    probe = 'for f; do test -r "$f" || { echo "$f"; exit 1; }; done'
    check = subprocess.run([*user_prefix(user), "sh", "-c", probe, "sh", *paths], capture_output=True, text=True)
    if check.returncode != 0:
        path = check.stdout.strip() or paths[0]
        what = "an input file" if path in inputs else "the code"
        raise PrivilegeError(
            f"the nodes run as '{user}' (not root) but cannot read {what}: {path} (a folder above "
            f"it is closed to that user, e.g. a 0700 temporary folder). Put "
            f"{'it' if path in inputs else 'the checkout'} where '{user}' can read it (o+rx on the folders "
            "above it), or --run-as root"
        )


def ensure_map_kernels(log=print):
    """Build the map server's kernels before the mission when this source has none built (`make
    setup` normally did), so that no node compiles during the mission; the nodes only read them."""
    from cps_mapping import kernel_cache

    if kernel_cache.is_built():
        return
    log("[bringup] building the map server's kernels for this source (once; `make setup` does it too)")
    built = subprocess.run([sys.executable, "-m", "cps_mapping.build_kernels"], capture_output=True, text=True)
    if built.returncode != 0:
        tail = (built.stderr or built.stdout).strip().splitlines()[-1:]
        log(
            f"[bringup] WARNING: could not build them ({' '.join(tail)}); the map server compiles them at its "
            f"start and the clouds wait for it"
        )
    else:
        log(built.stdout.strip())
