#!/usr/bin/env bash
# Calibration Monte Carlo: #13's self-calibration target ("with calibration
# off by 0.3% focal / 1.5 px / 5 ms, mean error within 1.5x of the same flight
# with the true camera") over many draws of the error instead of the one that
# `scripts/bench_realistic.sh`'s flights ship, after that script (its flights
# in target/realistic/flights/).
#
# Each flight is navigated with the true camera (the simulator's: the shipped
# camera.json corrected by the scenario's `camera_error`) and with DRAWS
# camera.json files that hold an error of the yardstick's size in a drawn
# direction: the focal length 0.3% long or short, the principal point off by
# the scenario's (1.5, -1.0) px turned by an angle drawn uniformly, k1 off by
# 0.002 either way. The images, the IMU log and the 5 ms clock offset are the
# flight's own (only camera.json changes, so nothing is rendered again).
#
# Per flight: the true camera's mean error; over the draws, the mean, the
# least and the largest of the runs' mean errors, their mean over the true
# camera's, how many runs are within 1.5x of it; the runs' mean NEES (the
# mean over the draws, the least and the largest: a consistent navigator's is
# 3 on average over draws of the errors it models, whatever one flight's draw
# gives) and the farthest fix of all the runs in its own covariance's sigmas.
#
#   scripts/bench_calibration.sh
# Environment: OUT (default target/realistic), DRAWS (default 6), SEED
#   (default 1), NAV_ARGS (more trn navigate options), RESULTS (the results
#   file's name in OUT/calibration/, default results.md), FLIGHTS (names,
#   space-separated; default every flight of OUT/suite.tsv), ERRORS (which
#   errors the draws hold, comma-separated among focal, principal and k1;
#   default all three: the others are the true camera's), PRINCIPAL_PX (the
#   principal point error's length, px; default the scenario's, 1.8),
#   BASELINE (flight names, space-separated, or "all": those flights' draws
#   are navigated by the OpenCV baseline too, on the database
#   `scripts/bench_realistic.sh` built it for the flight's camera, named in
#   OUT/bench/results.json, with the same camera.json; the results then
#   give the baseline's mean over the draws and trn's over it), PY (the
#   baseline's Python, default .venv/bin/python as bench_nav.sh's).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
source scripts/realistic_suite.sh
PY=${PY:-.venv/bin/python}
work="$OUT/calibration"
label=${RESULTS:-results.md}
label=${label%.md}
runs="$work/$label"
rm -rf "$runs"
mkdir -p "$runs"
jobs="$runs/jobs.txt"
: > "$jobs"
while IFS=$'\t' read -r name flight db _; do
  if [ -n "${FLIGHTS:-}" ] && [[ " $FLIGHTS " != *" $name "* ]]; then continue; fi
  # A flight folder per camera: camera.json written, every other file linked.
  python3 - "$flight" "$runs/$name" "${DRAWS:-6}" "${SEED:-1}" "${ERRORS:-focal,principal,k1}" "${PRINCIPAL_PX:-}" <<'PY'
import json, math, os, random, sys
flight, base, draws, seed = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
errors = set(sys.argv[5].split(","))
principal_px = float(sys.argv[6]) if sys.argv[6] else None
unknown = errors - {"focal", "principal", "k1"}
if unknown:
    sys.exit(f"ERRORS: unknown {sorted(unknown)} (focal, principal, k1)")
shipped = json.load(open(os.path.join(flight, "camera.json")))
err = json.load(open(os.path.join(flight, "scenario.json")))["camera_error"]
true = json.loads(json.dumps(shipped))
true["fx"] *= 1 + err["focal_rel"]
true["fy"] *= 1 + err["focal_rel"]
true["cx"] += err["principal_du_px"]
true["cy"] += err["principal_dv_px"]
true["distortion"]["k1"] += err["k1"]
# One generator per flight and seed: the draws do not depend on which
# flights run.
rng = random.Random(f"{seed}/{os.path.basename(flight.rstrip('/'))}")
cameras = {"true": true}
for k in range(draws):
    focal = rng.choice((-1.0, 1.0)) * abs(err["focal_rel"])
    turn = rng.uniform(0.0, 2.0 * math.pi)
    du = err["principal_du_px"] * math.cos(turn) - err["principal_dv_px"] * math.sin(turn)
    dv = err["principal_du_px"] * math.sin(turn) + err["principal_dv_px"] * math.cos(turn)
    if principal_px is not None:
        scale = principal_px / math.hypot(err["principal_du_px"], err["principal_dv_px"])
        du, dv = du * scale, dv * scale
    k1 = rng.choice((-1.0, 1.0)) * abs(err["k1"])
    # Drawn whatever ERRORS says, so a draw's other errors stay the same.
    focal, du, dv, k1 = (x if on in errors else 0.0 for x, on in
                         ((focal, "focal"), (du, "principal"), (dv, "principal"), (k1, "k1")))
    c = json.loads(json.dumps(true))
    c["fx"] /= 1 + focal
    c["fy"] /= 1 + focal
    c["cx"] -= du
    c["cy"] -= dv
    c["distortion"]["k1"] -= k1
    c["_draw"] = {"focal_rel": focal, "principal_du_px": du, "principal_dv_px": dv, "k1": k1}
    cameras[f"draw{k + 1}"] = c
for label, cam in cameras.items():
    d = os.path.join(base, label, "flight")
    os.makedirs(d, exist_ok=True)
    for f in os.listdir(flight):
        if f != "camera.json":
            os.symlink(os.path.abspath(os.path.join(flight, f)), os.path.join(d, f))
    draw = cam.pop("_draw", None)
    json.dump(cam, open(os.path.join(d, "camera.json"), "w"), indent=2)
    if draw:
        json.dump(draw, open(os.path.join(base, label, "draw.json"), "w"), indent=2)
PY
  base=-
  if [ -n "${BASELINE:-}" ] && { [ "$BASELINE" = all ] || [[ " $BASELINE " == *" $name "* ]]; }; then
    base=$(python3 -c "import json, sys; print(next(r['baseline_db'] for r in json.load(open(sys.argv[1])) if r['scenario'] == sys.argv[2]))" \
      "$OUT/bench/results.json" "$name") || { echo "$name: no baseline database in $OUT/bench/results.json" >&2; exit 1; }
  fi
  for d in "$runs/$name"/*/; do
    # The baseline on the drawn cameras only.
    b=$base; [ "$(basename "$d")" = true ] && b=-
    echo "${d%/} $db $b" >> "$jobs"
  done
done < "$suite"

navigate() {
  read -r dir db base <<< "$1"
  # shellcheck disable=SC2086
  "$trn" navigate --db "$db" --flight "$dir/flight" --out "$dir/poses.csv" ${NAV_ARGS:-} > "$dir/report.json" 2> "$dir/log"
  "$trn" evaluate --flight "$dir/flight" --poses "$dir/poses.csv" --json "$dir/eval.json" > /dev/null 2>&1
  if [ "$base" != - ]; then
    mkdir -p "$dir/opencv"
    "$PY" scripts/baseline_opencv.py --db "$base" --flight "$dir/flight" --out "$dir/opencv/poses.csv" \
      > "$dir/opencv/report.json" 2> "$dir/opencv/log"
    "$trn" evaluate --flight "$dir/flight" --poses "$dir/opencv/poses.csv" --json "$dir/opencv/eval.json" > /dev/null 2>&1
  fi
}
export -f navigate; export trn NAV_ARGS PY
echo "== navigating $(wc -l < "$jobs") runs" >&2
tr '\n' '\0' < "$jobs" | xargs -0 -P 2 -I{} bash -c 'navigate "$1"' _ {}

python3 - "$work/$label.md" "$runs" "${NAV_ARGS:-}" "${ERRORS:-focal,principal,k1}" "${PRINCIPAL_PX:-1.8}" <<'PY'
import json, os, statistics, sys
out, runs, nav_args, errors, principal_px = sys.argv[1:6]
lines = [
    f"trn navigate {nav_args or '(default options)'}; true camera and {{draws}} drawn camera.json errors per flight ({errors}; the principal point {principal_px} px off)",
    "",
    "| flight | true camera m | draws: mean m | least–largest m | mean ÷ true | runs within 1.5× | mean NEES: mean | least–largest | farthest fix (sigma) |",
    "|---|---:|---:|---|---:|---:|---:|---|---:|",
]
def run(d):
    e = json.load(open(os.path.join(d, "eval.json")))["runs"][0]
    fixes = [f["error"]["pos_m"] for f in e["per_frame"] if f["status"] == "fix"]
    if not fixes:
        sys.exit(f"{d}: no fix (see its log)")
    c = e["consistency"]
    return sum(fixes) / len(fixes), c["mean_nees"], c["max_sigma_distance"]
def baseline(d):
    """The baseline's mean error over its fixes in draw folder d (None: not
    run; inf: no fix)."""
    path = os.path.join(d, "opencv", "eval.json")
    if not os.path.exists(path):
        return None
    e = json.load(open(path))["runs"][0]
    fixes = [f["error"]["pos_m"] for f in e["per_frame"] if f["status"] == "fix"]
    return sum(fixes) / len(fixes) if fixes else float("inf")
versus = []
draws = 0
for name in sorted(os.listdir(runs)):
    base = os.path.join(runs, name)
    if not os.path.isdir(base):
        continue
    true = run(os.path.join(base, "true"))
    names = [d for d in sorted(os.listdir(base)) if d.startswith("draw")]
    ds = [run(os.path.join(base, d)) for d in names]
    bs = [baseline(os.path.join(base, d)) for d in names]
    if any(b is None for b in bs) and any(b is not None for b in bs):
        print(f"{name}: the baseline failed on some draws (see their opencv/log)", file=sys.stderr)
    if bs and all(b is not None for b in bs):
        fixed = [(m, b) for (m, _, _), b in zip(ds, bs) if b != float("inf")]
        versus.append(
            f"| {name} | {len(fixed)} of {len(bs)} | "
            + (f"{statistics.mean(b for _, b in fixed):.1f} | {statistics.mean(m for m, _ in fixed):.1f} | "
               f"{statistics.mean(m for m, _ in fixed) / statistics.mean(b for _, b in fixed):.2f} | "
               f"{min(m / b for m, b in fixed):.2f}–{max(m / b for m, b in fixed):.2f} |" if fixed else "n/a | n/a | n/a | n/a |")
        )
    draws = len(ds)
    means = [m for m, _, _ in ds]
    nees = [n for _, n, _ in ds]
    mean = statistics.mean(means)
    within = sum(m <= 1.5 * true[0] for m in means)
    far = max(s for _, _, s in ds)
    lines.append(
        f"| {name} | {true[0]:.1f} | {mean:.1f} | {min(means):.1f}–{max(means):.1f} | {mean / true[0]:.2f} "
        f"| {within} of {len(ds)} | {statistics.mean(nees):.2f} | {min(nees):.2f}–{max(nees):.2f} | {far:.1f} |"
    )
lines[0] = lines[0].replace("{draws}", str(draws))
if versus:
    lines += ["", "Against the OpenCV baseline on the same drawn camera.json (the draws it fixed at least once):", "",
              "| flight | draws the baseline fixed | baseline mean m | trn mean m | trn ÷ baseline | per draw |",
              "|---|---:|---:|---:|---:|---|"] + versus
open(out, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
PY
