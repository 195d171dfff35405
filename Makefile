# Everything a fresh machine needs: `make demo` runs the main job, `make test` the suite.
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.setup-done

.PHONY: setup test test-stress demo bench lint clean
setup: $(STAMP)

$(STAMP): pyproject.toml Makefile scripts/setup.sh scripts/build_ros_interfaces.sh \
          $(wildcard ros_interfaces/beehave_interfaces/* ros_interfaces/beehave_interfaces/action/*)
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

# Every extra is installed here, so a test that would skip for a missing one fails instead.
# Six pytest-xdist workers on two cores: most tests wait on processes, DDS and sim time
# (one run used 1.2 of the 2 cores on four workers). The files that start process-level
# scenarios run in three lanes (tests/conftest.py), so that at most three run at once:
# six workers without lanes drove the load average to 12-14 and browser, DDS and timing
# tests failed; with lanes it stays at about 6-10.
# --no-loadscope-reorder: the order tests/conftest.py gives (longest files first) holds.
# --max-worker-restart 0: a worker that dies ends the run with its failure; a replaced one
# can hang loadgroup for good (pytest-xdist#1323, #1378; seen once beside busy loops).
# (scripts/test_stress.py runs the same command.)
test: $(STAMP)
	BEEHAVE_REQUIRE_EXTRAS=1 $(PY) -m pytest -q -n 6 --dist loadgroup --no-loadscope-reorder --max-worker-restart 0

# The suite ten times on a clean clone of HEAD beside a busy loop per core; reports every
# test that failed in any run.
test-stress: $(STAMP)
	$(PY) scripts/test_stress.py --runs 10

demo: $(STAMP)
	$(VENV)/bin/beehave demo

bench: $(STAMP)
	$(PY) -m benchmarks

lint: $(STAMP)
	$(PY) -m mypy
	$(PY) -m ruff check beehave behaviours hal robots tests benchmarks

clean:
	rm -rf $(VENV) .pytest_cache
