# bid-sim: every target wraps the `bid` command line.
PYTHON ?= python3.11
VENV := .venv
BID := $(VENV)/bin/bid
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

TOWN ?= 02
DENSITY ?= normal

EPISODES ?= 48
WORKERS ?= 2
# Share of driving time with steering noise (recovery data; labels stay the expert's).
PERTURB ?= 0.2
# `make record` records Town01 unless TOWN is given (the demo's default is Town02).
RECORD_TOWN = $(if $(filter command line environment,$(origin TOWN)),$(TOWN),01)

AGENT ?= bid
# The BID shipped in the repository (`small` preset, trained on CPU; its card is beside it).
SHIPPED := checkpoints/bid_small.pt
CHECKPOINT ?= $(SHIPPED)
# How the shipped BID drives: its hazard head and SC (both fitted to the frozen network) brake
# for the pedestrian, the vehicle and the red light they see in the path (for a vehicle twice
# as hard as stopping short of it would take; at gain 1 it met cars ahead more often), and
# move a standing ego off once they have seen nothing within 8 m for 8 s (README "Results"); a
# pedestrian holds a slow ego standing only when seen within 6 m (SC reads some waiting on the
# kerb as in the path 7 m ahead); and it brakes above 9 m/s (at Town02's 11.2 m/s limit it
# drove past a bend it saw too late). Below 2 m/s the red light the light brake and move-off
# read comes from frame t alone (`--light-still`): seen from a standing ego, others' motion
# between frames t-1 and t read as red at a green light (docs/experiments.md, "Red from motion").
# The light brake stops 2.5 m short of a red light's line (`--light-short 2.5`; at the expert's
# 1 m the lamp is above the cameras' view), and after a stop at a red light move-off waits 1 s
# once clear, not 8 (`--move-off-green 1`: standing at green the control head does not go).
# Another CHECKPOINT drives on its control head alone unless DRIVE gives flags; `make evaluate
# DRIVE=` so drives the shipped one.
SHIPPED_DRIVE := --vehicle-brake 2 --light-brake 1 --move-off 8 --hazard-brake 1 --pedestrian-hold 6 --max-speed 9 --light-still --light-short 2.5 --move-off-green 1
DRIVE ?= $(if $(filter $(SHIPPED),$(CHECKPOINT)),$(SHIPPED_DRIVE))
WEATHERS ?= test
SEEDS ?= 3

# A DAgger round: which checkpoint drives, the round's number (its routes' seed) and its
# fine-tuning epochs (the shipped BID had 3 in round 1, 2 in rounds 2-4 and 6, 1 in round 5)
# and the share of samples given a random lighting change (the shipped BID: 0.8 from round 4
# on, none before).
STUDENT ?= runs/small/best.pt
ROUND ?= 1
DAGGER_RUN ?= small_dagger$(ROUND)
DAGGER_EPOCHS ?= 3
AUGMENT ?= 0
# Times each frame of hard steering or braking is trained on (the shipped BID: 3 in round 7).
HARD_REPEAT ?= 1
# BENDS=1: the round drives only routes that take a corner of the road early (bid record --bends).
BENDS ?=
# How the student drives (bid evaluate's drive flags): STUDENT_DRIVE='$(SHIPPED_DRIVE)' drives it
# as the shipped BID is evaluated; empty, on its control head alone (all rounds so far).
STUDENT_DRIVE ?=
# FORECAST=W: train the auxiliary speed forecast too, its loss weighted W (the shipped BID: 0.5).
FORECAST ?=

.PHONY: demo test bench towns clean lint record evaluate train dagger reproduce ablations multitown

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found; install Python 3.11 or run 'make PYTHON=python3 ...'"; exit 2; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev,cluster]'
	touch $(STAMP)

# The shipped BID drives six Town02 routes it has never seen, at normal density, in a test
# weather; one episode is filmed with the Grad-CAM overlay. It starts afresh each time (a few
# minutes), so a re-exported checkpoint is never scored with the previous one's episodes.
demo: $(STAMP)
	rm -rf results/demo
	$(BID) evaluate --town 02 --density normal --weathers WetSunset --seeds 1 --routes 0,1,2,3,4,5 \
		--agent bid --checkpoint $(SHIPPED) $(SHIPPED_DRIVE) --workers $(WORKERS) --video 1 --out results/demo
	@echo "video with Grad-CAM: $$(ls results/demo/videos/*.mp4)"

test: $(STAMP)
	$(PY) -m pytest tests

bench: $(STAMP)
	$(PY) benchmarks/bench_world.py
	$(BID) bench render
	$(BID) bench record
	$(PY) benchmarks/bench_reader.py
	$(PY) benchmarks/bench_model.py --checkpoint checkpoints/bid_small.pt

# The BID model, `small` preset, on the recordings of `make record`.
train: $(STAMP)
	$(BID) train --preset small --data data/town01 --name small

# The closed-loop benchmark; AGENT=expert needs no checkpoint.
evaluate: $(STAMP)
	$(BID) evaluate --town $(TOWN) --density $(DENSITY) --weathers $(WEATHERS) --seeds $(SEEDS) \
		--agent $(AGENT) $(if $(filter bid,$(AGENT)),--checkpoint $(CHECKPOINT) $(DRIVE)) --workers $(WORKERS) \
		--out results/town$(TOWN)_$(AGENT)_$(DENSITY)

# Demonstrations: the expert over random routes, four train weathers, three densities.
record: $(STAMP)
	$(BID) record --town $(RECORD_TOWN) --episodes $(EPISODES) --perturb $(PERTURB) --workers $(WORKERS) \
		--out data/town$(RECORD_TOWN)

# A DAgger round, after `make train`: the BID of STUDENT drives Town01 routes of its own, the
# expert labels every frame and takes the wheel when the BID strays; then the BID is
# fine-tuned from STUDENT on everything under data/town01 (demonstrations and DAgger rounds).
dagger: $(STAMP)
	$(BID) record --town 01 --episodes $(EPISODES) --seed $(ROUND) --dagger $(STUDENT) $(STUDENT_DRIVE) --workers $(WORKERS) \
		$(if $(BENDS),--bends) --out data/town01/dagger$(ROUND)
	$(BID) train --preset small --data data/town01 --name $(DAGGER_RUN) \
		$(if $(wildcard runs/$(DAGGER_RUN)/last.pt),--resume,--init $(STUDENT) --epochs $(DAGGER_EPOCHS) --lr 1e-4 --augment $(AUGMENT) \
		--hard-repeat $(HARD_REPEAT) $(if $(FORECAST),--forecast $(FORECAST)))

# Everything from scratch (hours on 2 cores; see README "Reproducing"): demonstrations,
# training, six DAgger rounds (as the shipped checkpoint had, the last three augmented), the
# weight average of the fifth and sixth, a seventh round from it with hard frames repeated,
# a round on routes with corners (seed 9, as data/town01/dagger9, not 8: `make ablations`
# records its own round 8) that also trains the speed forecast, then fresh recordings into
# data/town01_late (demonstrations, a DAgger round and a corner round, all driven or
# labelled by the corner round's BID) on which it is fine-tuned one epoch with accel's
# 0.3-quantile as the target, and the equal-weight average of the corner round and that
# (runs/reproduce_soup: the shipped network), a hazard head fitted to it with the network
# frozen, on fresh recordings (data/town01_hz: demonstrations and a DAgger round it drove;
# runs/reproduce_hazard), SC fitted beside it on those and on more pedestrians (data/town01_sc:
# links to data/town01_hz's files and 96 normal and crowded demonstrations;
# runs/reproduce_sc), SC fitted one epoch more on frames moved by up to 4 pixels, with a DAgger
# round it drove (data/town01_sc2: links to the seed-40 and seed-50 demonstrations and 48
# normal and crowded episodes; runs/reproduce_sc2: what is shipped), the Town02 NoCrash for the
# expert and for the new BID driving as the shipped one does (SHIPPED_DRIVE), and the result
# tables. The shipped checkpoint is left alone: copy runs/reproduce_sc2/last.pt over it with
# `bid export` only if it drives better.
reproduce: $(STAMP)
	$(MAKE) record TOWN=01
	$(BID) train --preset small --data data/town01 --name reproduce $(if $(wildcard runs/reproduce/last.pt),--resume)
	$(MAKE) dagger STUDENT=runs/reproduce/best.pt ROUND=1 DAGGER_RUN=reproduce_dagger1
	$(MAKE) dagger STUDENT=runs/reproduce_dagger1/last.pt ROUND=2 DAGGER_RUN=reproduce_dagger2 DAGGER_EPOCHS=2
	$(MAKE) dagger STUDENT=runs/reproduce_dagger2/last.pt ROUND=3 DAGGER_RUN=reproduce_dagger3 DAGGER_EPOCHS=2
	$(MAKE) dagger STUDENT=runs/reproduce_dagger3/last.pt ROUND=4 DAGGER_RUN=reproduce_dagger4 DAGGER_EPOCHS=2 AUGMENT=0.8
	$(MAKE) dagger STUDENT=runs/reproduce_dagger4/last.pt ROUND=5 DAGGER_RUN=reproduce_dagger5 DAGGER_EPOCHS=1 AUGMENT=0.8
	$(MAKE) dagger STUDENT=runs/reproduce_dagger5/last.pt ROUND=6 DAGGER_RUN=reproduce_dagger6 DAGGER_EPOCHS=2 AUGMENT=0.8 \
		EPISODES=96
	$(if $(wildcard runs/reproduce_soup56/last.pt),,$(BID) average runs/reproduce_dagger5/last.pt \
		runs/reproduce_dagger6/last.pt --out runs/reproduce_soup56/last.pt)
	$(MAKE) dagger STUDENT=runs/reproduce_soup56/last.pt ROUND=7 DAGGER_RUN=reproduce_dagger7 DAGGER_EPOCHS=1 \
		AUGMENT=0.8 HARD_REPEAT=3 EPISODES=96
	$(MAKE) dagger STUDENT=runs/reproduce_dagger7/last.pt ROUND=9 DAGGER_RUN=reproduce_corners DAGGER_EPOCHS=1 \
		AUGMENT=0.8 HARD_REPEAT=3 EPISODES=48 BENDS=1 FORECAST=0.5
	$(BID) record --town 01 --episodes 48 --perturb $(PERTURB) --seed 30 --workers $(WORKERS) \
		--out data/town01_late/expert30
	$(BID) record --town 01 --episodes 96 --seed 31 --dagger runs/reproduce_corners/last.pt \
		--workers $(WORKERS) --out data/town01_late/dagger31
	$(BID) record --town 01 --episodes 48 --seed 32 --bends --dagger runs/reproduce_corners/last.pt \
		--workers $(WORKERS) --out data/town01_late/bends32
	$(BID) train --preset small --data data/town01_late --name reproduce_q30 \
		$(if $(wildcard runs/reproduce_q30/last.pt),--resume,--init runs/reproduce_corners/last.pt --epochs 1 \
		--lr 1e-4 --augment 0.8 --hard-repeat 3 --forecast 0.5 --accel-quantile 0.3)
	$(if $(wildcard runs/reproduce_soup/last.pt),,$(BID) average runs/reproduce_corners/last.pt \
		runs/reproduce_q30/last.pt --out runs/reproduce_soup/last.pt)
	$(BID) record --town 01 --episodes 48 --perturb $(PERTURB) --seed 40 --workers $(WORKERS) \
		--out data/town01_hz/expert40
	$(BID) record --town 01 --episodes 96 --seed 41 --dagger runs/reproduce_soup/last.pt \
		--workers $(WORKERS) --out data/town01_hz/dagger41
	$(BID) train --preset small --data data/town01_hz --name reproduce_hazard \
		$(if $(wildcard runs/reproduce_hazard/last.pt),--resume,--init runs/reproduce_soup/last.pt --epochs 1 \
		--lr 1e-3 --augment 0.8 --forecast 0.5 --hazard 1 --hazard-pos-weight 2 --train-only hazard)
	test -d data/town01_sc/hz || $(call link_episodes,data/town01_hz,data/town01_sc/hz,1)
	$(BID) record --town 01 --episodes 96 --densities normal,crowded --perturb $(PERTURB) --seed 50 \
		--workers $(WORKERS) --out data/town01_sc/expert50
	$(BID) train --preset small --data data/town01_sc --name reproduce_sc \
		$(if $(wildcard runs/reproduce_sc/last.pt),--resume,--init runs/reproduce_hazard/last.pt --epochs 1 \
		--lr 1e-3 --augment 0.8 --mirror 0.5 --stop-keep 1 --motion-drop 0 --forecast 0.5 --hazard 1 \
		--hazard-sc --hazard-pos-weight 4 --train-only SC)
	test -d data/town01_sc2/expert40 || $(call link_episodes,data/town01_hz/expert40,data/town01_sc2/expert40,1)
	test -d data/town01_sc2/expert50 || $(call link_episodes,data/town01_sc/expert50,data/town01_sc2/expert50,1)
	$(BID) record --town 01 --episodes 48 --densities normal,crowded --seed 51 --dagger runs/reproduce_sc/last.pt \
		--workers $(WORKERS) --out data/town01_sc2/dagger51
	$(BID) train --preset small --data data/town01_sc2 --name reproduce_sc2 \
		$(if $(wildcard runs/reproduce_sc2/last.pt),--resume,--init runs/reproduce_sc/last.pt --epochs 1 \
		--lr 5e-4 --augment 0.8 --mirror 0.5 --shift 4 --stop-keep 1 --motion-drop 0 --forecast 0.5 --hazard 1 \
		--hazard-sc --hazard-pos-weight 4 --train-only SC)
	$(BID) evaluate --town 02 --density none,normal,crowded --weathers test --seeds 3 --agent expert \
		--workers $(WORKERS) --out results/reproduce/town02_expert
	$(BID) evaluate --town 02 --density none,normal,crowded --weathers test --seeds 3 --agent bid \
		--checkpoint runs/reproduce_sc2/last.pt $(SHIPPED_DRIVE) --workers $(WORKERS) \
		--out results/reproduce/town02_bid_small
	$(BID) lesion --checkpoint runs/reproduce_soup/last.pt --town 02 --density normal \
		--out results/reproduce/lesion_town02_normal
	$(BID) tables results/reproduce --out results/reproduce/tables.md

# The paper's ablations (about 1.5 h on 2 cores; README "Ablations"): each variant starts from
# the areas it shares with the shipped BID (`--init`; the ones it adds start afresh), is
# fine-tuned one epoch on a quarter of the episodes under data/town01 (links in
# data/ablation: episodes whose index i has (i + i // 12) % 4 == 0, as many of each weather
# and density), after the DAgger round the shipped BID drove is recorded (or finished), and
# drives the Town02 routes at normal density in the test weathers.
ABLATION_SEEDS ?= 1
# Links in $(2) (files, not folders: training does not follow linked folders) to the
# episodes under $(1) that the awk program $(3) prints; QUARTER prints those whose index i
# has (i + i // 12) % 4 == 0.
link_episodes = (cd $(1) && find . -name 'ep*.mcap' -not -path '*/.bid_cache/*' | sort | awk '$(3)' \
	| while read f; do mkdir -p $(CURDIR)/$(2)/$$(dirname $$f) && ln -s $$(realpath $$f) $(CURDIR)/$(2)/$$f || exit 1; done)
QUARTER = {match($$0, /ep[0-9]+_/); i = substr($$0, RSTART + 2, RLENGTH - 3) + 0; if ((i + int(i / 12)) % 4 == 0) print}
ablations: $(STAMP)
	$(BID) record --town 01 --episodes 96 --seed 8 --dagger $(SHIPPED) --workers $(WORKERS) \
		--out data/town01/dagger8
	test -d data/ablation || $(call link_episodes,data/town01,data/ablation,$(QUARTER))
	for v in full baseline both dorsal navigation; do \
		test -f runs/ablate_$$v/last.pt || $(BID) train --preset small --variant $$v --data data/ablation \
			--name ablate_$$v --init $(SHIPPED) --epochs 1 --lr 1e-4 --augment 0.8 --hard-repeat 3 || exit 1; \
		test -f results/ablations/$$v/summary.json || $(BID) evaluate --town 02 --density normal --weathers test \
			--seeds $(ABLATION_SEEDS) --agent bid --checkpoint runs/ablate_$$v/last.pt --workers $(WORKERS) \
			--out results/ablations/$$v || exit 1; \
	done
	$(BID) tables results/ablations --out results/ablations/tables.md

# The paper's multi-town setting, with the towns we have: the shipped BID (Town01 only) is
# fine-tuned one epoch on Town02 recordings (expert demonstrations and a DAgger round the
# shipped BID drove) and the quarter of Town01's of `make ablations`, then drives the Town05
# routes, a town it has never seen, at every density (about 1 h on 2 cores).
MULTITOWN_SEEDS ?= 1
multitown: $(STAMP)
	$(BID) record --town 02 --episodes 48 --perturb $(PERTURB) --workers $(WORKERS) --out data/town02
	$(BID) record --town 02 --episodes 96 --seed 22 --dagger $(SHIPPED) --workers $(WORKERS) \
		--out data/town02/dagger1
	test -d data/multitown || ($(call link_episodes,data/town01,data/multitown/town01,$(QUARTER)) \
		&& $(call link_episodes,data/town02,data/multitown/town02,1))
	test -f runs/multitown/last.pt || $(BID) train --preset small --data data/multitown --name multitown \
		--init $(SHIPPED) --epochs 1 --lr 1e-4 --augment 0.8 --hard-repeat 3
	$(BID) evaluate --town 05 --density none,normal,crowded --weathers test --seeds $(MULTITOWN_SEEDS) --agent bid \
		--checkpoint runs/multitown/last.pt --workers $(WORKERS) --out results/town05/multitown
	$(BID) tables results/town05 --out results/town05/tables.md

towns: $(STAMP)
	$(BID) towns

lint: $(STAMP)
	$(VENV)/bin/ruff check bid_sim bid_model tests benchmarks

clean:
	rm -rf build results runs .pytest_cache
