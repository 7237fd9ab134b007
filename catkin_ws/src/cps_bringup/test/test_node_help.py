"""Every node and command of the workspace answers --help: exit 0, a description, no master needed."""

import glob
import os
import subprocess
import sys

import pytest

SRC = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", ".."))
NODES = sorted(glob.glob(os.path.join(SRC, "*", "nodes", "*")))


def test_the_workspace_has_nodes():
    assert len(NODES) >= 16, NODES


@pytest.mark.parametrize("node", NODES, ids=[os.path.relpath(n, SRC) for n in NODES])
def test_node_answers_help_without_a_master(node):
    # A master URI nobody listens on: a node that tried to register would hang or fail.
    env = dict(os.environ, ROS_MASTER_URI="http://127.0.0.1:1")
    result = subprocess.run([sys.executable, node, "--help"], capture_output=True, text=True, timeout=60, env=env)
    assert result.returncode == 0, result.stdout + result.stderr
    assert len(result.stdout.strip().splitlines()) >= 2, result.stdout
