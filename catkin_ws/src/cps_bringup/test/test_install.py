"""`catkin_make install` gives a working install space: resources found through rospkg/catkin,
nodes start from it (the map server with its kernels built at install), and the front door without
setup.bash says what to do."""

import os
import subprocess
import sys

import pytest

from cps_fleet import names
from cps_ros.processes import RosGraph

SRC = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", ".."))
WORKSPACE = os.path.dirname(SRC)


def _clean_env():
    """This environment without the workspace's devel space and source tree on any path."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k
        not in (
            "CMAKE_PREFIX_PATH",
            "ROS_PACKAGE_PATH",
            "PYTHONPATH",
            "LD_LIBRARY_PATH",
            "PKG_CONFIG_PATH",
            "CPS_FLEET_FILE",
        )
    }
    env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if WORKSPACE not in p)
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env["PATH"]
    return env


@pytest.fixture(scope="module")
def install_space(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("catkin_install")
    result = subprocess.run(
        [
            "catkin_make",
            "--source",
            SRC,
            "--build",
            str(tmp / "build"),
            f"-DCATKIN_DEVEL_PREFIX={tmp / 'devel'}",
            f"-DCMAKE_INSTALL_PREFIX={tmp / 'install'}",
            f"-DPYTHON_EXECUTABLE={sys.executable}",
            "-DCATKIN_ENABLE_TESTING=OFF",
            "install",
        ],
        cwd=str(tmp),
        env=_clean_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]
    # The source tree's kernels (built by the set-up before any test) are reused, not compiled again.
    assert "map server kernels copied from" in result.stdout, result.stdout[-4000:]
    return tmp / "install"


def _in_install(install, command, env=None, **kwargs):
    script = f"source {install}/setup.bash && {command}"
    return subprocess.run(["bash", "-c", script], env={**_clean_env(), **(env or {})}, **kwargs)


@pytest.mark.ros
@pytest.mark.slow
def test_install_space_finds_its_resources(install_space):
    code = (
        "from cps_fleet.fleet import load_fleet; from cps_ros.processes import find_node; "
        "import cps_bringup; f = load_fleet(); "
        "print(f.path, f.site_path, find_node('cps_mapping', 'map_server'), cps_bringup.__file__, sep='\\n')"
    )
    result = _in_install(install_space, f'python -c "{code}"', capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.split()
    print("\n".join(lines))
    assert all(line.startswith(str(install_space)) for line in lines), lines
    for path in lines:
        assert os.path.exists(path), path


@pytest.mark.ros
@pytest.mark.slow
def test_a_node_starts_from_the_install_space(install_space, tmp_path):
    with RosGraph(log_dir=str(tmp_path)) as graph:
        proc = subprocess.Popen(
            [
                "bash",
                "-c",
                f"source {install_space}/setup.bash && exec rosrun cps_mapping map_server __ns:={names.absolute(names.TWIN_NS)} "
                f"_map_file:={tmp_path / 'map.bt'}",
            ],
            env={**_clean_env(), "ROS_MASTER_URI": graph.uri, "ROS_HOME": str(tmp_path)},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            graph.wait_for_topic(names.absolute(names.in_twin(names.OCTOMAP_BINARY)), timeout_s=60)
            graph.wait_for_service(
                names.absolute(names.in_twin(names.private(names.MAP_SERVER, names.CLEAR_BBX))), timeout_s=30
            )
            # catkin_make install built the kernels in the install space: the node compiled nothing.
            ready = subprocess.run(
                [
                    "rostopic",
                    "echo",
                    "-n",
                    "1",
                    names.absolute(names.in_twin(names.private(names.MAP_SERVER, names.READY))) + "/message",
                ],
                env={**os.environ, "ROS_MASTER_URI": graph.uri},
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert "kernels loaded from the build-time cache" in ready.stdout, ready.stdout + ready.stderr
            # rosrun execs the installed node: its Python path is the install space's, not the workspace's.
            with open(f"/proc/{proc.pid}/environ", "rb") as stream:
                environ = dict(item.split(b"=", 1) for item in stream.read().split(b"\0") if b"=" in item)
            python_path = environ[b"PYTHONPATH"].decode().split(os.pathsep)
            assert any(p.startswith(str(install_space)) for p in python_path), python_path
            assert not any(p.startswith(WORKSPACE) for p in python_path), python_path
        finally:
            graph.stop(proc)


@pytest.mark.ros
@pytest.mark.slow
def test_install_space_without_setup_bash_says_what_to_do(install_space):
    result = subprocess.run(
        [sys.executable, str(install_space / "lib" / "cps_bringup" / "cps_bringup"), "--help"],
        env=_clean_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0
    assert f"source {install_space}/setup.bash" in result.stderr, result.stderr
