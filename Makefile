# AuthROS portal. `make run` starts the stack, `make test` runs the whole suite, `make test-fast`
# its fast tier (tests/support/tiers.py) in a few minutes.
.PHONY: run test test-fast bench soak install install-test lint format contracts lock clean

# What `make run` needs (requirements/run.txt); install-test adds the test tooling and
# requirements/dev.txt (`make test` installs it itself; lint, the benchmarks and lock need it).
install:
	bash scripts/bootstrap.sh

install-test:
	bash scripts/bootstrap.sh --test

run:
	bash scripts/run.sh

test:
	bash scripts/test.sh

test-fast:
	bash scripts/test.sh --fast

bench: install-test
	.venv/bin/python -m bench

# An hour of make run's stack with its simulated robot, sampled (not part of `make bench`).
soak: install-test
	.venv/bin/python -m bench soak

lint: install-test
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .

format: install-test
	.venv/bin/ruff check --fix .
	.venv/bin/ruff format .

contracts: install
	node contracts/build.mjs

# requirements/*.txt: each role's packages (pyproject.toml's extras) at exact versions with their
# hashes, resolved by uv. dev.txt (everything `make test` needs) is resolved first and the
# roles' sets are held to its versions (run.txt, `make run`'s, among them), so a robot, an
# auditor, a server and `make run` run what the suite tested. Versions already locked are kept;
# `make lock UPGRADE=1` moves them.
# Each ROLE.txt is universal: its environment markers pick each platform's packages where pip
# runs (Linux x86_64 and aarch64, macOS; Python 3.11-3.13). The robot's and the auditor's sets
# are also locked per platform (ROLE-linux-MACHINE.txt, wheels only, the same versions), for a
# wheelhouse made on another machine (`pip download --platform`, which reads markers as the
# machine it runs on); tests/packaging/test_platforms.py downloads each for aarch64.
LOCK = .venv/bin/uv pip compile pyproject.toml --quiet --generate-hashes --universal \
	--python-version 3.11 --custom-compile-command "make lock" $(if $(UPGRADE),--upgrade)

PLATFORM_LOCK = .venv/bin/uv pip compile pyproject.toml --quiet --generate-hashes --only-binary :all: \
	--python-version 3.11 --custom-compile-command "make lock" $(if $(UPGRADE),--upgrade)

lock: install-test
	$(LOCK) --extra portal --extra agent --extra ros2 --extra verify --extra flower --extra run \
	  --extra dev -o requirements/dev.txt
	for role in portal agent ros2 verify flower run; do \
	  $(LOCK) --extra $$role -c requirements/dev.txt -o requirements/$$role.txt || exit 1; \
	done
	for role in agent verify; do for machine in x86_64 aarch64; do \
	  $(PLATFORM_LOCK) --python-platform $$machine-manylinux_2_28 --extra $$role \
	    -c requirements/$$role.txt -o requirements/$$role-linux-$$machine.txt || exit 1; \
	done; done

clean:
	rm -rf .venv node_modules .pytest_cache .ruff_cache .hypothesis
