#!/usr/bin/env bash
# `make run`: install what is missing, then start the stack on the embedded defaults
# (SQLite, local Redis, a local anvil chain whose state survives restarts), the Celery
# worker and beat, and the portal.
# Ctrl-C stops everything this script started; running it again is safe.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/bootstrap.sh

export DJANGO_DEBUG=${DJANGO_DEBUG:-true}
export REDIS_URL=${REDIS_URL:-redis://127.0.0.1:6379/0}
PORTAL_HOST=${PORTAL_HOST:-127.0.0.1}
PORTAL_PORT=${PORTAL_PORT:-8000}
ANVIL_PORT=${ANVIL_PORT:-8545}
export CHAIN_RPC_URL=${CHAIN_RPC_URL:-http://127.0.0.1:$ANVIL_PORT}
ANVIL=node_modules/@foundry-rs/anvil-linux-amd64/bin/anvil
LOG_DIR=var/log
mkdir -p "$LOG_DIR" var/anvil

say() { printf '\033[1;32m[run]\033[0m %s\n' "$*"; }
PIDS=()
OWN_REDIS=
cleanup() {
  trap - INT TERM EXIT
  if [ ${#PIDS[@]} -gt 0 ]; then
    say "stopping ${#PIDS[@]} process(es) started by make run"
    kill "${PIDS[@]}" 2>/dev/null || true
    wait "${PIDS[@]}" 2>/dev/null || true
  fi
  if [ -n "$OWN_REDIS" ]; then
    say "stopping the redis-server started by make run"
    redis-cli -u "$REDIS_URL" shutdown nosave >/dev/null 2>&1 || true
  fi
}
fail() {
  echo "make run: $*" >&2
  exit 1
}
trap 'cleanup; exit 0' INT TERM
trap cleanup EXIT

rpc_answers() {
  curl -sf -m 2 -H 'Content-Type: application/json' \
    -d '{"jsonrpc":"2.0","id":1,"method":"eth_chainId","params":[]}' "$1" >/dev/null 2>&1
}

if redis-cli -u "$REDIS_URL" ping >/dev/null 2>&1; then
  say "reusing the Redis at $REDIS_URL"
else
  OWN_REDIS=1
  bash scripts/redis.sh
  say "started Redis at $REDIS_URL (stopped again on Ctrl-C)"
fi

if rpc_answers "$CHAIN_RPC_URL"; then
  say "reusing the chain node at $CHAIN_RPC_URL"
else
  say "starting anvil on 127.0.0.1:$ANVIL_PORT (state kept in var/anvil/state.json)"
  "$ANVIL" --host 127.0.0.1 --port "$ANVIL_PORT" --state var/anvil/state.json \
    --state-interval 5 >"$LOG_DIR/anvil.log" 2>&1 &
  PIDS+=($!)
  for _ in $(seq 100); do rpc_answers "$CHAIN_RPC_URL" && break; sleep 0.1; done
  rpc_answers "$CHAIN_RPC_URL" || fail "anvil did not start; see $LOG_DIR/anvil.log"
fi

.venv/bin/python manage.py migrate --noinput >/dev/null
.venv/bin/python manage.py chain_deploy
.venv/bin/python manage.py chain_status

say "starting the Celery workers and beat (logs in $LOG_DIR/worker.log, verify.log, beat.log)"
.venv/bin/celery -A portal worker -l INFO -c 2 -n "authros-worker-$$@%h" >"$LOG_DIR/worker.log" 2>&1 &
PIDS+=($!)
# Views' integrity checks have a worker of their own: they never wait behind chain receipts.
.venv/bin/celery -A portal worker -l INFO -c 1 -n "authros-verify-$$@%h" \
  -Q "${CELERY_QUEUE:-authros}-verify" >"$LOG_DIR/verify.log" 2>&1 &
PIDS+=($!)
.venv/bin/celery -A portal beat -l INFO -s var/celerybeat-schedule >"$LOG_DIR/beat.log" 2>&1 &
PIDS+=($!)

say "starting the portal on http://$PORTAL_HOST:$PORTAL_PORT/"
.venv/bin/python manage.py runserver --noreload "$PORTAL_HOST:$PORTAL_PORT" \
  >"$LOG_DIR/portal.log" 2>&1 &
PIDS+=($!)

portal_answers() { curl -sf -o /dev/null "http://$PORTAL_HOST:$PORTAL_PORT/admin/login/"; }
for _ in $(seq 150); do portal_answers && break; sleep 0.2; done
portal_answers || fail "the portal did not answer on $PORTAL_HOST:$PORTAL_PORT; see $LOG_DIR/portal.log"

# --- the ROS side: a master, the simulated robot and an agent for a demo owner ----------
export ROS_MASTER_URI=${ROS_MASTER_URI:-http://127.0.0.1:11311}
export ROS_IP=${ROS_IP:-127.0.0.1}
export ROS_HOME=$PWD/var/ros
export ROS_LOG_DIR=$PWD/$LOG_DIR/ros
mkdir -p "$ROS_HOME" "$ROS_LOG_DIR"
if timeout 5 rostopic list >/dev/null 2>&1; then
  say "reusing the ROS master at $ROS_MASTER_URI"
else
  ros_port=${ROS_MASTER_URI##*:}
  say "starting roscore on port $ros_port"
  roscore -p "$ros_port" >"$LOG_DIR/roscore.log" 2>&1 &
  PIDS+=($!)
  for _ in $(seq 100); do timeout 5 rostopic list >/dev/null 2>&1 && break; sleep 0.2; done
  timeout 5 rostopic list >/dev/null 2>&1 || fail "roscore did not start; see $LOG_DIR/roscore.log"
fi

DEMO=$(.venv/bin/python manage.py demo_setup --dir var/demo --portal-url "http://$PORTAL_HOST:$PORTAL_PORT")
DEMO_USER=$(printf '%s' "$DEMO" | .venv/bin/python -c 'import json,sys; print(json.load(sys.stdin)["username"])')
DEMO_PASSWORD=$(cat var/demo/password)
say "starting the simulated robot and the demo owner's agent"
.venv/bin/python -m ros_agent.sim >"$LOG_DIR/sim.log" 2>&1 &
PIDS+=($!)
.venv/bin/python -m ros_agent --config var/demo/agent.yaml >"$LOG_DIR/agent.log" 2>&1 &
PIDS+=($!)
cat <<MSG

  AuthROS portal is up.
    Portal:        http://$PORTAL_HOST:$PORTAL_PORT/
    Log in as:     $DEMO_USER / $DEMO_PASSWORD   (the simulated robot's data arrives there)
    Admin console: http://$PORTAL_HOST:$PORTAL_PORT/admin/   (create a login: .venv/bin/python manage.py createsuperuser)
    API docs:      http://$PORTAL_HOST:$PORTAL_PORT/api/docs/
    Chain node:    $CHAIN_RPC_URL
    Logs:          $LOG_DIR/
  Press Ctrl-C to stop everything started here.

MSG
wait -n "${PIDS[@]}"
say "a process exited; see $LOG_DIR/"
