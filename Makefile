# The two front-door commands: `make demo` runs the mission, `make test` runs every test.
# Each target sets up what it needs first (Debian packages, .venv, catkin build); see ci/setup.sh.
SHELL := /bin/bash
ENV := source ci/env.sh &&
PYTEST_ARGS ?=

.PHONY: setup test test-unit demo monitor monitor-eval experiments bench clean

setup:
	@bash ci/setup.sh

# The set-up's time is reported apart from the tests' (ci/run_tests.sh prints both, the tests' last).
test:
	@t0=$$(date +%s.%N); bash ci/setup.sh && setup_s=$$(awk -v t0=$$t0 -v t1=$$(date +%s.%N) 'BEGIN {print t1 - t0}') \
	  && $(ENV) CPS_SETUP_S=$$setup_s bash ci/run_tests.sh $(PYTEST_ARGS)

# The quick tests that need no ROS master (under a minute; `make test` runs them all).
test-unit: setup
	@$(ENV) bash ci/run_tests.sh -m "unit and not slow" $(PYTEST_ARGS)

demo: setup
	@$(ENV) python catkin_ws/src/cps_experiments/nodes/demo $(DEMO_ARGS)

# The monitoring mission against the map the last `make demo` saved (out/demo/map.bt).
monitor: setup
	@$(ENV) python catkin_ws/src/cps_experiments/nodes/monitor $(MONITOR_ARGS)

# N monitoring missions against out/demo/map.bt on site changes drawn from SEED (half with champ and
# iris, half with the whole fleet), scored on what ran live: out/monitor-eval/results.md. The seeds
# the rules were tuned on (cps_experiments.monitor_eval.TUNING_SEEDS) are refused unless --tuning.
SCENARIOS ?= 12
SEED ?= 70873
monitor-eval: setup
	@$(ENV) python catkin_ws/src/cps_experiments/nodes/monitor_eval --scenarios $(SCENARIOS) --seed $(SEED) $(MONITOR_EVAL_ARGS)

experiments: setup
	@$(ENV) python catkin_ws/src/cps_experiments/nodes/experiments $(EXPERIMENT_ARGS)

bench: setup
	@$(ENV) for b in bench/*_bench.py; do echo "== $$b"; python "$$b" || exit 1; done

clean:
	rm -rf catkin_ws/build catkin_ws/devel catkin_ws/pcl_ros_plugin_prefix
