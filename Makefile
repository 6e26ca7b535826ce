# `make demo`, `make test`, `make bench`: each creates or reuses .venv and installs
# exactly the pins in requirements.txt first.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The ECC kernels compiled ahead of time (multi_instance_reg/core/native.py): without them a
# fresh process spends 1-2 s loading numba's JIT cache before its first registration.
CORE := multi_instance_reg/core
KERNELS_AOT := $(CORE)/.kernels_aot.built
# The numba kernels of the front ends, verification and tracker, compiled once into numba's
# cache (tools/warm_kernels.py), not by each process of a new checkout on its first frame.
KERNELS_WARM := $(VENV)/.kernels_warm
NUMBA_SOURCES := $(shell grep -rl --include='*.py' 'numba.njit' multi_instance_reg)
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: install demo test bench clean

install: $(STAMP) $(KERNELS_AOT) $(KERNELS_WARM)

# vision_msgs (Detection3DArray, LabelInfo) and realsense2_camera_msgs (Extrinsics) have no wheel:
# the last steps build them into the venv from interfaces/ unless the user's ROS already has them
# (about a minute each at most).
$(STAMP): requirements.txt setup.py setup.cfg package.xml interfaces/install_vision_msgs.py \
		$(wildcard interfaces/*/*.* interfaces/*/msg/*.msg)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	$(PY) interfaces/install_vision_msgs.py
	$(PY) interfaces/install_vision_msgs.py --package realsense2_camera_msgs
	touch $(STAMP)

$(KERNELS_AOT): $(STAMP) $(CORE)/native.py $(CORE)/clustering.py $(CORE)/compatibility.py $(CORE)/refinement.py $(CORE)/sampling.py
	$(PY) -m multi_instance_reg.core.build_native
	touch $(KERNELS_AOT)

$(KERNELS_WARM): $(STAMP) $(KERNELS_AOT) $(NUMBA_SOURCES) multi_instance_reg/tools/warm_kernels.py
	$(PY) -m multi_instance_reg.tools.warm_kernels
	touch $(KERNELS_WARM)

demo: install
	$(PY) -m multi_instance_reg.tools.demo

# Two steps at once. Everything but the live ROS tests, spread over worker processes
# (pytest-xdist; loadgroup keeps each xdist_group, e.g. a module whose fixture runs `mireg
# offline`, on one worker; session data is built once, test/conftest.py), runs at the lowest
# CPU priority (nice 19); beside it, the ROS tests, one at a time, at normal priority: they
# time a detector against a 30 Hz stream, and next to CPU-bound tests of the same priority
# they missed their deadlines (3 of 60 failed when run in the same pool). The ROS tests mostly
# wait (node start-up, streams played in real time), and the workers take what they leave.
# The ROS tests run in the foreground: a background job of sh ignores SIGINT, and so would the
# nodes they start and stop with it. The other step's output follows theirs. Both read the
# same built-once data (MIREG_TEST_SHARED), removed at the end.
TEST_WORKERS ?= 3
ROS_TESTS := $(wildcard test/test_ros_*.py)
test: install
	shared=$$(mktemp -d) || exit 1; export MIREG_TEST_SHARED=$$shared; status=0; \
	nice -n 19 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup $(addprefix --ignore=,$(ROS_TESTS)) test \
		> $$shared/tests.log 2>&1 & others=$$!; \
	trap 'kill $$others 2>/dev/null' INT TERM; \
	$(PY) -m pytest -q $(ROS_TESTS) || status=$$?; \
	wait $$others || status=$$?; echo "All but the ROS tests (run beside them):"; cat $$shared/tests.log; \
	rm -rf "$$shared"; exit $$status

# Figures quoted in the README; each line prints its own table (about 20 minutes in all).
bench: install
	$(VENV)/bin/mireg bench core
	$(VENV)/bin/mireg bench register-startup
	$(VENV)/bin/mireg bench table1 --samples-per-band 20
	$(VENV)/bin/mireg bench table1 --hard --samples-per-band 20 --no-baseline
	test ! -d ../shared/reference/core || $(VENV)/bin/mireg bench table1 --reference ../shared/reference/core
	$(VENV)/bin/mireg bench synth
	$(VENV)/bin/mireg bench frames
	$(VENV)/bin/mireg bench frames --objects snack_box,can,cereal_box --scenes 4 --frames 3
	$(VENV)/bin/mireg bench frames --objects snack_box,can,cereal_box --scenes 4 --frames 3 --seed 7
	$(VENV)/bin/mireg bench frames --untextured all --scenes 4 --frames 3
	$(VENV)/bin/mireg bench frames --untextured all --scenes 4 --frames 3 --seed 5
	$(VENV)/bin/mireg bench frames --untextured flush --scenes 4 --frames 3
	$(VENV)/bin/mireg bench frames --untextured flush --scenes 4 --frames 3 --seed 5
	$(VENV)/bin/mireg bench frames --untextured flush --sensor realistic --randomise --scenes 4 --frames 3 --seed 100
	$(VENV)/bin/mireg bench frames --untextured flush --sensor realistic --randomise --scenes 4 --frames 3 --seed 110
	$(VENV)/bin/mireg bench tracking
	$(VENV)/bin/mireg bench tracking --seed 1000
	$(VENV)/bin/mireg bench bop
	$(VENV)/bin/mireg bench scale
	$(VENV)/bin/mireg bench node

clean:
	rm -rf $(VENV) out $(KERNELS_AOT) $(CORE)/_kernels_aot*.so
