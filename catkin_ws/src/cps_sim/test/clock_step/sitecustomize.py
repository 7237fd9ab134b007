"""Fault injection for test_estop_ros: while the file $CPS_TEST_CLOCK_STEP_FILE exists, this
process's wall clock (time.time, what NTP steps) reads $CPS_TEST_CLOCK_STEP_S off (default -30 s)."""

import os
import time

_STEP_FILE = os.environ.get("CPS_TEST_CLOCK_STEP_FILE")
if _STEP_FILE:
    _wall = time.time
    _step_s = float(os.environ.get("CPS_TEST_CLOCK_STEP_S", "-30"))

    def _stepped():
        return _wall() + (_step_s if os.path.exists(_STEP_FILE) else 0.0)

    time.time = _stepped
