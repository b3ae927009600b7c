#!/usr/bin/env bash
# Make sure a Redis answers at $REDIS_URL (default 127.0.0.1:6379): reuse it, else start one
# (no persistence, files in var/redis/). The same code `make run` uses: stack/run.py.
set -euo pipefail
cd "$(dirname "$0")/.."
exec .venv/bin/python -m stack redis
