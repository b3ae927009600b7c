#!/usr/bin/env bash
# Make sure a Redis answers at $REDIS_URL (default 127.0.0.1:6379): reuse it, else start one.
set -euo pipefail
url=${REDIS_URL:-redis://127.0.0.1:6379/0}
if redis-cli -u "$url" ping >/dev/null 2>&1; then exit 0; fi
hostport=${url#redis://}; hostport=${hostport%%/*}; hostport=${hostport##*@}
host=${hostport%%:*}; port=${hostport##*:}
case "$host" in
  127.0.0.1|localhost) ;;
  *) echo "Redis at $url does not answer and is not local; start it yourself" >&2; exit 1 ;;
esac
echo "starting redis-server on $host:$port" >&2
mkdir -p var/redis
redis-server --daemonize yes --bind 127.0.0.1 --port "$port" --save "" --appendonly no \
  --dir "$PWD/var/redis" --logfile "$PWD/var/redis/redis.log"
for _ in $(seq 50); do redis-cli -u "$url" ping >/dev/null 2>&1 && exit 0; sleep 0.1; done
echo "redis-server did not come up; see var/redis/redis.log" >&2; exit 1
