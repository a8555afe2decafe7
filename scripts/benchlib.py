"""Helpers shared by the benchmark scripts' inline Python (bench_nav.sh,
bench_databases.sh): the terrain height under a flight from its landmark
database or from a DEM, and a camera's boresight against the local vertical."""
import math
import os
import sqlite3
import subprocess
import tempfile


def terrain_height(db, lat, lon, reach_deg=0.1):
    """Median ellipsoidal height (m) of the templates within `reach_deg` of
    (lat, lon) in the landmark database `db` (0 when there are none)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    hs = sorted(r[0] for r in con.execute(
        "SELECT t.h_m FROM templates_rtree AS r CROSS JOIN templates AS t ON t.fid = r.id "
        "WHERE r.max_lon >= ? AND r.min_lon <= ? AND r.max_lat >= ? AND r.min_lat <= ?",
        (lon - reach_deg, lon + reach_deg, lat - reach_deg, lat + reach_deg)))
    return hs[len(hs) // 2] if hs else 0.0


def dem_terrain_height(dems, lat, lon, vertical="egm96", reach_deg=0.1):
    """Median ellipsoidal height (m) of the DEM cells within `reach_deg` of
    (lat, lon), read from the DEM file(s) with GDAL's command-line tools (any
    CRS: the window is given in WGS84 degrees); `vertical` is the DEM's datum
    as `trn build --dem-vertical` takes it: "egm96" adds the EGM96 undulation
    at (lat, lon) from proj-data's grid, "ellipsoid" adds nothing. Nodata
    cells are skipped; 0 when no cell is valid. Independent of any landmark
    database, so a benchmark's rule that uses it does not move when trn's
    database does."""
    hs = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, dem in enumerate(dems):
            # Warped onto WGS84 degrees over the window (nearest cell; what lies
            # outside the file is NaN), then listed as X Y Z.
            cut = os.path.join(tmp, f"{k}.tif")
            warp = subprocess.run(
                ["gdalwarp", "-q", "-ot", "Float32", "-t_srs", "EPSG:4326", "-te", str(lon - reach_deg),
                 str(lat - reach_deg), str(lon + reach_deg), str(lat + reach_deg), "-dstnodata", "nan", dem, cut],
                capture_output=True, text=True)
            if warp.returncode != 0:
                raise RuntimeError(f"{dem}: gdalwarp failed: {warp.stderr.strip()}")
            xyz = subprocess.run(["gdal_translate", "-q", "-b", "1", "-of", "XYZ", cut, "/vsistdout/"], check=True,
                                 capture_output=True, text=True).stdout
            for line in xyz.splitlines():
                parts = line.split()
                if len(parts) == 3 and math.isfinite(v := float(parts[2])):
                    hs.append(v)
    if not hs:
        return 0.0
    hs.sort()
    h = hs[len(hs) // 2]
    if vertical == "egm96":
        out = subprocess.run(["gdallocationinfo", "-valonly", "-wgs84", "/usr/share/proj/egm96_15.gtx",
                              str(lon), str(lat)], check=True, capture_output=True, text=True)
        h += float(out.stdout.split()[0])
    elif vertical != "ellipsoid":
        raise ValueError(f"dem_terrain_height: vertical datum '{vertical}' (egm96 or ellipsoid)")
    return h


def boresight_cos_from_vertical(q_ecef_cam, lat, lon):
    """Cosine of the angle between the camera's boresight (its z axis, from
    the quaternion w, x, y, z rotating camera to ECEF) and straight down at
    (lat, lon) in degrees (geocentric enough for this use)."""
    w, x, y, z = q_ecef_cam
    bz = (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))
    la, lo = math.radians(lat), math.radians(lon)
    up = (math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la))
    return -sum(a * b for a, b in zip(bz, up)) / math.sqrt(sum(a * a for a in bz))
