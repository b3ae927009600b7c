# AuthROS portal. `make run` starts the stack, `make test` runs the whole suite, `make test-fast`
# its fast tier (tests/support/tiers.py) in a few minutes.
.PHONY: run test test-fast bench soak install lint format contracts lock clean

install:
	bash scripts/bootstrap.sh

run:
	bash scripts/run.sh

test:
	bash scripts/test.sh

test-fast:
	bash scripts/test.sh --fast

bench: install
	.venv/bin/python -m bench

# An hour of make run's stack with its simulated robot, sampled (not part of `make bench`).
soak: install
	.venv/bin/python -m bench soak

lint: install
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .

format: install
	.venv/bin/ruff check --fix .
	.venv/bin/ruff format .

contracts: install
	node contracts/build.mjs

# requirements/*.txt: each role's packages (pyproject.toml's extras) at exact versions with their
# hashes, resolved by uv. dev.txt (everything `make run` and `make test` need) is resolved
# first and the roles' sets are held to its versions, so a robot, an auditor and a server run
# what the suite tested. Versions already locked are kept; `make lock UPGRADE=1` moves them.
LOCK = .venv/bin/uv pip compile pyproject.toml --quiet --generate-hashes --universal \
	--python-version 3.11 --custom-compile-command "make lock" $(if $(UPGRADE),--upgrade)

lock: install
	$(LOCK) --extra portal --extra agent --extra verify --extra dev -o requirements/dev.txt
	for role in portal agent verify; do \
	  $(LOCK) --extra $$role -c requirements/dev.txt -o requirements/$$role.txt || exit 1; \
	done

clean:
	rm -rf .venv node_modules .pytest_cache .ruff_cache .hypothesis
