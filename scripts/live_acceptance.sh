#!/usr/bin/env bash
# A live session with real processes, as issue 14's acceptance asks (docs/LIVE.md):
#   scripts/live_acceptance.sh SETUP RATE_HZ SECONDS [SEED] [extra `jointid live` args...]
# Runs `jointid live --record` against `acquire-sim` (data sub-steps 8, 1 % noise), samples
# the live process's RSS every 2 s, then prints the published `batch` parameters over time
# with their distance from the truth in standard errors (examples/live_timeline.rs), the
# live report's faults, and whether `jointid replay` on the recording gives the same final
# parameters. Needs `cargo build --release --bins --examples` first. Output in $OUT (default
# a temporary directory).
set -euo pipefail
setup=$1 rate=$2 seconds=$3 seed=${4:-11}
shift $(( $# < 4 ? $# : 4 ))
root=$(cd "$(dirname "$0")/.." && pwd)
bin=$root/target/release
out=${OUT:-$(mktemp -d)}
mkdir -p "$out"
prefix="acc_$$_"
"$bin/jointid" live --setup "$setup" --record "$out/session.mcap" --prefix "$prefix" --json "$@" \
    > "$out/live.json" 2> "$out/live.err" &
live=$!
sleep 1
( while kill -0 $live 2>/dev/null; do
      echo "$(date +%s) $(ps -o rss= -p $live 2>/dev/null || true)"; sleep 2
  done ) > "$out/rss.txt" &
"$bin/acquire-sim" --setup "$setup" --rate "$rate" --seconds "$seconds" --prefix "$prefix" \
    --substeps 8 --noise additive:0.01 --seed "$seed" > "$out/acquire.txt" 2>&1
wait $live || echo "jointid live exited $?"
echo "== $setup at $rate Hz for $seconds s, seed $seed ($out)"
python3 - "$out/live.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
f = r["faults"]
print(f"live: {r['samples']} samples, ended {r['ended']}, missing {f['missing_samples']}, "
      f"transport drops {f['transport_drops']}, windows identified {r['windows_identified']}, "
      f"latency p99 {r['latency']['p99_us']:.0f} us")
for w in r["warnings"]:
    print("  warning:", w[:200])
for p in r["parameters"]:
    print(f"  final {p['key']:<18} {p['value']:.6e} ± {p['std_error']:.3e}  truth {p.get('truth')}")
PY
awk 'NF==2 {n++; if (n==1) a=$2; b=$2; if ($2>m) m=$2} END {printf "RSS: first %d kB, last %d kB, max %d kB (%d samples)\n", a, b, m, n}' "$out/rss.txt"
"$bin/examples/live_timeline" "$out/session.mcap" --kind batch
"$bin/jointid" replay "$out/session.mcap" --json > "$out/replay.json" 2> "$out/replay.err" || echo "replay exited $?"
python3 - "$out/live.json" "$out/replay.json" <<'PY'
import json, sys
live = {p["key"]: (p["value"], p["std_error"]) for p in json.load(open(sys.argv[1]))["parameters"]}
rep = {p["key"]: (p["value"], p["std_error"]) for p in json.load(open(sys.argv[2]))["parameters"]}
same = live == rep
print("replay of the recording:", "identical final parameters" if same else "DIFFERENT")
if not same:
    for k in rep:
        print(f"  {k}: live {live.get(k)} replay {rep[k]}")
PY
