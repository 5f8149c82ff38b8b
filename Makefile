# The two commands of the README:  `make demo` (main job on examples/parts)  and  `make test`.
# Both set everything up first (system packages, .venv, pinned install) through scripts/setup.sh.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
OUT ?= out/demo

.PHONY: setup test demo examples synth-preview bench clean

$(STAMP): pyproject.toml constraints.txt scripts/setup.sh
	VENV=$(VENV) scripts/setup.sh
	touch $(STAMP)

setup: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q

demo: $(STAMP)
	$(VENV)/bin/polycubenet mesh examples/parts -o $(OUT) --formats vtu,inp --hexes 3000 --polycube-points 8192

examples: $(STAMP)
	$(PY) scripts/make_examples.py

synth-preview: $(STAMP)
	$(PY) -m polycubenet.synth.preview --out docs/synth_pairs.png --count 6 --seed 0

bench: $(STAMP)
	$(PY) benchmarks/bench_sampling.py
	$(PY) benchmarks/bench_synth.py
	$(PY) benchmarks/bench_cpd.py
	$(PY) benchmarks/check_hexgen_quality.py

clean:
	rm -rf out .pytest_cache
