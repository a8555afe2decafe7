#!/usr/bin/env bash
# What a realistic flight's error is made of: the flight simulated again with
# parts of its "world that is not the map" taken away, one at a time, and
# navigated on the same default database, after scripts/bench_realistic.sh
# (its databases and suite in target/realistic/).
#
# Variants of each flight's scenario (data-samples/scenarios/realistic/):
#   shipped      the scenario as it is (simulated again here, with the same seed)
#   true-camera  no calibration or clock error (`camera_error` removed)
#   no-sun       the true camera, and the ortho's own lighting (no `realism.sun`:
#                the world is not lit again under another sun)
#   sun+180      the true camera, the sun's azimuth turned by 180 degrees
#   no-realism   the true camera and no `realism` at all (no sun, haze, noise,
#                vignetting, blur, photometric change; the DEM and the
#                database's degraded DEM are still the two different ones)
# Per flight and variant: fix share, mean / p95 3D error of accepted fixes,
# the mean east / north / up error (a bias the world puts into every fix
# stays in the mean; noise does not), and what trn's inliers say with the
# true camera (scripts/inlier_geometry.py): their mean offset from the true
# pose's projection (px) and rms, and OpenCV's PnP on each fix's inliers
# alone (its mean 3D error, over the first and second half of the fixes).
# A second table splits the inliers by their landmark's shading share (how much
# of its template's contrast relief shading could make, as `trn build` stores
# it): per bin, the landmarks and the rms of each landmark's mean offset from
# the true projection (the part of its error that repeats in every frame it is
# seen in, what another sun moves).
#
#   scripts/bench_realism.sh
# Environment: OUT (default target/realistic), FLIGHTS (names, space-separated;
#   default the two low rockets), VARIANTS (which of the variants above,
#   space-separated; default all five), NAV_ARGS (more trn navigate options), DB (a
#   database to navigate on instead of the suite's, for FLIGHTS of one world:
#   e.g. one built with `--sun`), LABEL (runs and results in
#   OUT/realism/LABEL/ instead of OUT/realism/), PY (Python with OpenCV,
#   default .venv/bin/python).
# Results in OUT/realism/results.md (OUT/realism/LABEL/results.md).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
source scripts/realistic_suite.sh
PY=${PY:-.venv/bin/python}
scen_dir=data-samples/scenarios/realistic
# The worlds as bench_realistic.sh renders them.
source scripts/realistic_worlds.sh
flights=${FLIGHTS:-sierra-rocket-200x150 sierra-rocket-640x480}
read -r -a variants <<< "${VARIANTS:-shipped true-camera no-sun sun+180 no-realism}"
for v in "${variants[@]}"; do
  case $v in shipped | true-camera | no-sun | sun+180 | no-realism) ;;
    *) echo "VARIANTS: '$v' is not one of shipped, true-camera, no-sun, sun+180, no-realism" >&2; exit 1 ;;
  esac
done
read -r -a nav_args <<< "${NAV_ARGS:-}"
if [ -n "${LABEL:-}" ] && ! [[ "$LABEL" =~ ^[A-Za-z0-9._-]+$ ]]; then
  echo "LABEL: '$LABEL' is not a plain name (letters, digits, . _ -)" >&2
  exit 1
fi
work="$OUT/realism${LABEL:+/$LABEL}"
if [ -n "${DB:-}" ] && [ ! -f "$DB" ]; then
  echo "DB: no database at $DB" >&2
  exit 1
fi
mkdir -p "$work"
rows="$work/rows.tsv"
: > "$rows"
for name in $flights; do
  line=$(awk -F'\t' -v n="$name" '$1 == n' "$suite")
  [ -n "$line" ] || { echo "FLIGHTS: $name is not in $suite" >&2; exit 1; }
  IFS=$'\t' read -r _ _ db ortho_file _ opts <<< "$line"
  db=${DB:-$db}
  read -r -a opt_arr <<< "$opts"
  world=${name%%-*}
  for v in "${variants[@]}"; do
    d="$work/$name/$v"
    rm -rf "$d"
    mkdir -p "$d"
    python3 - "$scen_dir/$name.json" "$v" "$d/scenario.json" <<'PY'
import json, sys
src, variant, out = sys.argv[1:]
s = json.load(open(src))
if variant != "shipped":
    s.pop("camera_error", None)
if variant == "no-sun":
    s.get("realism", {}).pop("sun", None)
elif variant == "sun+180":
    sun = s["realism"]["sun"]
    sun["azimuth_deg"] = (sun["azimuth_deg"] + 180.0) % 360.0
elif variant == "no-realism":
    s.pop("realism", None)
json.dump(s, open(out, "w"), indent=1)
PY
    echo "== $name: $v" >&2
    "$trn" simulate --ortho "$ortho_file" --dem "${dem[$world]}" "${opt_arr[@]}" \
      --scenario "$d/scenario.json" --out "$d/flight" > "$d/simulate.json" 2> "$d/simulate.log"
    "$trn" navigate --db "$db" --flight "$d/flight" --out "$d/poses.csv" "${nav_args[@]}" \
      > "$d/report.json" 2> "$d/navigate.log"
    "$trn" evaluate --flight "$d/flight" --poses "$d/poses.csv" --json "$d/eval.json" > "$d/eval.txt" 2>&1
    "$PY" scripts/inlier_geometry.py "$d/flight" "$d" "$db" > "$d/inliers.json"
    printf '%s\t%s\t%s\n' "$name" "$v" "$d/eval.json" >> "$rows"
  done
done
python3 - "$rows" "$work/results.md" <<'PY'
import json, math, sys
rows, out = sys.argv[1:]
lines = [
    "| flight | variant | fix | mean m | p95 m | mean east m | mean north m | mean up m "
    "| inliers' offset u, v px | rms px | PnP on inliers m (first half, second) |",
    "|---|---|---:|---:|---:|---:|---:|---:|---|---:|---|",
]
for r in open(rows):
    name, variant, path = r.rstrip("\n").split("\t")
    frames = json.load(open(path))["runs"][0]["per_frame"]
    fixes = [f for f in frames if f["status"] == "fix"]
    if not fixes:
        lines.append(f"| {name} | {variant} | 0% | n/a | n/a | n/a | n/a | n/a | n/a | n/a | n/a |")
        continue
    err = sorted(f["error"]["pos_m"] for f in fixes)
    p95 = err[math.ceil(0.95 * len(err)) - 1]  # nearest rank, as trn evaluate's
    mean = [sum(f["error"]["enu_m"][i] for f in fixes) / len(fixes) for i in range(3)]
    g = json.load(open(path.replace("eval.json", "inliers.json")))
    lines.append(
        f"| {name} | {variant} | {100 * len(fixes) / len(frames):.0f}% | {sum(err) / len(err):.1f} | {p95:.1f} "
        f"| {mean[0]:+.1f} | {mean[1]:+.1f} | {mean[2]:+.1f} "
        f"| {g['offset_u_px']:+.2f}, {g['offset_v_px']:+.2f} | {g['rms_px']:.2f} "
        f"| {g['pnp_mean_m']:.1f} ({g['pnp_early_m']:.1f}, {g['pnp_late_m']:.1f}) |"
    )
lines += [
    "",
    "Inliers' offset that repeats, by their landmark's shading share: the rms over the landmarks of each "
    "one's mean offset from the true projection (px; in brackets, the landmarks):",
    "",
    "| flight | variant | share < 0.2 | 0.2–0.4 | 0.4–0.6 | ≥ 0.6 |",
    "|---|---|---:|---:|---:|---:|",
]
for r in open(rows):
    name, variant, path = r.rstrip("\n").split("\t")
    bins = json.load(open(path.replace("eval.json", "inliers.json"))).get("by_shading_share", [])
    cells = [f"{b['systematic_px']:.2f} ({b['landmarks']})" if b["landmarks"] else "n/a" for b in bins] or ["n/a"] * 4
    lines.append(f"| {name} | {variant} | " + " | ".join(cells) + " |")
open(out, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
print(f"wrote {out}", file=sys.stderr)
PY
