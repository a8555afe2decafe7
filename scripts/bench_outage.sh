#!/usr/bin/env bash
# A total cloud cover (issue #13): a realistic flight (run
# scripts/bench_realistic.sh first; default sierra-balloon-nadir, 30 km) with
# every image from T0 for DURATION seconds replaced by a uniform grey one (no
# landmark can match), navigated by trn with each --filter. Prints, per
# filter, the position error at the last frame before the outage, the drift
# at its last frame, the time from its end to the next fix and the mean error
# of the fixes after it; results in target/realistic/outage/results.md.
# (Drift: the change of the east/north/up error vector over the outage.)
# Usage: scripts/bench_outage.sh [FLIGHT [T0 [DURATION]]]   (default: sierra-balloon-nadir 15 30)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
name=${1:-sierra-balloon-nadir}; t0=${2:-15}; dur=${3:-30}
src="$OUT/flights/$name"
world=${name%%-*}
db="$OUT/db/$world.gpkg"
[ -f "$src/frames.csv" ] && [ -f "$db" ] || { echo "run scripts/bench_realistic.sh first ($src, $db)" >&2; exit 1; }
cargo build --release --quiet --bin trn
trn=target/release/trn
work="$OUT/outage"
f="$work/flight"
rm -rf "$work"; mkdir -p "$f/images"
for x in "$src"/*; do [ "$(basename "$x")" = images ] || ln -s "$(readlink -f "$x")" "$f/"; done
for x in "$src"/images/*; do ln -s "$(readlink -f "$x")" "$f/images/"; done
# Grey out the outage's images (a uniform picture: no texture, no match).
python3 - "$src" "$f" "$t0" "$dur" <<'PY'
import csv, sys, zlib, struct
src, dst, t0, dur = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
def png_grey(path_like_src, out):
    data = open(path_like_src, 'rb').read()
    w, h = struct.unpack('>II', data[16:24])
    raw = b''.join(b'\x00' + b'\x80' * w for _ in range(h))
    def chunk(t, d): return struct.pack('>I', len(d)) + t + d + struct.pack('>I', zlib.crc32(t + d) & 0xffffffff)
    png = b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', struct.pack('>IIBBBBB', w, h, 8, 0, 0, 0, 0)) + chunk(b'IDAT', zlib.compress(raw)) + chunk(b'IEND', b'')
    import os
    os.remove(out)
    open(out, 'wb').write(png)
n = 0
for row in csv.DictReader(open(f"{src}/frames.csv")):
    t = float(row['t'])
    if t0 <= t < t0 + dur:
        png_grey(f"{src}/{row['image']}", f"{dst}/{row['image']}"); n += 1
print(f"{n} images greyed from t = {t0} s for {dur} s", file=sys.stderr)
PY
rows=()
for filter in tight loose fixes; do
  d="$work/$filter"; mkdir -p "$d"
  "$trn" navigate --db "$db" --flight "$f" --filter "$filter" --out "$d/poses.csv" > "$d/report.json" 2> "$d/log.txt"
  "$trn" evaluate --flight "$f" --poses "$d/poses.csv" --json "$d/eval.json" > /dev/null 2>&1
  rows+=("$(python3 - "$d/eval.json" "$t0" "$dur" "$filter" <<'PY'
import json, sys
e = json.load(open(sys.argv[1]))['runs'][0]
t0, dur, filt = float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
fr = e['per_frame']
def err(r): return r['error']['pos_m']
before = [r for r in fr if r['t'] < t0]
during = [r for r in fr if t0 <= r['t'] < t0 + dur]
after = [r for r in fr if r['t'] >= t0 + dur]
first_fix = next((r['t'] - (t0 + dur) for r in after if r['status'] == 'fix'), float('nan'))
fixes_after = [err(r) for r in after if r['status'] == 'fix']
mean_after = sum(fixes_after) / len(fixes_after) if fixes_after else float('nan')
# Drift: how far the estimate moved against the truth over the outage (the
# change of the east/north/up error vector, not of its length).
e0, e1 = before[-1]['error']['enu_m'], during[-1]['error']['enu_m']
drift = sum((a - b) ** 2 for a, b in zip(e0, e1)) ** 0.5
print(f"| {filt} | {err(before[-1]):.1f} | {err(during[-1]):.1f} | {drift:.1f} | {first_fix:.1f} | {mean_after:.1f} |")
PY
)")
done
{
  echo "Outage: $name, images from t = $t0 s greyed for $dur s"
  echo
  echo "| filter | error before (m) | error at the outage's end (m) | drift (m) | next fix after (s) | mean error after (m) |"
  echo "|---|---:|---:|---:|---:|---:|"
  printf '%s\n' "${rows[@]}"
} | tee "$work/results.md"
