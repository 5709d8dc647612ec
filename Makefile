PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip wheel setuptools >/dev/null

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -e '.[test,batch]'
	touch $(VENV)/.installed $@

demo: $(VENV)/.installed
	$(BIN)/softplot demo

CHROMIUM := $(or $(SOFTPLOT_CHROMIUM),$(shell command -v chromium 2>/dev/null),$(shell command -v chromium-browser 2>/dev/null))

test: $(VENV)/.installed-test
	@OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 --dist loadfile; rc=$$?; \
	if [ -z "$(CHROMIUM)" ]; then \
	  echo "NOTE: the browser tests (tests/test_view_browser.py) were SKIPPED: no chromium found."; \
	  echo "      Install one (Debian/Ubuntu: sudo apt-get install chromium) or point"; \
	  echo "      SOFTPLOT_CHROMIUM at a Chromium binary, then run make test again."; \
	else echo "browser tests ran with $(CHROMIUM)"; fi; exit $$rc

lint: $(VENV)/.installed-test
	$(BIN)/ruff check src tests tools

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info
