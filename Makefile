# Everything a fresh machine needs: `make serve` runs the service, `make test` the tests.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: serve test bench bench-ground bench-features bench-mixed bench-vegetation bench-rotation bench-buildings bench-progress bench-load bench-submit bench-kill bench-audit bench-malformed bench-driver bench-survey openapi clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

serve: $(STAMP)
	$(VENV)/bin/terrasift serve

# one test process per core, files kept whole; the OpenAPI fuzzing runs alone after them:
# under test processes its generated cases collapse to one operation's
test: $(STAMP)
	$(VENV)/bin/ruff check terrasift tests benchmarks scripts
	$(VENV)/bin/ruff format --check terrasift tests benchmarks scripts
	$(VENV)/bin/mypy terrasift
	$(PY) -m pytest -n auto --dist loadfile --ignore=tests/test_api_fuzz.py
	$(PY) -m pytest tests/test_api_fuzz.py

bench: $(STAMP)
	$(PY) benchmarks/pipeline_speed.py

bench-ground: $(STAMP)
	$(PY) benchmarks/ground_accuracy.py

bench-features: $(STAMP)
	$(PY) benchmarks/features_accuracy.py

bench-mixed: $(STAMP)
	$(PY) benchmarks/mixed_accuracy.py

bench-vegetation: $(STAMP)
	$(PY) benchmarks/vegetation_accuracy.py

bench-rotation: $(STAMP)
	$(PY) benchmarks/rotation_accuracy.py

bench-buildings: $(STAMP)
	$(PY) benchmarks/buildings_accuracy.py

bench-progress: $(STAMP)
	$(PY) benchmarks/progress_trace.py

bench-load: $(STAMP)
	$(PY) benchmarks/load.py

bench-submit: $(STAMP)
	$(PY) benchmarks/submit_latency.py

bench-kill: $(STAMP)
	$(PY) benchmarks/kill_timings.py

bench-malformed: $(STAMP)
	$(PY) benchmarks/malformed_corpus.py $(MALFORMED_ARGS)

# the issue's nine failures re-probed against `make serve` (its own port and data folder)
bench-audit: $(STAMP)
	$(PY) benchmarks/audit_live.py

bench-driver: $(STAMP)
	$(PY) benchmarks/driver_overhead.py

# 16 and 64 tiles of 0.5 M pulses on a local Dask cluster (scheduler + `terrasift worker`
# processes); a small machine: make bench-survey SURVEY_ARGS="--points 50000"
bench-survey: $(STAMP)
	$(PY) benchmarks/survey_scale.py $(SURVEY_ARGS)

openapi: $(STAMP)
	$(PY) scripts/export_openapi.py

clean:
	rm -rf $(VENV) bench-out .pytest_cache
