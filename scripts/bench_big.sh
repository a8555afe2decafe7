#!/usr/bin/env bash
# Real-size inputs benchmark (issue #12, point 5): `trn build` on
#  1. a 20000 x 20000 RGB ortho at 1 m (400 MP, tiled DEFLATE GeoTIFF, UTM
#     zone 13N) with a 1/3 arc-second DEM (1/10800 deg) in another CRS
#     (EPSG:4269, NAD83 geographic): peak RSS, wall time, templates, and
#     whether the progress bar is drawn (the build runs in a pseudo-terminal,
#     `script`, as indicatif draws only to a terminal);
#  2. a mosaic over two UTM zones: one synthetic scene cut along the -108 deg
#     meridian, its west part reprojected to zone 12N (EPSG:32612, 1 m) and its
#     east part kept in zone 13N (EPSG:32613), both with an alpha band; one
#     1/3" EPSG:4269 DEM over both; built together (`--ortho A --ortho B`).
#     Templates per source, and the templates in a strip +-500 m around the
#     zone border against equal strips 2.5 km away, for the mosaic and for the
#     same scene built as one zone-13N ortho (reference): a gap along the
#     border shows as a border/control ratio below the reference's.
# The DEMs are trn synth's ellipsoidal heights warped (bilinear) to the 1/3"
# grid, so the builds take --dem-vertical ellipsoid.
# Inputs are generated once and cached in target/bench-big/ (the 400 MP synth
# takes ~3.5 min on 2 cores); results in target/bench-big/results.md.
# Usage: scripts/bench_big.sh [SIZE_PX]   (default 20000)
# Environment: MOSAIC_SIZE=12000 (side of the scene cut into the two zones, px at 1 m)
set -euo pipefail
cd "$(dirname "$0")/.."
size=${1:-20000}
msize=${MOSAIC_SIZE:-12000}
data=target/bench-big
third=0.0000925925925926 # 1/3 arc-second in degrees (1/10800)
mkdir -p "$data"
scripts/install-deps.sh
cargo build --release --quiet --bin trn
trn=target/release/trn
tiff_co=(-co TILED=YES -co BLOCKXSIZE=512 -co BLOCKYSIZE=512 -co COMPRESS=DEFLATE)

# timed NAME CMD...: runs CMD, appends "NAME wall_s peak_rss_kb" to $data/gen-times.txt.
timed() {
  local name=$1; shift
  /usr/bin/time -f "%e %M" -o "$data/.timed" "$@"
  echo "$name $(cat "$data/.timed")" >> "$data/gen-times.txt"; rm -f "$data/.timed"
}
# to_1third SRC DST: warps a DEM to the 1/3" EPSG:4269 grid (target-aligned pixels).
to_1third() {
  gdalwarp -q -overwrite -t_srs EPSG:4269 -tr "$third" "$third" -tap -r bilinear -ot Float32 \
    -dstnodata -9999 -co TILED=YES -co COMPRESS=DEFLATE -co PREDICTOR=3 "$1" "$2.part.tif"
  mv "$2.part.tif" "$2"
}

# --- 1. 400 MP ortho, 1/3" DEM in EPSG:4269 ---------------------------------
ortho="$data/ortho-$size.tif"; dem_utm="$data/ortho-$size-dem-utm.tif"; dem="$data/dem-$size-4269.tif"
if [ ! -f "$ortho" ] || [ ! -f "$dem_utm" ]; then
  echo "generating $ortho (trn synth, a few minutes) ..." >&2
  timed "synth-$size" "$trn" synth --ortho "$ortho.part.tif" --dem "$dem_utm" --size "$size" \
    --gsd 1.0 --seed 12 --relief 300 >/dev/null
  mv "$ortho.part.tif" "$ortho"
fi
[ -f "$dem" ] || to_1third "$dem_utm" "$dem"

# --- 2. two-zone mosaic inputs ------------------------------------------------
# The scene is centred on the -108 deg meridian (the zone 12/13 border) at 40.1 N.
msrc="$data/mosaic-src-$msize.tif"; mdem_utm="$data/mosaic-src-$msize-dem-utm.tif"
mdem="$data/mosaic-$msize-dem-4269.tif"
mwest="$data/mosaic-$msize-z12.tif"; meast="$data/mosaic-$msize-z13.tif"
to_utm13() { gdaltransform -s_srs EPSG:4326 -t_srs EPSG:32613 -output_xy; }
to_geo() { gdaltransform -s_srs EPSG:32613 -t_srs EPSG:4326 -output_xy; }
read -r ce cn < <(echo "-108 40.1" | to_utm13)
e0=$(python3 -c "print(round($ce) - $msize // 2)"); n0=$(python3 -c "print(round($cn) + $msize // 2)")
if [ ! -f "$msrc" ] || [ ! -f "$mdem_utm" ]; then
  echo "generating $msrc (trn synth) ..." >&2
  timed "synth-$msize" "$trn" synth --ortho "$msrc.part.tif" --dem "$mdem_utm" --size "$msize" \
    --gsd 1.0 --seed 13 --relief 300 --east "$e0" --north "$n0" >/dev/null
  mv "$msrc.part.tif" "$msrc"
fi
[ -f "$mdem" ] || to_1third "$mdem_utm" "$mdem"
if [ ! -f "$mwest" ] || [ ! -f "$meast" ]; then
  echo "cutting $msrc along -108 deg into zones 12N and 13N ..." >&2
  # The meridian's eastings at the scene's top and bottom (it leans ~2 deg in zone 13).
  read -r _ lat_top < <(echo "$e0 $n0" | to_geo)
  read -r _ lat_bot < <(echo "$e0 $((n0 - msize))" | to_geo)
  read -r e_top _ < <(echo "-108 $lat_top" | to_utm13)
  read -r e_bot _ < <(echo "-108 $lat_bot" | to_utm13)
  # Windows reach 64 m past the meridian: the cutline, not the window, makes the edge.
  read -r west_cols east_col0 < <(python3 -c "
import math
lo, hi = min($e_top, $e_bot), max($e_top, $e_bot)
print(math.ceil(hi + 64 - $e0), math.floor(lo - 64 - $e0))")
  # Cutlines in WGS84 lon/lat, densified along the meridian.
  python3 - "$data/cut-west.geojson" "$data/cut-east.geojson" <<'PY'
import json, sys
lats = [39.5 + i * 0.001 for i in range(1001)]
meridian = [[-108.0, la] for la in lats]
def write(path, ring):
    ring = ring + [ring[0]]
    json.dump({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
              "geometry": {"type": "Polygon", "coordinates": [ring]}}]}, open(path, "w"))
write(sys.argv[1], [[-109.0, 39.5]] + meridian + [[-109.0, 40.5]])
write(sys.argv[2], meridian + [[-107.0, 40.5], [-107.0, 39.5]])
PY
  gdal_translate -q -of VRT -srcwin 0 0 "$west_cols" "$msize" "$msrc" "$data/west-src.vrt"
  gdal_translate -q -of VRT -srcwin "$east_col0" 0 "$((msize - east_col0))" "$msize" "$msrc" "$data/east-src.vrt"
  timed "warp-z12" gdalwarp -q -overwrite -multi -wo NUM_THREADS=ALL_CPUS -t_srs EPSG:32612 -tr 1 1 -tap \
    -r bilinear -cutline "$data/cut-west.geojson" -dstalpha "${tiff_co[@]}" "$data/west-src.vrt" "$mwest.part.tif"
  timed "cut-z13" gdalwarp -q -overwrite -multi -wo NUM_THREADS=ALL_CPUS -tr 1 1 -tap \
    -cutline "$data/cut-east.geojson" -dstalpha "${tiff_co[@]}" "$data/east-src.vrt" "$meast.part.tif"
  mv "$mwest.part.tif" "$mwest"; mv "$meast.part.tif" "$meast"
fi

# --- builds ---------------------------------------------------------------------
# build NAME ARGS...: `trn build ARGS --out $data/NAME.gpkg` in a pseudo-terminal (so
# that the progress bar is drawn), under /usr/bin/time: report JSON in NAME.json,
# terminal output in NAME.log, "peak_rss_kb wall_s user_s sys_s" in NAME.time.
build() {
  local name=$1; shift
  rm -f "$data/$name.gpkg" "$data/$name.time"
  local cmd show=/dev/null
  cmd="$(printf '%q ' /usr/bin/time -f '%M %e %U %S' -o "$data/$name.time" "$trn" build "$@" --out "$data/$name.gpkg") > $(printf %q "$data/$name.json")"
  [ -t 2 ] && show=/dev/stderr
  echo "trn build ... --out $data/$name.gpkg" >&2
  if command -v script >/dev/null 2>&1; then
    if ! TERM=${TERM:-xterm} script -qfec "$cmd" "$data/$name.log" > "$show"; then
      echo "error: trn build $name failed; end of $data/$name.log:" >&2
      tr '\r' '\n' < "$data/$name.log" | grep -av 'tiles,' | tail -5 >&2
      exit 1
    fi
  else
    bash -c "$cmd" 2> "$data/$name.log"
  fi
}
load=$(cut -d' ' -f1 /proc/loadavg 2>/dev/null || echo "?")
build big --ortho "$ortho" --dem "$dem" --dem-vertical ellipsoid
build mosaic --ortho "$mwest" --ortho "$meast" --dem "$mdem" --dem-vertical ellipsoid
build mosaic-ref --ortho "$msrc" --dem "$mdem" --dem-vertical ellipsoid

# --- results ----------------------------------------------------------------------
python3 - "$data" "$size" "$msize" "$ortho" "$mwest" "$meast" "$msrc" "$load" <<'PY'
import json, math, os, re, sqlite3, subprocess, sys
data, size, msize, ortho, mwest, meast, msrc, load = sys.argv[1:]

def raster(path):
    info = json.loads(subprocess.run(["gdalinfo", "-json", path], capture_output=True, text=True, check=True).stdout)
    w, h = info["size"]
    crs = re.findall(r'ID\["EPSG",(\d+)\]\]$', info["coordinateSystem"]["wkt"].strip())
    return w, h, len(info["bands"]), "EPSG:" + crs[-1] if crs else "?"

def run(name):
    rss_kb, wall, user, sys_s = open(f"{data}/{name}.time").read().split()[-4:]
    report = json.load(open(f"{data}/{name}.json"))
    log = open(f"{data}/{name}.log", "rb").read().decode("utf-8", "replace")
    bars = re.findall(r"(\d+)/(\d+) tiles", log)
    db = sqlite3.connect(f"{data}/{name}.gpkg")
    sources = json.loads(db.execute("SELECT value FROM trn_metadata WHERE key = 'sources'").fetchone()[0])
    per_src = dict(db.execute("SELECT source, count(*) FROM templates GROUP BY source").fetchall())
    return {"rss_mb": round(int(rss_kb) / 1024), "wall_s": float(wall), "cpu_s": round(float(user) + float(sys_s), 1), "templates": report["templates"],
            "bar": f"drawn {len(bars)} times, last {bars[-1][0]}/{bars[-1][1]} tiles" if bars else "not seen",
            "sources": [(", ".join(os.path.basename(f) for f in s["files"]), per_src.get(s["index"], 0)) for s in sources],
            "db": db, "gpkg_mb": round(os.path.getsize(f"{data}/{name}.gpkg") / 2**20)}

big, mos, ref = run("big"), run("mosaic"), run("mosaic-ref")
w, h, nb, crs = raster(ortho)
ww, wh, _, wcrs = raster(mwest); ew, eh, _, ecrs = raster(meast); sw, sh, _, _ = raster(msrc)
dem = raster(f"{data}/dem-{size}-4269.tif")
mp = lambda *d: round(sum(a * b for a, b in zip(d[::2], d[1::2])) / 1e6, 1)
out = []
out.append(f"# trn build on real-size inputs ({os.cpu_count()} cores; 1-min load average {load} before the builds)\n")
out.append("| input | size | templates | wall s | CPU s | peak RSS MB |")
out.append("|---|---|---|---|---|---|")
out.append(f"| ortho {w}x{h} RGB 1 m {crs} + DEM 1/3\" {dem[3]} ({dem[0]}x{dem[1]}) | {mp(w, h)} MP | "
           f"{big['templates']} | {big['wall_s']} | {big['cpu_s']} | {big['rss_mb']} |")
out.append(f"| mosaic over 2 UTM zones: {wcrs} {ww}x{wh} + {ecrs} {ew}x{eh}, RGBA 1 m + DEM 1/3\" EPSG:4269 | "
           f"{mp(ww, wh, ew, eh)} MP | {mos['templates']} | {mos['wall_s']} | {mos['cpu_s']} | {mos['rss_mb']} |")
out.append(f"| reference: the mosaic's scene as one EPSG:32613 ortho {sw}x{sh} | {mp(sw, sh)} MP | "
           f"{ref['templates']} | {ref['wall_s']} | {ref['cpu_s']} | {ref['rss_mb']} |")
out.append("")
out.append(f"Progress bar (build in a pseudo-terminal): 400 MP build {big['bar']}; mosaic {mos['bar']}.  ")
out.append(f"Database sizes: {big['gpkg_mb']} MB, {mos['gpkg_mb']} MB, {ref['gpkg_mb']} MB.  ")
out.append("Mosaic templates per source: " + "; ".join(f"{f}: {n}" for f, n in mos["sources"]) + ".")
if os.path.exists(f"{data}/gen-times.txt"):
    gen = [l.split() for l in open(f"{data}/gen-times.txt") if l.strip()]
    out.append("Input generation (when last generated): " +
               "; ".join(f"{n} {float(s):.0f} s, {round(int(k) / 1024)} MB" for n, s, k in gen[-4:]) + ".")
out.append("")

# Templates near the zone border (the -108 deg meridian) against control strips.
A, F = 6378137.0, 1 / 298.257223563
E2 = F * (2 - F)
def east_m(lon, lat):  # metres east of -108 deg along the parallel
    p = math.radians(lat)
    return math.radians(lon + 108) * A * math.cos(p) / math.sqrt(1 - E2 * math.sin(p) ** 2)
half, ctrl = 500.0, 2500.0
lat0, lat1 = ref["db"].execute("SELECT min(lat_deg), max(lat_deg) FROM templates WHERE level = 0").fetchone()
lat0, lat1 = lat0 + 0.01, lat1 - 0.01  # ~1 km inside the scene's north and south edges
def strips(db, level):
    border = control = 0
    near_w, near_e = -1e9, 1e9
    for lon, lat in db.execute("SELECT lon_deg, lat_deg FROM templates WHERE level = ? AND lat_deg BETWEEN ? AND ?",
                               (level, lat0, lat1)):
        d = east_m(lon, lat)
        if abs(d) <= half: border += 1
        if abs(abs(d) - ctrl) <= half: control += 1
        if d < 0: near_w = max(near_w, d)
        else: near_e = min(near_e, d)
    return border, control / 2, near_e - near_w
levels = ref["db"].execute("SELECT level, gsd_m * template_px FROM trn_levels ORDER BY level").fetchall()
out.append(f"Templates within {half:.0f} m of the zone border (-108 deg) vs the mean of two equal strips centred "
           f"{ctrl / 1000:g} km west and east of it, between {lat0:.3f} and {lat1:.3f} N; "
           "gap: distance between the templates nearest to the border on either side.\n")
out.append("| level | footprint m | mosaic border | mosaic control | mosaic ratio | mosaic gap m | ref border | ref control | ref ratio | ref gap m |")
out.append("|---|---|---|---|---|---|---|---|---|---|")
for level, foot in levels:
    mb, mc, mg = strips(mos["db"], level)
    rb, rc, rg = strips(ref["db"], level)
    ratio = lambda b, c: f"{b / c:.2f}" if c else "-"
    gap = lambda g: f"{g:.0f}" if g < 1e8 else "-"
    out.append(f"| {level} | {foot:.0f} | {mb} | {mc:g} | {ratio(mb, mc)} | {gap(mg)} | {rb} | {rc:g} | {ratio(rb, rc)} | {gap(rg)} |")
text = "\n".join(out) + "\n"
open(f"{data}/results.md", "w").write(text)
print(text, end="")
PY
