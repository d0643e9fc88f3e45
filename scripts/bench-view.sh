#!/usr/bin/env bash
# Cost of the live viewer: steps/s of the same run with no viewer, with a page attached
# for the whole run, and with a page that attached for the first second and left
# (interleaved, ROUNDS times each). In-process (100 agents) and distributed (10 agent
# processes × 100 agents).
#
#   scripts/bench-view.sh [ROUNDS]   (the release build, or GEESE=path/to/geese)
set -euo pipefail
ROUNDS="${1:-3}"
B="${GEESE:-${CARGO_TARGET_DIR:-$(dirname "$0")/../target}/release/geese}"
OUT="$(mktemp -d)"
trap 'rm -rf "$OUT"' EXIT

# run MODE VIEWER ARGS…: prints steps/s of one run.
run() {
    local viewer="$1"; shift
    local log="$OUT/log" extra=()
    [ "$viewer" != none ] && extra=(--view)
    "$B" run "$@" "${extra[@]}" --quiet --out "$OUT/r" >"$log" 2>/dev/null &
    local pid=$!
    if [ "$viewer" != none ]; then
        local url=""
        for _ in $(seq 100); do url=$(grep -o 'http://[^ ]*' "$log" || true); [ -n "$url" ] && break; sleep 0.1; done
        local t=600; [ "$viewer" = detached ] && t=1
        timeout "$t" curl -sN "${url}events" >/dev/null || true &
    fi
    wait "$pid"
    # In-process runs print their wall time; distributed ones their steps/s.
    local steps; steps=$(grep -c . "$OUT/r/steps.csv"); steps=$((steps - 1))
    if grep -q 'steps/s once' "$log"; then
        grep -o '([0-9.]* steps/s' "$log" | tr -d '(' | cut -d' ' -f1
    else
        awk -v n="$steps" '/^wall time:/ { printf "%.1f\n", n / $3 }' "$log"
    fi
}

for mode in in-process distributed; do
    if [ "$mode" = in-process ]; then args=(--agents 100 --steps 2000 --seed 3); else args=(--agents 1000 --processes 10 --steps 300 --seed 3); fi
    declare -A rates=()
    for r in $(seq "$ROUNDS"); do
        for v in none attached detached; do
            rates[$v]+="$(run "$v" "${args[@]}") "
        done
    done
    for v in none attached detached; do
        echo "$mode ${args[*]}: viewer $v: steps/s ${rates[$v]}"
    done
    unset rates
done
