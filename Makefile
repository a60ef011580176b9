# lightprobe: the two commands a newcomer needs are `make run` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
HOST ?= 127.0.0.1
PORT ?= 8080
SCENE ?= flashlight
# the mesh /view shows beside its spheres: the shared cow when ../shared is beside the clone
VIEW_MESH ?= $(wildcard ../shared/data/meshes/spot.obj)

.PHONY: run test lint bench clean venv blender-addon deb deb-check

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[probe,relight,mqtt,test]'
	$(BIN)/python -m compileall -q core cli device drivers sim calibration hostlink bench  # bytecode up front: faster service start
	$(BIN)/lightprobe warm-kernels  # compile every numba kernel the service runs, once, at install
	touch $(STAMP)

venv: $(STAMP)

run: $(STAMP)
	@$(BIN)/python -m compileall -q core cli device drivers sim calibration hostlink bench  # sources changed since install (a pull)
	$(BIN)/lightprobe serve --camera sim --scene $(SCENE) --host $(HOST) --port $(PORT) $(if $(VIEW_MESH),--view-mesh $(VIEW_MESH))

NODE_TOOLS := tests/node/node_modules/.installed

# the tests' independent checkers from npm (Khronos glTF-Validator, ktx-parse), pinned by the lock file
$(NODE_TOOLS): tests/node/package.json tests/node/package-lock.json
	cd tests/node && npm ci --silent --no-audit --no-fund
	touch $(NODE_TOOLS)

BPY_VENV := build/bpy-venv/.installed

# Blender as a Python module for the add-on's test: a venv of its own (bpy 4.2 pins numpy < 2)
$(BPY_VENV):
	$(BIN)/python -m venv --clear build/bpy-venv
	build/bpy-venv/bin/pip install --quiet 'bpy>=4.2,<4.3'
	touch $(BPY_VENV)

test: $(STAMP) $(NODE_TOOLS) $(BPY_VENV)
	$(BIN)/python -m pytest -q

# the Blender add-on as a user installs it (Preferences > Add-ons > Install from Disk)
blender-addon:
	@mkdir -p dist
	cd hostlink/blender && $(PY) -c "import pathlib, zipfile; z = zipfile.ZipFile('../../dist/lightprobe_blender-0.1.0.zip', 'w', zipfile.ZIP_DEFLATED); [z.write(f, str(f)) for f in sorted(pathlib.Path('lightprobe_blender').rglob('*')) if f.is_file() and '__pycache__' not in f.parts]"
	@echo dist/lightprobe_blender-0.1.0.zip

# the Debian packages an installer puts on a unit (amd64 and arm64, from one recipe) into dist/,
# then lintian on them (every tag kept is explained in packaging/build_deb.py's overrides)
deb: $(STAMP)
	@command -v dpkg-deb >/dev/null || { echo "make deb: needs dpkg-deb (apt install dpkg-dev)"; exit 2; }
	$(BIN)/python packaging/build_deb.py --arch amd64 --arch arm64
	@if command -v lintian >/dev/null; then for d in dist/lightprobe_*_amd64.deb dist/lightprobe_*_arm64.deb; do \
	  echo "lintian $$d"; lintian --fail-on error,warning $$d || exit 1; done; else echo "lintian not installed: not run"; fi

# each package installed in a clean Debian 12 root (arm64 under QEMU) and its unit's service
# run to first lights on v4l2-fake and sim; arm64's lights against amd64's (root, network)
deb-check: deb
	$(BIN)/python packaging/check_deb.py --allow-skip --report dist/deb-check.json

lint: $(STAMP)
	$(BIN)/ruff check core cli device drivers sim calibration hostlink bench tests packaging setup.py
	@mkdir -p build/mypy/lightprobe  # mypy reads the one namespace through links to the folders (setup.py's map)
	@for f in core cli device drivers sim calibration hostlink bench; do ln -sfn ../../../$$f build/mypy/lightprobe/$$f; done
	MYPYPATH=build/mypy $(BIN)/mypy -p lightprobe
	$(BIN)/mypy --ignore-missing-imports packaging

bench: $(STAMP)
	$(BIN)/lightprobe bench pipeline --out bench/results
	$(BIN)/lightprobe bench samplers --out bench/results
	$(BIN)/lightprobe bench live --out bench/results

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
