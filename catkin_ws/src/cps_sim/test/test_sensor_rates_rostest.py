"""The package's rostest file, run as a user runs it (`rostest cps_sim sensor_rates.test`, its own master):
the simulator's sensors keep their rates (stock hztest)."""

import pytest

from cps_harness.testing import run_rostest

pytestmark = [pytest.mark.rostest, pytest.mark.waiting]


def test_sensor_rates_rostest():
    result = run_rostest("cps_sim", "sensor_rates.test")
    assert result.returncode == 0, result.stdout[-4000:]
