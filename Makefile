# respecd — two commands: `make run` (simulated rover) and `make test` (`make test-fast` while editing).
# A Jetson user points TORCH_SPEC at NVIDIA's wheel, e.g.
#   make install TORCH_SPEC=/path/to/torch-2.5.0a0+nv24.08-cp310-cp310-linux_aarch64.whl
# PyPI's Linux torch pulls ~2.5 GB of CUDA libraries; TORCH_INDEX adds PyTorch's CPU index (for torch
# alone, not its dependencies), whose 2.13.0+cpu outranks PyPI's 2.13.0. Where it is unreachable the
# install says so in one line and takes torch from the usual indexes; TORCH_INDEX= skips it.
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
BIN := $(VENV)/bin
ARGS ?=
# the package's extras to install: add fleet for `respecd fleet --address` on Ray (and its tests:
# `make test EXTRAS=test,lab,fleet`; without it they skip)
EXTRAS ?= test,lab
comma := ,
# one stamp per set of extras: another EXTRAS installs again
INSTALLED := $(VENV)/.installed-$(subst $(comma),-,$(EXTRAS))

SHARED ?= ../shared

.PHONY: install run test test-fast bench bench-peers latency-cpu weights weights-sim-rover weights-rgbt weights-rgbt-hituav lint clean

install: $(INSTALLED)

$(INSTALLED): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	@index="$(TORCH_INDEX)"; \
	if [ -n "$$index" ] && ! $(BIN)/python -c "$$PROBE" "$$index" 2>/dev/null; then \
	  echo "make: $$index unreachable: torch from the usual indexes"; index=; fi; \
	echo $(BIN)/pip install --quiet --no-deps "$(TORCH_SPEC)" $${index:+--extra-index-url $$index}; \
	$(BIN)/pip install --quiet --no-deps "$(TORCH_SPEC)" $${index:+--extra-index-url $$index}
	$(BIN)/pip install --quiet "$(TORCH_SPEC)"  # its dependencies, from the usual indexes
	# setuptools' note on every editable install whose packages are mapped (respecd.drivers <- drivers/)
	PYTHONWARNINGS="ignore:Editable installation" $(BIN)/pip install --quiet -e ".[$(EXTRAS)]"
	touch $@

# one quick look at an index (pip would retry an unreachable one five times, a warning each)
export PROBE := import sys, urllib.request; urllib.request.urlopen(sys.argv[1].rstrip("/") + "/torch/", timeout=10)

run: install
	$(BIN)/respecd $(ARGS)

test: install
	$(BIN)/pytest -q

# every package, in-process, no long runs: the tests marked slow or e2e (an interpreter per
# case, the console script end to end) are left to `make test`, which runs everything (CI)
test-fast: install
	$(BIN)/pytest -q -m "not slow and not e2e"

bench: install
	mkdir -p out
	$(BIN)/respecd bench pipeline --json out/bench-pipeline.json

# YOLOv8n for `respecd bench peers` (the daemon never imports it). Without its dependencies: they
# include opencv-python, which would overwrite the headless OpenCV the project pins; building the
# network needs only torch and torchvision (torchvision 0.28 is torch 2.13's). TI's parser,
# juhasch/xwr68xxisk and message_filters are not on PyPI: docs/PERFORMANCE.md "Peers".
bench-peers: install
	$(BIN)/pip install --quiet --no-deps ultralytics==8.4.190 torchvision==0.28.0

# the detector latency tables of the experiment (docs/RESULTS.md "What it rests on"): this machine's CPU, measured
# (process CPU time, median of 5, one torch thread; run it on a quiet machine), and the Orin Nano estimate derived
# from published figures and the network's FLOPs (it reads the CPU table's attribution multiple: run it after)
latency-cpu: install
	$(BIN)/respecd experiment latency respecd/lab/experiment/latency_tables/cpu.json --clock cpu --repeats 5
	$(BIN)/respecd experiment platforms orin-nano

# builtin:sim-rover in nine stages (docs/PERCEPTION.md "The shipped checkpoint"): from scratch, a fine-tune on the
# daylight-crossover world, then four fine-tunes where cut people stay targets (--keep-cut 0.4), strips zoom to
# 1.8-2x (near, frame-cut people whole) and radar-only scenes come more often; then three where each RGB size has
# its own strip zoom and 640x360 / 1280x720 strips are drawn more often. ~9240 CPU-s in all (the shipped base
# stage was trained before daylight crossover: equivalent, not bit-identical). Last, `respecd calibrate` fits the
# confidence calibration per RGB size on a validation world (add --check-seed 3000003 to score it on
# a second world: docs/PERCEPTION.md "Confidence calibration").
STRIPS := --keep-cut 0.4 --radar-alone 0.18
CURTAIN_AND_CUT := --scenario-weight behind-curtain=4,occlusion-partial=3
# extra flags for every stage, e.g. WEIGHTS_FLAGS="--precision bf16 --threads 2": 47.7 min from a clean clone,
# within 0.000-0.015 mAP@0.5 of the shipped file on the validation worlds (docs/PERCEPTION.md)
WEIGHTS_FLAGS ?=
SIZE_ZOOMS := --strip-zoom 0.7,2.0 --strip-zoom 640x360=0.8,1.25 --strip-zoom 960x540=0.7,1.6

# every shipped checkpoint (docs/PERCEPTION.md "Checkpoints"): the simulator's, then the two real ones
weights: weights-sim-rover weights-rgbt weights-rgbt-hituav

weights-sim-rover: install
	mkdir -p build
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --out build/sim-rover-base.pt --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-base.pt --epochs 5 --lr 0.001 \
	  --out build/sim-rover-crossover.pt --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-crossover.pt --epochs 6 --lr 0.001 $(STRIPS) \
	  --strip-zoom 0.7,1.8 --scenario-weight behind-curtain=3 --out build/sim-rover-cut1.pt --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-cut1.pt --epochs 8 --lr 0.0007 $(STRIPS) \
	  --strip-zoom 0.7,2.0 --scenario-weight behind-curtain=4 --out build/sim-rover-cut2.pt --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-cut2.pt --epochs 8 --lr 0.0005 $(STRIPS) \
	  --strip-zoom 0.7,2.0 $(CURTAIN_AND_CUT) --out build/sim-rover-cut3.pt \
	  --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-cut3.pt --epochs 8 --lr 0.0004 $(STRIPS) \
	  --strip-zoom 0.7,2.0 $(CURTAIN_AND_CUT) --out build/sim-rover-cut4.pt \
	  --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-cut4.pt --epochs 6 --lr 0.0003 $(STRIPS) $(SIZE_ZOOMS) \
	  $(CURTAIN_AND_CUT) --resolution-weight 640x360=3 \
	  --out build/sim-rover-zoom1.pt --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-zoom1.pt --epochs 3 --lr 0.0002 $(STRIPS) $(SIZE_ZOOMS) \
	  $(CURTAIN_AND_CUT) --resolution-weight 640x360=2,1280x720=2 \
	  --out build/sim-rover-zoom2.pt --eval-frames 0
	$(BIN)/respecd train $(WEIGHTS_FLAGS) --data sim --init build/sim-rover-zoom2.pt --epochs 3 --steps 200 --lr 0.0002 --seed 1 \
	  $(STRIPS) $(SIZE_ZOOMS) $(CURTAIN_AND_CUT) \
	  --resolution-weight 640x360=2,1280x720=3 --out build/sim-rover-sizes.pt
	$(BIN)/respecd calibrate --weights build/sim-rover-sizes.pt --out respecd/perception/weights/sim-rover.pt \
	  --seed 2000003 --no-progress

PRETRAINED := $(SHARED)/data/pretrained/yolo_fastest
REAL := $(SHARED)/data/real

# builtin:rgbt (configs/spec-rover.yaml): Yolo-Fastest 1.1 xl (a COCO detector trained on real photos) on both
# backbones, thermal replicated to R, G, B at full size, the thermal evidence with one 1x1 map while RGB is black
# (W_aux) and one while it is not (W_both). Everything pretrained stays frozen: RGB backbone, head and W_rgb = I (RGB
# alone is the pretrained detector), the thermal backbone (its real-photo features) and W_both = I (both cameras on
# is the pretrained sum). Only W_aux, thermal alone, trains: on real ground-level LWIR (thermal_dogs_people train)
# and drone-view LWIR (HIT-UAV train, a quarter of the crops, zoomed in), the epoch chosen on thermal_dogs_people val.
weights-rgbt: install
	$(BIN)/respecd train --data $(REAL)/thermal_dogs_people/gray --out respecd/perception/weights/rgbt.pt \
	  --init $(PRETRAINED)/yolo-fastest-1.1-xl.weights --aux thermal --rgb-aware-fusion \
	  --freeze rgb,head,aux,fuse.*.rgb,fuse.*.both --extra-data $(REAL)/hituav_thermal=0.25@1.5,4 \
	  --epochs 6 --steps 60 --batch 16 --lr 0.003 --scale 1.0 --crop 320x256 --zoom 0.6,2.0 --no-progress

# builtin:rgbt-hituav: backbone 2 fine-tuned on HIT-UAV's real thermal train split (RGB backbone, head and
# fusion frozen), the epoch chosen on its val split (100 of its images at scale 2).
weights-rgbt-hituav: install
	$(BIN)/respecd train --data $(REAL)/hituav_thermal --out respecd/perception/weights/rgbt-hituav.pt \
	  --init $(PRETRAINED)/yolo-fastest-1.1_body.weights --aux thermal \
	  --freeze rgb,head,fuse --epochs 5 --steps 150 --batch 16 --lr 0.001 --scale 1.0 --val-scale 2.0 \
	  --val-limit 100 --crop 320x256 --zoom 1.2,4 --no-progress

TYPECHECK := build/typecheck
lint: install
	$(BIN)/ruff check respecd drivers tests
	rm -rf $(TYPECHECK) && mkdir -p $(TYPECHECK)/respecd
	for entry in respecd/*; do ln -s "$$PWD/$$entry" $(TYPECHECK)/respecd/; done
	ln -s "$$PWD/drivers" $(TYPECHECK)/respecd/drivers
	cd $(TYPECHECK) && $(CURDIR)/$(BIN)/mypy --config-file $(CURDIR)/pyproject.toml respecd

clean:
	rm -rf $(VENV) build dist *.egg-info out
