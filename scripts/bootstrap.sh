#!/usr/bin/env bash
# Install what is missing, idempotently: Debian packages, npm packages, the virtualenv.
# Used by `make run`, `make test` and `make bench`; safe to run again at any time.
# `bootstrap.sh` installs what running needs (`make run`: the Python packages of
# requirements/run.txt); `bootstrap.sh --test` (make test) adds the test tooling: PostgreSQL
# (the suite's second database), Chromium (browser tests), systemd's analyzer (the unit tests)
# and requirements/dev.txt (Playwright, pytest, the linters, the benchmarks' plotting, ...).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(
  python3-venv python3-dev redis-server
  ros-core python3-rospy python3-rosmaster python3-roslaunch
  python3-nav-msgs python3-sensor-msgs python3-std-msgs
)
TEST_APT_PACKAGES=(postgresql postgresql-client chromium systemd)
# every version and hash locked (`make lock`); pip refuses a download whose hash differs
REQUIREMENTS=requirements/run.txt
if [ "${1:-}" = "--test" ]; then
  APT_PACKAGES+=("${TEST_APT_PACKAGES[@]}"); REQUIREMENTS=requirements/dev.txt; shift
fi
# --list: what this run would install, one a line (the Debian packages, then the locked set of
# Python packages), and nothing installed
if [ "${1:-}" = "--list" ]; then printf '%s\n' "${APT_PACKAGES[@]}" "$REQUIREMENTS"; exit 0; fi
VENV=.venv
STAMP_DIR=$VENV/.stamps

log() { printf '\033[1;34m[bootstrap]\033[0m %s\n' "$*" >&2; }

as_root() {
  if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else
    log "need root for: $*"; exit 1; fi
}

install_debian_packages() {
  local missing=()
  for pkg in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" || missing+=("$pkg")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    log "installing Debian packages: ${missing[*]}"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  fi
}

install_npm_packages() {
  if ! command -v npm >/dev/null; then log "npm is required (apt-get install nodejs npm)"; exit 1; fi
  if [ ! -f node_modules/.package-lock.json ] || [ package-lock.json -nt node_modules/.package-lock.json ]; then
    log "installing npm packages (package-lock.json)"
    npm ci --no-audit --no-fund --loglevel=error
  fi
}

install_python_packages() {
  if [ ! -x $VENV/bin/python ]; then
    log "creating $VENV (sees Debian's rospy through --system-site-packages)"
    /usr/bin/python3 -m venv --system-site-packages $VENV
  fi
  mkdir -p $STAMP_DIR
  # one stamp per set: make test's (dev.txt) holds make run's, not the other way round
  local stamp
  stamp=$STAMP_DIR/$(basename "$REQUIREMENTS" .txt)
  if [ ! -f "$stamp" ] || [ "$REQUIREMENTS" -nt "$stamp" ]; then
    log "installing Python packages ($REQUIREMENTS)"
    $VENV/bin/python -m pip install -q --disable-pip-version-check --require-hashes \
      -r "$REQUIREMENTS"
    touch "$stamp"
  fi
}

# The project itself, editable, into .venv: its console scripts (`authros-verify`, as the export
# page prints it, and `authros-agent`) run from any folder and always run this checkout's code.
# setuptools is in the locked set, so no build isolation (nothing downloaded). Done again only
# when pyproject.toml changes or the venv points at another checkout (the stamp holds its path).
install_project() {
  if [ -x $VENV/bin/authros-verify ] && [ -f $STAMP_DIR/project ] \
    && [ "$(cat $STAMP_DIR/project)" = "$PWD" ] && [ ! pyproject.toml -nt $STAMP_DIR/project ]; then
    return
  fi
  log "installing the project into $VENV (editable: authros-verify, authros-agent)"
  $VENV/bin/python -m pip install -q --disable-pip-version-check --no-deps \
    --no-build-isolation --no-index -e .
  printf '%s' "$PWD" >$STAMP_DIR/project
}

install_debian_packages
install_npm_packages
install_python_packages
install_project
