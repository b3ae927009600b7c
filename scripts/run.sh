#!/usr/bin/env bash
# `make run`: install what is missing, then start the whole stack with `python -m stack run`
# (stack/run.py): Redis, anvil (state in var/anvil/), the contract, the Celery workers and
# beat, the portal under gunicorn, and the ROS side with a simulated robot and a demo agent.
# Ctrl-C stops everything it started; running it again is safe. Options and environment
# variables: `.venv/bin/python -m stack run --help`, docs/operations.md.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/bootstrap.sh
exec .venv/bin/python -m stack run "$@"
