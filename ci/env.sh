# Source this file to get a shell with the workspace, the venv and the pcl_ros fix:
#   source ci/env.sh
_cps_root=$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)
# shellcheck disable=SC1091
source "$_cps_root/catkin_ws/devel/setup.bash"
export VIRTUAL_ENV="$_cps_root/.venv"
export PATH="$VIRTUAL_ENV/bin:$PATH"
export CMAKE_PREFIX_PATH="$_cps_root/catkin_ws/pcl_ros_plugin_prefix:$CMAKE_PREFIX_PATH"
export CPS_ROOT="$_cps_root"
unset _cps_root
