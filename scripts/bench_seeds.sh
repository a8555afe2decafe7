#!/usr/bin/env bash
# How much of a realistic flight's figure is its one rendering: each flight of
# the realistic suite (after scripts/bench_realistic.sh: its databases and
# suite in target/realistic/) simulated again under SEEDS other seeds (the
# scenario's `seed` replaced: other clouds, cords, image and IMU noise,
# initial error and random parts of the motion (a balloon's drift, spin bursts
# and sway), the same scenario otherwise: its path, sun, camera and calibration
# error) and
# navigated on the same default database, so a change to the navigator or the
# database can be judged over several renderings instead of one.
#
# The renderings are kept (OUT/seeds/flights/NAME/sSEED/) and only simulated
# when missing, so runs with other navigator options (NAV_ARGS) or another
# database (DB_SIERRA, DB_SALTLAKE) navigate the same images; each such run
# is a LABEL (its runs in OUT/seeds/LABEL/).
#
# Per flight: the mean over the seeds of the runs' mean error, their standard
# deviation, the least and the largest, the fix share over all frames, and the
# farthest fix of all the runs in its own covariance's sigmas; then the sum of
# the flights' means (each flight's mean over the seeds).
#
#   scripts/bench_seeds.sh
# Environment: OUT (default target/realistic), SEEDS (default "101 102 103"),
#   FLIGHTS (names, space-separated; default every flight of OUT/suite.tsv),
#   LABEL (default default), NAV_ARGS (more trn navigate options),
#   DB_SIERRA / DB_SALTLAKE (databases instead of the suite's), JOBS
#   (parallel runs, default the cores), BASELINE (flight names,
#   space-separated, or "all": those renderings are navigated by the OpenCV
#   baseline too, once (kept beside the rendering), on the database
#   `scripts/bench_realistic.sh` built it for the flight's camera, named in
#   OUT/bench/results.json; the results then give its mean over the seeds and
#   trn's over it), PY (the baseline's Python, default .venv/bin/python).
# Results in OUT/seeds/LABEL/results.md.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
source scripts/realistic_suite.sh
scen_dir=data-samples/scenarios/realistic
# The worlds as bench_realistic.sh renders them.
source scripts/realistic_worlds.sh
declare -A db_of
db_of[sierra]=${DB_SIERRA:-}
db_of[saltlake]=${DB_SALTLAKE:-}
for w in sierra saltlake; do
  [ -z "${db_of[$w]}" ] || [ -f "${db_of[$w]}" ] \
    || { echo "DB_${w^^}: no database at ${db_of[$w]}" >&2; exit 1; }
done
seeds=${SEEDS:-101 102 103}
label=${LABEL:-default}
[[ "$label" =~ ^[A-Za-z0-9._-]+$ ]] || { echo "LABEL: '$label' is not a plain name (letters, digits, . _ -)" >&2; exit 1; }
[ "$label" != flights ] || { echo "LABEL: 'flights' is where the renderings are kept" >&2; exit 1; }
jobs=${JOBS:-$(nproc)}
PY=${PY:-.venv/bin/python}
for s in $seeds; do
  [[ "$s" =~ ^[0-9]+$ ]] || { echo "SEEDS: '$s' is not a whole number" >&2; exit 1; }
done
for n in ${FLIGHTS:-}; do
  awk -F'\t' -v n="$n" '$1 == n { found = 1 } END { exit !found }' "$suite" \
    || { echo "FLIGHTS: $n is not in $suite" >&2; exit 1; }
done
renders="$OUT/seeds/flights"
runs="$OUT/seeds/$label"
mkdir -p "$renders"
rm -rf "$runs"
mkdir -p "$runs"
: > "$runs/jobs.tsv"
while IFS=$'\t' read -r name _ db ortho_file _ opts; do
  if [ -n "${FLIGHTS:-}" ] && [[ " $FLIGHTS " != *" $name "* ]]; then continue; fi
  world=${name%%-*}
  [ -n "${db_of[$world]:-}" ] && db=${db_of[$world]}
  base=-
  if [ -n "${BASELINE:-}" ] && { [ "$BASELINE" = all ] || [[ " $BASELINE " == *" $name "* ]]; }; then
    base=$(python3 -c "import json, sys; print(next(r['baseline_db'] for r in json.load(open(sys.argv[1])) if r['scenario'] == sys.argv[2]))" \
      "$OUT/bench/results.json" "$name") || { echo "$name: no baseline database in $OUT/bench/results.json" >&2; exit 1; }
  fi
  for s in $seeds; do
    f="$renders/$name/s$s"
    if [ ! -f "$f/flight/frames.csv" ] || [ "$scen_dir/$name.json" -nt "$f/flight/frames.csv" ]; then
      echo "== simulate $name, seed $s" >&2
      rm -rf "$f"
      mkdir -p "$f"
      python3 - "$scen_dir/$name.json" "$s" "$f/scenario.json" <<'PY'
import json, sys
src, seed, out = sys.argv[1:]
s = json.load(open(src))
s["seed"] = int(seed)
json.dump(s, open(out, "w"), indent=1)
PY
      read -r -a opt_arr <<< "$opts"
      "$trn" simulate --ortho "$ortho_file" --dem "${dem[$world]}" "${opt_arr[@]}" \
        --scenario "$f/scenario.json" --out "$f/flight.part" > "$f/simulate.json" 2> "$f/simulate.log"
      mv "$f/flight.part" "$f/flight"
    fi
    printf '%s\t%s\t%s\t%s\t%s\n' "$name" "$s" "$f/flight" "$db" "$base" >> "$runs/jobs.tsv"
  done
done < "$suite"
[ -s "$runs/jobs.tsv" ] || { echo "no flight in $suite" >&2; exit 1; }
echo "== navigate ($label: ${NAV_ARGS:-default options}), $jobs at a time" >&2
export trn runs NAV_ARGS PY
# shellcheck disable=SC2016
tr '\t' ' ' < "$runs/jobs.tsv" | xargs -P "$jobs" -L 1 bash -c '
  set -euo pipefail
  name=$0 s=$1 flight=$2 db=$3 base=$4
  d="$runs/$name/s$s"
  mkdir -p "$d"
  read -r -a nav_args <<< "${NAV_ARGS:-}"
  "$trn" navigate --db "$db" --flight "$flight" --out "$d/poses.csv" "${nav_args[@]}" \
    > "$d/report.json" 2> "$d/navigate.log"
  "$trn" evaluate --flight "$flight" --poses "$d/poses.csv" --json "$d/eval.json" > "$d/eval.txt" 2>&1
  # The baseline does not depend on trn'"'"'s options: once per rendering.
  o="${flight%/flight}/opencv"
  if [ "$base" != - ] && [ ! -f "$o/eval.json" ]; then
    rm -rf "$o.part" && mkdir -p "$o.part"
    "$PY" scripts/baseline_opencv.py --db "$base" --flight "$flight" --out "$o.part/poses.csv" \
      > "$o.part/report.json" 2> "$o.part/log"
    "$trn" evaluate --flight "$flight" --poses "$o.part/poses.csv" --json "$o.part/eval.json" > /dev/null 2>&1
    rm -rf "$o" && mv "$o.part" "$o"
  fi
'
python3 - "$runs" "$label" "${NAV_ARGS:-}" <<'PY'
import json, math, os, statistics, sys
runs, label, nav_args = sys.argv[1:]
rows = {}
baselines = {}
def mean_error(path):
    """Mean error over the fixes of an evaluation (nan: no fix), the fixes, the frames, the farthest fix."""
    ev = json.load(open(path))["runs"][0]
    frames = ev["per_frame"]
    fixes = [f["error"]["pos_m"] for f in frames if f["status"] == "fix"]
    far = (ev.get("consistency") or {}).get("max_sigma_distance", math.nan)
    return (sum(fixes) / len(fixes) if fixes else math.nan, len(fixes), len(frames), far)
for line in open(os.path.join(runs, "jobs.tsv")):
    name, seed, flight, _, base = line.rstrip("\n").split("\t")
    rows.setdefault(name, []).append(mean_error(os.path.join(runs, name, f"s{seed}", "eval.json")))
    if base != "-":
        baselines.setdefault(name, []).append(mean_error(os.path.join(os.path.dirname(flight), "opencv", "eval.json"))[0])
lines = [
    f"{label} ({nav_args or 'default options'}), seeds per flight: {max(len(v) for v in rows.values())}",
    "",
    "| flight | mean of the runs' mean errors m | sd m | least–largest m | fixes | farthest fix (sigma) |",
    "|---|---:|---:|---|---:|---:|",
]
total = 0.0
for name, v in rows.items():
    means = [m for m, *_ in v]
    mean = statistics.fmean(means)
    sd = statistics.stdev(means) if len(means) > 1 else math.nan
    total += mean
    fixes, frames = sum(f for _, f, _, _ in v), sum(n for _, _, n, _ in v)
    far = max(x for *_, x in v)
    lines.append(
        f"| {name} | {mean:.1f} | {'n/a' if math.isnan(sd) else f'{sd:.1f}'} | {min(means):.1f}–{max(means):.1f} "
        f"| {100 * fixes / frames:.0f}% | {far:.1f} |"
    )
lines += ["", f"Sum of the flights' means: {total:.1f} m"]
if baselines:
    lines += [
        "",
        "Against the OpenCV baseline on the same renderings (those it fixed at least once):",
        "",
        "| flight | renderings the baseline fixed | baseline mean m | trn mean m | trn ÷ baseline | per rendering |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for name, bs in baselines.items():
        pairs = [(m, b) for (m, *_), b in zip(rows[name], bs) if not math.isnan(b)]
        if not pairs:
            lines.append(f"| {name} | 0 of {len(bs)} | n/a | n/a | n/a | n/a |")
            continue
        tm, bm = statistics.fmean(m for m, _ in pairs), statistics.fmean(b for _, b in pairs)
        lines.append(
            f"| {name} | {len(pairs)} of {len(bs)} | {bm:.1f} | {tm:.1f} | {tm / bm:.2f} "
            f"| {min(m / b for m, b in pairs):.2f}–{max(m / b for m, b in pairs):.2f} |"
        )
open(os.path.join(runs, "results.md"), "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
PY
