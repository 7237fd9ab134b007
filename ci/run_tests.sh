#!/usr/bin/env bash
# Every package's tests: ruff, then one pytest run on both cores (pytest-xdist, `--dist loadgroup`:
# the missions on one worker, one at a time; a third worker runs the modules marked `waiting`, which
# mostly wait, beside the two CPU-bound ones; see catkin_ws/src/conftest.py). The packages' rostest
# `.test` files run in it too, each as a test that runs `rostest` (its own master on a free port). Writes out/test/junit.xml and out/test/durations.md (where the time
# went) and prints the test time last, beside the budget. Expects ci/env.sh to be sourced (make test
# does that); CPS_SETUP_S, if set, is the set-up's time (reported apart from the tests').
set -uo pipefail
cd "$CPS_ROOT"
BUDGET_S=600  # the suite's budget: ten minutes of tests on this 2-core machine
export CPS_TEST_OUT="${CPS_TEST_OUT:-$CPS_ROOT/out/test}"  # the reference mission keeps its small files here too
report_dir="$CPS_TEST_OUT"
mkdir -p "$report_dir"
now() { date +%s.%N; }
t0=$(now)
# ruff (ruff.toml): lint and format check of every Python file, nodes included; a finding fails the
# run, after the tests have run.
lint_rc=0
ruff check . && ruff format --check . || lint_rc=1
if [ "$lint_rc" -eq 0 ]; then echo "ruff: lint and format clean"; else echo "ruff: findings above; the run fails" >&2; fi
# --max-worker-restart 0: a worker that dies (final9: the kernel's OOM killer) ends the run with a
# failure. Replaced, pytest-xdist 3.6's loadgroup scheduler left both workers waiting for work
# forever (pytest-xdist issues 1323 and 1327): CI would have hung to its 90 min.
parallel=(-n 3 --dist loadgroup --max-worker-restart 0)
for arg in "$@"; do
  case "$arg" in -n|-n*|--numprocesses*|-p) parallel=() ;; esac
done
t_pytest=$(now)
# PYTHONDONTWRITEBYTECODE (set on some machines) also stops pytest from caching its rewritten test
# modules: every worker then rewrites and compiles all ~150 at collection (9.4 CPU-s a collection
# here, 3.4 with the cache). For this run it is off; __pycache__ is ignored by git.
PYTHONDONTWRITEBYTECODE= python -m pytest --durations=20 "${parallel[@]}" --junitxml="$report_dir/junit.xml" \
  --durations-table="$report_dir/durations.md" catkin_ws/src "$@"
rc=$?
t_end=$(now)
[ "$lint_rc" -ne 0 ] && [ "$rc" -eq 0 ] && rc=1  # ruff printed its findings before the tests
# pytest's 5 means it collected no test: that is a failure of the suite, not a pass.
[ "$rc" -eq 5 ] && echo "no tests were collected" >&2
awk -v t0="$t0" -v p="$t_pytest" -v e="$t_end" -v b="$BUDGET_S" -v s="${CPS_SETUP_S:-}" -v d="$report_dir" 'BEGIN {
  total = e - t0
  printf "where the time went: %s/durations.md; junit: %s/junit.xml\n", d, d
  if (s != "") printf "set-up: %.0f s (not counted in the tests)\n", s
  printf "tests: %.0f s of the %d s budget (ruff %.0f s, pytest %.0f s)%s\n", total, b, p - t0, e - p, (total > b ? ": OVER BUDGET" : "")
}'
exit "$rc"
