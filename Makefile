# cm2optics — `make demo` and `make test` set everything up on a fresh machine first.
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.cm2optics-installed
SYSTEM := $(VENV)/.system-deps-installed

.PHONY: setup demo test test-slow clean-out

setup: $(SYSTEM) $(STAMP)

$(SYSTEM): scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	@mkdir -p $(VENV) && touch $@

$(STAMP): pyproject.toml scripts/install-python-deps.sh
	bash scripts/install-python-deps.sh $(VENV)
	touch $@

demo: setup
	$(VENV)/bin/cm2 demo --out out/demo

test: setup
	$(PY) -m pytest -q

test-slow: setup
	$(PY) -m pytest -q -m slow

clean-out:
	rm -rf out
