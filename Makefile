# Two commands do everything on a fresh machine (Debian 12, Python 3.11):
#   make demo   - the main job on the bundled default data
#   make test   - the whole test suite (unit + topic-level integration, slow ones included)
# Both create .venv first when it is missing (scripts/bootstrap_env.sh) and reuse it otherwise.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: env demo test test-fast bags bench bench-quick bench-gap bench-oracle bench-plants bench-limits bench-scenarios bench-microgrid bench-independent clean

env:
	@bash scripts/bootstrap_env.sh

demo: env
	$(VENV)/bin/pisml demo --out out/demo

test: env
	$(PY) -m pytest -q $(PYTEST_ARGS)

# quick loop while developing: skips the tests marked slow
test-fast: env
	$(PY) -m pytest -q -m "not slow" $(PYTEST_ARGS)

# the small demo recordings in bags/ (made by the project's own tools)
bags: env
	$(VENV)/bin/pisml simulate --scenario train --snr-db 40 --seed 0 --out bags/train_40dB
	$(VENV)/bin/pisml simulate --scenario test --seed 0 --out bags/test_clean
	$(VENV)/bin/pisml simulate --scenario smallsignal --snr-db 40 --seed 0 --out bags/smallsignal_40dB

# identification benchmark (paper protocol, ten 40 dB recordings; 23-28 min on 2 cores at stops 55-57 (target: 30);
# earlier runs' times in docs/HISTORY.md): bench/results.json, bench/RESULTS.md, bench/figures/
bench: env
	$(PY) bench/bench.py

# the same on the standard plant only, clean and 40 dB, no sweeps (~10 min)
bench-quick: env
	$(PY) bench/bench.py --quick --out bench/results_quick.json --markdown bench/RESULTS_quick.md

# gap workflow benchmark (the full matrix, 40 cases, ~6 min on 2 cores at stop 58; `--quick`, 16 of them:
# bench/gap_results_quick.json): bench/gap_results.json, bench/GAP_RESULTS.md
bench-gap: env
	$(PY) bench/gap_bench.py

# PISML and Mod-SINDy on the default inverter and two with other parameters, clean and 40 dB, recordings 0-2 (~11-13 min on 2 cores at stops 34-37, 11 at stop 42):
# bench/plants_results.json, bench/PLANTS_RESULTS.md
bench-plants: env
	$(PY) bench/plants_bench.py

# PISML on the default inverter with a limit of its current reference (a magnitude limit, a per-axis
# clamp) or of its voltage command (modulation), two recordings each: bench/limits_results.json,
# bench/LIMITS_RESULTS.md (~26 min on 2 cores at stop 57)
bench-limits: env
	$(PY) bench/plants_bench.py --plants saturation,clamp,modulation --seeds 0,1 --out bench/limits_results.json --markdown bench/LIMITS_RESULTS.md

# PISML on the protocol with one thing changed (sample rate, voltages, phase jumps, small-signal point,
# record count/length; ~20 min on 2 cores at stop 38, 23 at stop 40): bench/scenarios_results.json, bench/SCENARIOS_RESULTS.md
bench-scenarios: env
	$(PY) bench/scenarios_bench.py

# the true structure's coefficients fitted to 40 dB protocol data, three recordings (~10 min):
# bench/oracle_results.json, bench/ORACLE_RESULTS.md
bench-oracle: env
	$(PY) bench/oracle_bench.py

# the identified inverter inside the 3-bus microgrid of config/microgrid.yaml against the true plant there,
# PISML and Mod-SINDy, clean recording 0 and 40 dB recordings 0-9 (~10 min): bench/microgrid_results.json, bench/MICROGRID_RESULTS.md
bench-microgrid: env
	$(PY) bench/microgrid_bench.py --seeds 0-9 --clean

clean:
	rm -rf build install log out .pytest_cache

# the models of `make bench` (bench/models/) scored by code that rebuilds f(x, u) from each JSON file alone
# (sympy, scipy), side by side with the package's figures (~2.5 min on 2 cores): bench/independent_results.json, bench/INDEPENDENT_RESULTS.md
bench-independent: env
	$(PY) bench/independent_score.py --compare --out bench/independent_results.json --markdown bench/INDEPENDENT_RESULTS.md
