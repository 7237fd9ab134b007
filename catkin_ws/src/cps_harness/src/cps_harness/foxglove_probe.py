"""A viewer no one here wrote, for the Foxglove endpoint's tests: the npm `@foxglove/ws-protocol`
client run with node (js/foxglove_probe.js), installed by `install_client` into a folder outside
git from the npm registry at pinned versions.

`probe(url, seconds, topics)` returns its JSON report: the channels advertised, per topic the
messages received and decoded with their advertised schema, decode errors, and a summary of the
last message. `stalled_viewer(url)` starts one that subscribes and then never reads.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from typing import List, Optional

# The client and what it needs to decode the SDK's protobuf schemas, pinned.
NPM_PACKAGES = ("@foxglove/ws-protocol@0.8.0", "protobufjs@7.6.6", "ws@8.23.0")
SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "js", "foxglove_probe.js")
# The workspace's out/ (ignored by git): the installed client is kept between runs.
DEFAULT_FOLDER = os.path.join(os.path.dirname(os.path.abspath(__file__)), *[os.pardir] * 5, "out", "npm-foxglove-probe")


class ClientMissing(RuntimeError):
    """node or npm is absent, or the npm registry could not be reached: the message says which."""


def _stamp(folder):
    return os.path.join(folder, ".installed")


def install_client(folder: Optional[str] = None, timeout_s: float = 300.0, packages=NPM_PACKAGES) -> str:
    """The node_modules folder holding `packages` (pinned), installed into `folder` if not there yet."""
    folder = os.path.abspath(folder or DEFAULT_FOLDER)
    modules = os.path.join(folder, "node_modules")
    wanted = "\n".join(packages)
    if os.path.exists(_stamp(folder)) and open(_stamp(folder)).read() == wanted:
        return modules
    for tool in ("node", "npm"):
        if shutil.which(tool) is None:
            raise ClientMissing(f"{tool} is not installed (Debian: apt-get install nodejs npm)")
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "package.json"), "w") as stream:
        json.dump({"name": "cps-foxglove-probe", "private": True}, stream)
    try:
        result = subprocess.run(
            ["npm", "install", "--no-audit", "--no-fund", "--ignore-scripts", "--save-exact", *packages],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )
    except subprocess.TimeoutExpired as exc:
        raise ClientMissing(f"npm install {' '.join(packages)} did not finish in {timeout_s:.0f} s") from exc
    if result.returncode != 0:
        raise ClientMissing(
            f"npm install {' '.join(packages)} failed (is the npm registry reachable?): "
            f"{(result.stderr or result.stdout).strip()[-800:]}"
        )
    with open(_stamp(folder), "w") as stream:
        stream.write(wanted)
    return modules


def _argv(url, seconds, topics, stall, calls=()):
    argv = ["node", SCRIPT, url, str(seconds), json.dumps(list(topics or [])), *(["--stall"] if stall else [])]
    for service, request in calls:
        argv += ["--call", service, json.dumps(request)]
    return argv


def _env(modules):
    return {**os.environ, "NODE_PATH": modules}


def probe_argv(url: str, seconds: float, topics: List[str], modules: str) -> List[str]:
    """The probe as one command (for running it elsewhere, e.g. on a mission's twin side): it
    prints its JSON report as the last line of its output."""
    return ["env", f"NODE_PATH={modules}", *_argv(url, seconds, topics, False)]


def probe(url: str, seconds: float, topics: List[str] = (), modules: Optional[str] = None, calls=()) -> dict:
    """Connect to `url` for `seconds`, subscribe `topics` (empty: all), call each (service, request
    dict) of `calls`, and return the report."""
    modules = modules or install_client()
    result = subprocess.run(
        _argv(url, seconds, topics, False, calls),
        env=_env(modules),
        capture_output=True,
        text=True,
        timeout=seconds + 30,
    )
    if result.returncode != 0 or not result.stdout.strip():
        raise RuntimeError(f"foxglove probe failed ({result.returncode}): {result.stderr.strip()[-800:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def stalled_viewer(url: str, seconds: float, modules: Optional[str] = None) -> subprocess.Popen:
    """A viewer that subscribes every channel and never reads again, for `seconds`; the caller
    waits for it (or kills it)."""
    modules = modules or install_client()
    return subprocess.Popen(
        _argv(url, seconds, [], True), env=_env(modules), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def wait_paused(stalled: subprocess.Popen, timeout_s: float = 10.0) -> bool:
    """True once a `stalled_viewer` says it has subscribed and stopped reading its socket."""
    import selectors

    with selectors.DefaultSelector() as selector:
        selector.register(stalled.stderr, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and selector.select(deadline - time.monotonic()):
            line = stalled.stderr.readline()
            if not line or line.strip() == "paused":
                return bool(line)
    return False


if __name__ == "__main__":  # python -m cps_harness.foxglove_probe ws://127.0.0.1:8765 [seconds]
    print(json.dumps(probe(sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 5.0), indent=1))
