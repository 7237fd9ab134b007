#!/usr/bin/env bash
# Every package's tests in one pytest run (rostest-style tests start their own private roscore),
# preceded by the rostest `.test` files (each starts its own master on a free port) unless the
# arguments select a subset (-m, -k, paths). Both counts appear in pytest's summary; pytest's
# closing line stays last. Expects ci/env.sh to be sourced (make test does that).
set -uo pipefail
cd "$CPS_ROOT"
# ruff (ruff.toml): lint and format check of every Python file, nodes included; a finding fails the
# run, after the tests have run.
lint_rc=0
ruff check . && ruff format --check . || lint_rc=1
if [ "$lint_rc" -eq 0 ]; then echo "ruff: lint and format clean"; else echo "ruff: findings above; the run fails" >&2; fi
run_rostest=1
for arg in "$@"; do
  case "$arg" in -m|-m*|-k|-k*|catkin_ws/*|*.py|*::*) run_rostest=0 ;; esac
done
rostest_summary=""
if [ "$run_rostest" -eq 1 ]; then
  rostest_summary=$(mktemp)
  rostest_home=$(mktemp -d)
  passed=0; failed=0; failed_files=""
  for test_file in catkin_ws/src/*/test/*.test; do
    echo "rostest $test_file"
    if ROS_HOME="$rostest_home" timeout 600 rostest "$test_file" >"$rostest_home/$(basename "$test_file").log" 2>&1; then
      passed=$((passed + 1))
    else
      failed=$((failed + 1)); failed_files="$failed_files $test_file"
      tail -30 "$rostest_home/$(basename "$test_file").log"
    fi
  done
  echo "rostest: $passed passed, $failed failed${failed_files:+ (failed:$failed_files)}" >"$rostest_summary"
  export CPS_ROSTEST_SUMMARY="$rostest_summary"
fi
python -m pytest --durations=20 catkin_ws/src "$@"
rc=$?
[ "$lint_rc" -ne 0 ] && [ "$rc" -eq 0 ] && rc=1  # ruff printed its findings before the tests
# pytest's 5 means it collected no test: that is a failure of the suite, not a pass.
[ "$rc" -eq 5 ] && echo "no tests were collected" >&2
if [ -n "$rostest_summary" ]; then
  grep -q ", 0 failed" "$rostest_summary" || { [ "$rc" -eq 0 ] && rc=1; }
  rm -f "$rostest_summary"
fi
exit "$rc"
