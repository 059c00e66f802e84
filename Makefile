# Two commands do all the set-up on a fresh machine (Python 3.11, pip, gcc, make):
#   make quickstart   create .venv on first use, install, run the quickstart config (configs/quickstart.toml)
#   make test         create .venv on first use, install, run the fast tests
#   make docs         the documentation site: regenerate the reference pages (docs/gen.py), mkdocs build --strict into site/
#   make libero       the LIBERO benchmark (env.backend = "libero"): the libero extra, then `ebrl libero setup`
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_FLAGS ?= -q -rs  # -rs: print why each skipped test skipped

.PHONY: install quickstart test test-slow schemas docs libero clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml constraints.txt
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[test]'
	touch $@

quickstart: install
	$(VENV)/bin/ebrl up quickstart

test: install
	$(PY) -m pytest $(PYTEST_FLAGS)

test-slow: install
	$(PY) -m pytest $(PYTEST_FLAGS) -m slow

schemas: install
	$(VENV)/bin/ebrl schemas --dir schemas

# the docs extra (MkDocs, Material) once, into the same venv; then the generated pages and a strict build
# (NO_MKDOCS_2_WARNING: without Material's end-of-life banner)
$(VENV)/.docs-installed: $(VENV)/.installed pyproject.toml
	$(PY) -m pip install -q -c constraints.txt -e '.[docs]'
	touch $@

docs: $(VENV)/.docs-installed
	$(PY) docs/gen.py
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict --site-dir site

# LIBERO: the extra with the known-good constraints, then LIBERO itself without its dependencies (it asks for
# robosuite>=1.5.2, whose mink pin needs numpy<2), its assets linked and its config written
libero: $(VENV)/.libero-installed

$(VENV)/.libero-installed: $(VENV)/.installed pyproject.toml constraints.txt
	$(PY) -m pip install -q -c constraints.txt -e '.[libero]'
	$(VENV)/bin/ebrl libero setup
	touch $@

clean:
	rm -rf $(VENV) runs .pytest_cache site
