#!/usr/bin/env bash
# Start a Zenoh router and a GEESE swarm on this host, then stop the router.
#
#   deploy/swarm.sh [PROCESSES] [extra `geese run` flags...]
#   e.g. deploy/swarm.sh 20 --agents 100 --steps 2000 --agents-per-process 5
#
# Uses zenohd if it is on PATH (or $ZENOHD), otherwise `geese router` (no install).
# Everything listens on 127.0.0.1 only. The router is ended by its PID on exit.
set -euo pipefail
cd "$(dirname "$0")/.."

PROCESSES="${1:-10}"
shift || true
PORT="${GEESE_ROUTER_PORT:-7447}"
ENDPOINT="tcp/127.0.0.1:${PORT}"
BIN="${GEESE_BIN_DIR:-target/release}"

if [ ! -x "$BIN/geese" ] || [ ! -x "$BIN/geese-world" ] || [ ! -x "$BIN/geese-agent" ]; then
  cargo build --release --bins
fi

ZENOHD="${ZENOHD:-$(command -v zenohd || true)}"
if [ -n "$ZENOHD" ]; then
  "$ZENOHD" -c deploy/router.json5 --cfg "listen/endpoints:[\"${ENDPOINT}\"]" &
else
  "$BIN/geese" router --listen "$ENDPOINT" &
fi
ROUTER_PID=$!
trap 'kill "$ROUTER_PID" 2>/dev/null || true; wait "$ROUTER_PID" 2>/dev/null || true' EXIT

# Wait (bounded) for the router's port.
for _ in $(seq 1 50); do
  if (exec 3<>"/dev/tcp/127.0.0.1/${PORT}") 2>/dev/null; then break; fi
  sleep 0.1
done

GEESE_BIN_DIR="$BIN" "$BIN/geese" run --processes "$PROCESSES" --router "$ENDPOINT" "$@"
