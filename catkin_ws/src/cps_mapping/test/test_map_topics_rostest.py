"""The package's rostest file, run as a user runs it (`rostest cps_mapping map_topics.test`, its own master):
the map server publishes octomap_server's map topics and its statistics before any cloud arrives."""

import pytest

from cps_harness.testing import run_rostest

pytestmark = pytest.mark.rostest


def test_map_topics_rostest():
    result = run_rostest("cps_mapping", "map_topics.test")
    assert result.returncode == 0, result.stdout[-4000:]
