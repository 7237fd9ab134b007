#!/usr/bin/env bash
# Every package's tests in one pytest run (rostest-style tests start their own private roscore).
# Expects ci/env.sh to be sourced (make test does that).
set -uo pipefail
cd "$CPS_ROOT"
python -m pytest catkin_ws/src "$@"
rc=$?
# pytest's 5 means it collected no test: that is a failure of the suite, not a pass.
[ "$rc" -eq 5 ] && echo "no tests were collected" >&2
exit "$rc"
