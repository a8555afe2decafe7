#!/usr/bin/env bash
# Integrity through a narrow view (issue #13: no accepted fix more than 5
# sigma or 250 m from the truth): a hole in the cloud, as
# `WINDOW=F scripts/bench_outage.sh` makes it (every image from T0 for
# DURATION seconds grey but for a centred box of F times its sides, a few
# dozen landmarks), run on the shipped rendering of a realistic flight and on
# each of its other renderings that scripts/bench_seeds.sh left in
# OUT/seeds/flights/FLIGHT/sSEED/, since one rendering says little about a
# narrow view's worst fix.
#
# Per rendering and box: the fixes accepted in the outage, the worst of them
# (m), and the farthest fix of the whole run in its own covariance's sigmas
# (`trn evaluate`, with its time); then how many runs accepted a fix beyond
# 250 m or 5 sigma. Results in WORK/results.md.
#
# Usage: scripts/bench_narrow.sh [FLIGHT]   (default sierra-balloon-nadir)
# Environment: BOXES (default "0.35 0.45"), T0 (15), DURATION (30), TRN (a trn
#   binary; default this checkout's, built), NAV_ARGS (more trn navigate
#   options), FILTER (tight), OUT (target/realistic), WORK (OUT/narrow).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
name=${1:-sierra-balloon-nadir}
world=${name%%-*}
boxes=${BOXES:-0.35 0.45}
t0=${T0:-15}; dur=${DURATION:-30}
filter=${FILTER:-tight}
work=${WORK:-$OUT/narrow}
[ -f "$OUT/flights/$name/frames.csv" ] && [ -f "$OUT/db/$world.gpkg" ] \
  || { echo "run scripts/bench_realistic.sh first ($OUT/flights/$name, $OUT/db/$world.gpkg)" >&2; exit 1; }
for b in $boxes; do
  python3 -c "import sys; b = float(sys.argv[1]); sys.exit(0 if 0 < b < 1 else 1)" "$b" 2>/dev/null \
    || { echo "BOXES: '$b' is not a share of the image's sides (0 < F < 1)" >&2; exit 1; }
done
if [ -z "${TRN:-}" ]; then cargo build --release --quiet --bin trn; fi
trn=$(readlink -f "${TRN:-target/release/trn}")
# bench_outage.sh reads OUT/flights/NAME and OUT/db/WORLD.gpkg: a staging
# folder of links gives it every rendering under a name of that world.
stage="$work/stage"
rm -rf "$work"; mkdir -p "$stage/flights" "$stage/db"
ln -s "$(readlink -f "$OUT/db/$world.gpkg")" "$stage/db/$world.gpkg"
renderings=(shipped)
ln -s "$(readlink -f "$OUT/flights/$name")" "$stage/flights/$world-shipped"
for d in "$OUT/seeds/flights/$name"/s*/flight; do
  [ -f "$d/frames.csv" ] || continue
  s=$(basename "$(dirname "$d")")
  renderings+=("$s")
  ln -s "$(readlink -f "$d")" "$stage/flights/$world-$s"
done
echo "${#renderings[@]} rendering(s) of $name: ${renderings[*]}" >&2
rows=()
for r in "${renderings[@]}"; do
  for b in $boxes; do
    run="$work/$r-$b"
    echo "== $name ($r), box $b" >&2
    OUT="$stage" TRN="$trn" FILTERS="$filter" WINDOW="$b" NAV_ARGS="${NAV_ARGS:-}" WORK="$run" \
      scripts/bench_outage.sh "$world-$r" "$t0" "$dur" > "$run.log" 2>&1 \
      || { echo "$name ($r), box $b: bench_outage.sh failed, see $run.log" >&2; exit 1; }
    rows+=("$r $b $run")
  done
done
python3 - "$work" "$filter" "$name" "$t0" "$dur" "${rows[@]}" <<'PY'
import json, sys
work, filt, name, t0, dur, rows = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5], sys.argv[6:]
out = [f"Narrow views of {name}: each image from {t0} s for {dur} s grey but for a centred box "
       f"(share of the sides); --filter {filt}.", "",
       "| rendering | box | fixes in the outage | worst of them (m) | farthest fix of the run (sigma, at s) |",
       "|---|---:|---:|---:|---:|"]
beyond_m = beyond_sigma = 0
worst_all = (0.0, "")
for row in rows:
    r, b, run = row.split(" ", 2)
    # bench_outage.sh's table, its columns found by their headers.
    table = [[c.strip() for c in l.strip().strip("|").split("|")]
             for l in open(f"{run}/results.md") if l.startswith("|")]
    head, cells = table[0], next(r for r in table if r[0] == filt)
    col = {h: i for i, h in enumerate(head)}
    n_fix, worst = int(cells[col["fixes in the outage"]]), cells[col["worst of them (m)"]]
    c = json.load(open(f"{run}/{filt}/eval.json"))["runs"][0].get("consistency", {})
    far, far_t = c.get("max_sigma_distance", float("nan")), c.get("max_sigma_distance_t", float("nan"))
    w = float(worst) if worst != "none" else 0.0
    beyond_m += w > 250.0
    beyond_sigma += far > 5.0
    if w > worst_all[0]:
        worst_all = (w, f"{r}, box {b}")
    out.append(f"| {r} | {b} | {n_fix} | {worst} | {far:.1f} ({far_t:.1f}) |")
out += ["", f"Runs with an accepted fix beyond 250 m: {beyond_m} of {len(rows)}; beyond 5 sigma: "
        f"{beyond_sigma} of {len(rows)}; the worst accepted fix in an outage: "
        + (f"{worst_all[0]:.1f} m ({worst_all[1]})." if worst_all[1] else "none.")]
open(f"{work}/results.md", "w").write("\n".join(out) + "\n")
print("\n".join(out))
PY
