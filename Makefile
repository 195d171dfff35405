# Everything a fresh machine needs: `make demo` runs the main job, `make test` the suite.
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.setup-done

.PHONY: setup test demo bench lint clean
setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

# Every extra is installed here, so a test that would skip for a missing one fails instead.
test: $(STAMP)
	BEEHAVE_REQUIRE_EXTRAS=1 $(PY) -m pytest -q

demo: $(STAMP)
	$(VENV)/bin/beehave demo

bench: $(STAMP)
	$(PY) -m benchmarks

lint: $(STAMP)
	$(PY) -m mypy
	$(PY) -m ruff check beehave behaviours hal robots tests benchmarks

clean:
	rm -rf $(VENV) .pytest_cache
