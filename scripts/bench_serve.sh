#!/usr/bin/env bash
# Landmark server benchmark: typical navigator queries (nadir footprints of a
# 1024 x 768, 32 deg camera at the level that fits, server/examples/bench_serve.rs)
# on a database of >= 100k templates, made in-process against the store (SQLite,
# and the in-memory catalogue) and over HTTP against `trn serve` through the
# navigator's HttpSource (binary encoding, keep-alive), same number of clients.
# Usage: scripts/bench_serve.sh [CLIENTS] [SECONDS]   (default 4 clients, 10 s each)
# The database: a 10000 x 10000 synthetic ortho at 1 m (as scripts/bench_build.sh)
# built with --spacing 32 (~126k templates), in target/bench-data/serve.gpkg.
set -euo pipefail
cd "$(dirname "$0")/.."
clients=${1:-4}
seconds=${2:-10}
data=target/bench-data
mkdir -p "$data"
[ -n "${NO_BUILD:-}" ] || cargo build --release --quiet --bin trn -p trn -p trn-server --example bench_serve
trn=target/release/trn
ortho="$data/synth-10000.tif"; dem="$data/synth-10000-dem.tif"; db="$data/serve.gpkg"
if [ ! -f "$ortho" ] || [ ! -f "$dem" ]; then
  echo "generating $ortho ..." >&2
  "$trn" synth --ortho "$ortho.part.tif" --dem "$dem" --size 10000 --gsd 1.0 --seed 11 >/dev/null
  mv "$ortho.part.tif" "$ortho"
fi
if [ ! -f "$db" ]; then
  echo "building $db ..." >&2
  TRN_LOG=warn "$trn" build --ortho "$ortho" --dem "$dem" --dem-vertical ellipsoid --spacing 32 --out "$db" > "$data/serve-build.json"
fi
count=$(python3 -c "import json; print(json.load(open('$data/serve-build.json'))['templates'])" 2>/dev/null || echo "?")
log="$data/serve.log"
TRN_LOG=warn "$trn" serve --db "$db" --listen 127.0.0.1:0 > "$data/serve.addr" 2> "$log" &
pid=$!
trap 'kill $pid 2>/dev/null || true' EXIT
for _ in $(seq 100); do grep -q listening "$data/serve.addr" 2>/dev/null && break; sleep 0.1; done
url=$(sed -n 's/^listening on //p' "$data/serve.addr")
echo "database: $db ($count templates), $(nproc) cores, $clients clients, ${seconds} s per mode, server at $url"
target/release/examples/bench_serve --db "$db" --url "$url" --clients "$clients" --seconds "$seconds" | tee "$data/serve-bench.jsonl"
python3 - "$data/serve-bench.jsonl" <<'PY'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
print("| path | clients | queries/s | templates/query | p50 ms | p90 ms | p99 ms |")
print("|---|---:|---:|---:|---:|---:|---:|")
for r in rows:
    print(f"| {r['mode']} | {r['clients']} | {r['queries_per_s']:.0f} | {r['templates_per_query']:.0f} | {r['p50_ms']:.2f} | {r['p90_ms']:.2f} | {r['p99_ms']:.2f} |")
by = {r['mode']: r for r in rows}
if 'http' in by:
    for m in ('in-process', 'in-process-memory'):
        if m in by:
            print(f"HTTP throughput / {m}: {by['http']['queries_per_s'] / by[m]['queries_per_s']:.2f}")
PY
