#!/usr/bin/env bash
# `make test`: install what is missing, lint, then the whole suite on SQLite and, side by side,
# the tests that use the database on PostgreSQL (PG_TEST_URL, else a server at 127.0.0.1:5432,
# else a throwaway cluster of its own).
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/bootstrap.sh
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
  .venv/bin/pytest --durations=25 "$@" || rc=$?
  if [ "$rc" = 5 ]; then
    echo "ERROR: pytest collected no tests; refusing to report success" >&2
    exit 1
  fi
  return "$rc"
}

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

# Only the tests that touch the database run again: crypto, contract and agent-only tests do
# not depend on it. The two passes run side by side (much of the suite waits on workers, nodes
# and browsers rather than on a core); this one's output follows the SQLite pass's.
pg_log=var/test-postgresql.log
mkdir -p var
say "tests that use the database, on PostgreSQL ($PG_TEST_URL), in the background: $pg_log"
(DATABASE_URL="$PG_TEST_URL" run_pytest "$@" -m "not nodb" -p no:cacheprovider) >"$pg_log" 2>&1 &
pg_pid=$!
# Stopped with the rest if the SQLite pass is interrupted (a background job ignores Ctrl-C).
cleanups=("pkill -TERM -P $pg_pid" "${cleanups[@]}")

say "test suite on SQLite"
sqlite_rc=0
DATABASE_URL="sqlite:///$PWD/var/db.sqlite3" run_pytest "$@" || sqlite_rc=$?

pg_rc=0
wait "$pg_pid" || pg_rc=$?
say "tests that use the database, on PostgreSQL ($PG_TEST_URL): exit $pg_rc"
cat "$pg_log"
say "SQLite pass: exit $sqlite_rc; PostgreSQL pass: exit $pg_rc"
[ "$sqlite_rc" = 0 ] && [ "$pg_rc" = 0 ]
