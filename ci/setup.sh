#!/usr/bin/env bash
# Set up everything the workspace needs on a Debian 12 machine; idempotent and quick when done.
#   1. Debian packages from ci/apt-packages.txt (only the missing ones; needs root then)
#   2. .venv made from /usr/bin/python3 with --system-site-packages, pinned ci/requirements.txt
#   3. catkin_make of catkin_ws (only when a package's build files changed)
#   4. the map server's numba kernels, compiled next to their source and keyed by its content
#      (cps_mapping.kernel_cache): no node compiles them during a mission; and the workspace's .pyc
#   5. the pcl_ros plugin-path fix, so that nodelet can load pcl/VoxelGrid
#   6. the fleet's TLS keys and certificates for the Zenoh bridges in .certs (outside git)
#
# CPS_VENV and CPS_APT_PACKAGES override the venv folder and the package list (used by the tests).
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
say() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

# --- 1. Debian packages --------------------------------------------------------------------
[ -r /etc/debian_version ] || die "this project needs Debian 12 (bookworm) and its ROS packages; /etc/debian_version is missing"
apt_list=${CPS_APT_PACKAGES:-ci/apt-packages.txt}
[ -r "$apt_list" ] || die "cannot read the package list $apt_list"
mapfile -t wanted < <(grep -vE '^\s*(#|$)' "$apt_list")
missing=()
for pkg in "${wanted[@]}"; do
  status=$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null || true)
  [ "$status" = "install ok installed" ] || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" -ne 0 ]; then
    die "missing Debian packages: ${missing[*]}
  install them as root:  sudo apt-get update && sudo apt-get install -y --no-install-recommends ${missing[*]}"
  fi
  say "installing ${#missing[@]} Debian package(s): ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q >/tmp/cps-apt-update.log 2>&1 || die "apt-get update failed: no network to Debian's package mirrors? (see /tmp/cps-apt-update.log)"
  apt-get install -y -q --no-install-recommends "${missing[@]}" >/tmp/cps-apt-install.log 2>&1 \
    || die "apt-get install failed; no network to Debian's package mirrors, or a package name unknown? (see /tmp/cps-apt-install.log): $(tail -3 /tmp/cps-apt-install.log)"
fi

# --- 2. the venv ---------------------------------------------------------------------------
venv="${CPS_VENV:-$root/.venv}"
req_hash=$(sha256sum ci/requirements.txt | cut -d' ' -f1)
venv_ok() {
  [ -x "$venv/bin/python" ] && "$venv/bin/python" -c 'import rospy, numpy, yaml' >/dev/null 2>&1
}
if [ -d "$venv" ] && ! venv_ok; then
  say ".venv is broken (its python cannot import rospy/numpy); rebuilding it"
  rm -rf "$venv"
fi
if [ ! -d "$venv" ]; then
  say "creating .venv from /usr/bin/python3 (with Debian's site-packages for ROS)"
  /usr/bin/python3 -m venv --system-site-packages "$venv" || die "cannot create .venv (is python3-venv installed?)"
fi
if [ "$(cat "$venv/.requirements.sha256" 2>/dev/null)" != "$req_hash" ]; then
  say "installing ci/requirements.txt into .venv"
  "$venv/bin/python" -m pip install -q --disable-pip-version-check -r ci/requirements.txt >/tmp/cps-pip.log 2>&1 \
    || die "pip install failed: no network to PyPI? (see /tmp/cps-pip.log): $(tail -3 /tmp/cps-pip.log)"
  echo "$req_hash" >"$venv/.requirements.sha256"
fi
venv_ok || die ".venv still cannot import rospy/numpy/yaml after set-up"

# --- 3. catkin workspace -------------------------------------------------------------------
ws="$root/catkin_ws"
stamp="$ws/devel/.cps_built"
# (__pycache__ is not a build file: a test that imports a node script as a module writes one
# under nodes/, and every later set-up took it for a changed node.)
if [ ! -f "$stamp" ] || [ -n "$(find "$ws/src" -name __pycache__ -prune -o \( -name package.xml -o -name CMakeLists.txt \
     -o -name setup.py -o -name '*.msg' -o -name '*.srv' -o -path '*/nodes/*' \) -newer "$stamp" -print -quit)" ]; then
  say "catkin_make"
  (
    cd "$ws"
    # The venv's python so that catkin's generated scripts and messages use it.
    exec 9>"$ws/.catkin.lock"; flock 9
    catkin_make -DPYTHON_EXECUTABLE="$venv/bin/python" -DCATKIN_ENABLE_TESTING=OFF >/tmp/cps-catkin.log 2>&1
  ) || die "catkin_make failed (see /tmp/cps-catkin.log): $(tail -5 /tmp/cps-catkin.log)"
  touch "$stamp"
fi

# --- 4. the map server's kernels ---------------------------------------------------------------
# Quick when built: the cache folder's key is the source's hash (+ numba and Python versions).
PYTHONPATH="$ws/src/cps_mapping/src${PYTHONPATH:+:$PYTHONPATH}" "$venv/bin/python" -m cps_mapping.build_kernels \
  >/tmp/cps-kernels.log 2>&1 || die "building the map server's kernels failed (see /tmp/cps-kernels.log): $(tail -3 /tmp/cps-kernels.log)"

# --- 4b. the workspace's bytecode ------------------------------------------------------------
# Every node, tool and test process imports the workspace's modules; with no .pyc beside them each
# compiles them anew at its start (~1.5 CPU-s a process: a mission starts ~17, the test suite
# hundreds). Nothing writes them otherwise: the nodes run as `nobody`, who cannot write here, and
# PYTHONDONTWRITEBYTECODE (set on some machines) stops everyone else. compileall writes them
# regardless and skips those up to date; an edited module's stale .pyc is seen by its mtime and
# compiled in memory, as before.
"$venv/bin/python" -m compileall -q -j 0 -x '/numba_kernels/' "$ws/src" "$ws/devel/lib" >/tmp/cps-compileall.log 2>&1 \
  || die "compiling the workspace's Python failed (see /tmp/cps-compileall.log): $(tail -3 /tmp/cps-compileall.log)"

# --- 5. pcl_ros plugin path ----------------------------------------------------------------
# Debian's pcl_ros nodelet description names "lib/libpcl_ros_filters"; pluginlib looks for it as
# <prefix>/lib/lib/libpcl_ros_filters.so on CMAKE_PREFIX_PATH. ci/env.sh puts this prefix there.
fix="$ws/pcl_ros_plugin_prefix/lib/lib"
mkdir -p "$fix"
for lib in /usr/lib/x86_64-linux-gnu/libpcl_ros_*.so /usr/lib/*/libpcl_ros_*.so; do
  [ -e "$lib" ] && ln -sfn "$lib" "$fix/$(basename "$lib")"
done
[ -e "$fix/libpcl_ros_filters.so" ] || die "libpcl_ros_filters.so not found (is libpcl-ros-dev installed?)"

# --- 6. TLS material for the Zenoh bridges ---------------------------------------------------
# The testbed's addresses; for real hosts see catkin_ws/src/cps_link/README.md.
[ -f "$root/.certs/ca.pem" ] || catkin_ws/src/cps_link/scripts/make_certs "$root/.certs" >/dev/null \
  || die "could not make the bridges' certificates (is openssl installed?)"
exit 0
