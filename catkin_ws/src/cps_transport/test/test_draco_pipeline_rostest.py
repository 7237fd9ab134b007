"""The package's rostest file, run as a user runs it (`rostest cps_transport draco_pipeline.test`, its own master):
a simulated depth cloud goes through the Draco encoder, the rate limiter and the decoder, and every stage publishes (stock publishtest)."""

import pytest

from cps_harness.testing import run_rostest

pytestmark = pytest.mark.rostest


def test_draco_pipeline_rostest():
    result = run_rostest("cps_transport", "draco_pipeline.test")
    assert result.returncode == 0, result.stdout[-4000:]
