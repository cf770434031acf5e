#!/usr/bin/env bash
# Set up everything the tests need (Debian's PostgreSQL, Redis, Chromium and its driver, the
# venv), then run the linter and the type checker (their settings are in pyproject.toml) and the
# tests.
set -euo pipefail
cd "$(dirname "$0")/.."
as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

have_servers() {
  command -v redis-server >/dev/null && ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 \
    && command -v chromium >/dev/null && command -v chromedriver >/dev/null
}
if ! have_servers; then
  as_root apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql redis-server \
    chromium chromium-driver >/dev/null
fi
bash scripts/setup.sh test
.venv/bin/ruff check .
.venv/bin/mypy
exec .venv/bin/python -m pytest "$@"
