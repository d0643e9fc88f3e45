#!/usr/bin/env bash
# Regenerates agent/geese-agent.order: the functions a `geese-agent` process executes,
# hottest first, which agent/build.rs hands to the linker (`--symbol-ordering-file`) so
# that they sit together in the binary. A one-agent process then touches ~2.5 MiB of
# code instead of ~8.5 MiB scattered over 12 MiB of text (the kernel maps the 16 pages
# around every page fault), and its resident memory drops from ~14 to ~7.5 MiB
# (issue 29; docs/PERFORMANCE.md). Run it after a dependency update or a large change
# to the agent's code path: `cargo test` fails (`footprint::agent_link_order_…`) once too few of
# the listed symbols are left in the binary.
#
#   scripts/agent-link-order.sh     (needs valgrind and python3; builds the release bins)
#
# How: a few short distributed runs (secure and insecure, one agent and twenty agents,
# foraging and nest, BeTr-GEESE and GEESE-BT) with every agent process under callgrind
# (`--demangle=no`: the linker wants the mangled names). Functions that callgrind saw
# and the binary defines are listed, most executed instructions first.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$ROOT/target}"
command -v valgrind >/dev/null || { echo "valgrind is required" >&2; exit 1; }
command -v python3 >/dev/null || { echo "python3 is required" >&2; exit 1; }
cargo build --release --bins
B="$CARGO_TARGET_DIR/release"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
mkdir -p "$WORK/bin" "$WORK/cg"
ln -s "$B/geese-world" "$WORK/bin/geese-world"
cat >"$WORK/bin/geese-agent" <<EOF
#!/bin/sh
exec valgrind -q --tool=callgrind --demangle=no --callgrind-out-file=$WORK/cg/agent.%p.out "$B/geese-agent" "\$@"
EOF
chmod +x "$WORK/bin/geese-agent"

run() { GEESE_BIN_DIR="$WORK/bin" timeout 900 "$B/geese" run -q --out "$WORK/out" "$@" >/dev/null; }
run --processes 2 --agents 2 --steps 1000
run --processes 4 --agents 20 --steps 2000
run --processes 2 --agents 20 --steps 1000 --insecure
run --processes 2 --agents 20 --steps 1000 --task nest
run --processes 2 --agents 20 --steps 1000 --algorithm geese-bt

for f in "$WORK"/cg/agent.*.out; do
    callgrind_annotate --threshold=100 --inclusive=no "$f" >"$f.txt"
done
nm --defined-only "$B/geese-agent" | awk '$2 ~ /^[tTwW]$/ {print $3}' >"$WORK/defined"
python3 - "$WORK" >"$ROOT/agent/geese-agent.order" <<'EOF'
import collections, glob, re, sys
work = sys.argv[1]
defined = set(open(f"{work}/defined").read().split())
ir = collections.Counter()
for path in glob.glob(f"{work}/cg/agent.*.out.txt"):
    for line in open(path):
        m = re.match(r"\s*([\d,]+) \([^)]*\)\s+\S+?:(\S+)", line)
        if m:
            ir[m.group(2)] += int(m.group(1).replace(",", ""))
# Functions with a cost below the annotation's threshold are still executed: every
# name callgrind defined, after the costed ones.
seen = set()
for path in glob.glob(f"{work}/cg/agent.*.out"):
    for line in open(path):
        m = re.match(r"c?fn=\(\d+\) (\S+)$", line)
        if m and m.group(1) not in ir:
            seen.add(m.group(1))
order = [n for n, _ in ir.most_common() if n in defined]
order += sorted(n for n in seen if n in defined)
print("\n".join(order))
print(f"{len(order)} functions", file=sys.stderr)
EOF
echo "wrote agent/geese-agent.order"
