"""Helpers shared by the benchmark scripts' inline Python (bench_nav.sh,
bench_databases.sh): the terrain height under a flight from its landmark
database, and a camera's boresight against the local vertical."""
import math
import sqlite3


def terrain_height(db, lat, lon, reach_deg=0.1):
    """Median ellipsoidal height (m) of the templates within `reach_deg` of
    (lat, lon) in the landmark database `db` (0 when there are none)."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    hs = sorted(r[0] for r in con.execute(
        "SELECT t.h_m FROM templates_rtree AS r CROSS JOIN templates AS t ON t.fid = r.id "
        "WHERE r.max_lon >= ? AND r.min_lon <= ? AND r.max_lat >= ? AND r.min_lat <= ?",
        (lon - reach_deg, lon + reach_deg, lat - reach_deg, lat + reach_deg)))
    return hs[len(hs) // 2] if hs else 0.0


def boresight_cos_from_vertical(q_ecef_cam, lat, lon):
    """Cosine of the angle between the camera's boresight (its z axis, from
    the quaternion w, x, y, z rotating camera to ECEF) and straight down at
    (lat, lon) in degrees (geocentric enough for this use)."""
    w, x, y, z = q_ecef_cam
    bz = (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))
    la, lo = math.radians(lat), math.radians(lon)
    up = (math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la))
    return -sum(a * b for a, b in zip(bz, up)) / math.sqrt(sum(a * a for a in bz))
