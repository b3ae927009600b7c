#!/usr/bin/env bash
# `make test`: install what is missing, lint, then the whole suite in its tiers
# (tests/support/tiers.py), in passes one after the other, each in parallel by pytest-xdist:
#   1. the unit tier on SQLite (with the benchmark tooling's tests), one worker per core;
#   2. on PostgreSQL (PG_TEST_URL, else a server at 127.0.0.1:5432, else a throwaway cluster of
#      its own): the process, browser and slow tests, once, and beside them, at the same time,
#      the unit tests that use the database again. Its connections commit without waiting for the disk
#      (synchronous_commit=off, through PGOPTIONS): the test databases are thrown away.
# `make test-fast` (`scripts/test.sh --fast`): the fast tier on SQLite only, for the inner loop.
# Further arguments go to pytest. TEST_WORKERS sets the xdist workers of the SQLite pass
# and of `make test-fast` (default: one per core), TEST_PROCESS_WORKERS those of the PostgreSQL
# process tests (default 3: they mostly wait on the processes they start), TEST_UNIT_DB_WORKERS
# those of the unit tests beside them (default 2).
set -euo pipefail
cd "$(dirname "$0")/.."

fast=0
if [ "${1:-}" = --fast ]; then fast=1; shift; fi

bash scripts/bootstrap.sh --test
# What the suite started, stopped again when it is done, whatever its outcome.
cleanups=()
cleanup() {
  for command in "${cleanups[@]}"; do eval "$command" >/dev/null 2>&1 || true; done
}
trap cleanup EXIT

export REDIS_URL=${REDIS_URL:-redis://127.0.0.1:6379/0}
if ! redis-cli -u "$REDIS_URL" ping >/dev/null 2>&1; then
  bash scripts/redis.sh
  cleanups+=('redis-cli -u "$REDIS_URL" shutdown nosave')
fi

say() { printf '\n\033[1;32m== %s\033[0m\n' "$*"; }

run_pytest() {
  local rc=0
  .venv/bin/pytest --durations=25 -p no:cacheprovider "$@" || rc=$?
  if [ "$rc" = 5 ]; then
    echo "ERROR: pytest collected no tests; refusing to report success" >&2
    exit 1
  fi
  return "$rc"
}

workers=${TEST_WORKERS:-auto}
process_workers=${TEST_PROCESS_WORKERS:-3}
unit_db_workers=${TEST_UNIT_DB_WORKERS:-2}
unit_db_redis=${TEST_UNIT_DB_REDIS_URL:-redis://127.0.0.1:6379/13}
sqlite_url="sqlite:///$PWD/var/db.sqlite3"
mkdir -p var

if [ "$fast" = 1 ]; then
  say "ruff check"
  .venv/bin/ruff check .
  say "fast tier on SQLite (${TEST_WORKERS:-auto} workers)"
  DATABASE_URL="$sqlite_url" run_pytest -n "${TEST_WORKERS:-auto}" --tier=fast "$@"
  exit
fi

say "ruff check and ruff format --check"
.venv/bin/ruff check .
.venv/bin/ruff format --check .

say "contract artifact is up to date"
node contracts/build.mjs --check

pg_answers() {
  .venv/bin/python - "$1" <<'PY' 2>/dev/null
import sys, psycopg
psycopg.connect(sys.argv[1].rsplit("/", 1)[0] + "/postgres", connect_timeout=3).close()
PY
}

# The PostgreSQL pass always runs: on PG_TEST_URL if it is set, else on a server at the
# default address if one answers, else on a throwaway cluster of our own (scripts/postgres.sh)
# on a free port, removed when the suite is done (PG_TEST_THROWAWAY=1 asks for that one).
if [ -n "${PG_TEST_URL:-}" ]; then
  pg_answers "$PG_TEST_URL" || { echo "ERROR: no PostgreSQL answers at PG_TEST_URL=$PG_TEST_URL" >&2; exit 1; }
elif [ "${PG_TEST_THROWAWAY:-}" != 1 ] && pg_answers postgres://postgres@127.0.0.1:5432/authros; then
  PG_TEST_URL=postgres://postgres@127.0.0.1:5432/authros
else
  pg_dir=$(mktemp -d /tmp/authros-test-postgresql.XXXXXX)
  cleanups+=("bash scripts/postgres.sh stop $pg_dir")
  say "starting a throwaway PostgreSQL cluster in $pg_dir"
  PG_TEST_URL=$(bash scripts/postgres.sh start "$pg_dir")
fi

say "unit tier on SQLite ($workers workers)"
sqlite_rc=0
DATABASE_URL="$sqlite_url" run_pytest -n "$workers" --tier=unit "$@" || sqlite_rc=$?

# Two pytest runs on PostgreSQL, side by side: the process, browser and slow tests mostly
# wait on the processes they start (about 69% of two cores busy), and the unit tests that use
# the database fill the rest. The second has a database name and a Redis database of its own
# (pytest-django names the test databases after the first and the xdist worker, the same in
# both runs); its output is shown when it is done.
pg_rc=0
unit_db_url="${PG_TEST_URL%/*}/$(basename "${PG_TEST_URL##*/}")_unit_db"
unit_db_log=var/test-unit-db.log
say "on PostgreSQL ($PG_TEST_URL): the process, browser and slow tests ($process_workers workers)" \
  "and, beside them, the unit tests that use the database ($unit_db_workers workers, $unit_db_log)"
DATABASE_URL="$unit_db_url" TEST_REDIS_URL="$unit_db_redis" \
  PGOPTIONS="${PGOPTIONS:-} -c synchronous_commit=off" \
  run_pytest -n "$unit_db_workers" --tier=unit-db "$@" >"$unit_db_log" 2>&1 &
unit_db_pid=$!
cleanups+=("kill $unit_db_pid")
DATABASE_URL="$PG_TEST_URL" PGOPTIONS="${PGOPTIONS:-} -c synchronous_commit=off" \
  run_pytest -n "$process_workers" --tier=once "$@" || pg_rc=$?
unit_db_rc=0
wait "$unit_db_pid" || unit_db_rc=$?
say "on PostgreSQL ($unit_db_url): the unit tests that use the database"
cat "$unit_db_log"
[ "$unit_db_rc" = 0 ] || pg_rc=$unit_db_rc

say "SQLite pass: exit $sqlite_rc; PostgreSQL pass: exit $pg_rc"
[ "$sqlite_rc" = 0 ] && [ "$pg_rc" = 0 ]
