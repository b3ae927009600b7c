#!/usr/bin/env bash
# `make test`: install what is missing, lint, then the whole suite on SQLite and, where a
# PostgreSQL answers (PG_TEST_URL, default postgres://postgres@127.0.0.1:5432/authros), on it too.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/bootstrap.sh
export REDIS_URL=${REDIS_URL:-redis://127.0.0.1:6379/0}
if ! redis-cli -u "$REDIS_URL" ping >/dev/null 2>&1; then
  bash scripts/redis.sh
  # Ours: stop it again when the suite is done, whatever its outcome.
  trap 'redis-cli -u "$REDIS_URL" shutdown nosave >/dev/null 2>&1 || true' EXIT
fi

say() { printf '\n\033[1;32m== %s\033[0m\n' "$*"; }

run_pytest() {
  local rc=0
  .venv/bin/pytest "$@" || rc=$?
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

say "test suite on SQLite"
DATABASE_URL="sqlite:///$PWD/var/db.sqlite3" run_pytest "$@"

PG_TEST_URL=${PG_TEST_URL:-postgres://postgres@127.0.0.1:5432/authros}
if .venv/bin/python - "$PG_TEST_URL" <<'PY' 2>/dev/null
import sys, psycopg
psycopg.connect(sys.argv[1].rsplit("/", 1)[0] + "/postgres", connect_timeout=3).close()
PY
then
  # Only the tests that touch the database run again: crypto, contract and agent-only
  # tests do not depend on it.
  say "tests that use the database, on PostgreSQL ($PG_TEST_URL)"
  DATABASE_URL="$PG_TEST_URL" run_pytest "$@" -m "not nodb"
elif [ "${CI:-}" = "true" ] || [ "${REQUIRE_POSTGRES:-}" = 1 ]; then
  echo "ERROR: no PostgreSQL at $PG_TEST_URL, and CI requires the PostgreSQL pass" >&2
  exit 1
else
  say "no PostgreSQL at $PG_TEST_URL: skipped the PostgreSQL pass"
fi
