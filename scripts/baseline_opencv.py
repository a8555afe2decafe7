#!/usr/bin/env python3
"""OpenCV baseline of the trn navigator: the same terrain relative navigation
pipeline written with stock OpenCV, as the benchmark to beat. Meant to be what
a competent engineer would write in a few days, not a handicapped version: it
gets its own landmark database with a template size chosen for the camera
(scripts/bench_nav.sh builds it with trn build; see the rule there), as many
landmarks per frame as trn navigate, every database level that fits, the
gyro-propagated guess and a wide first search for a poor initial guess.

Usage:
  baseline_opencv.py --db DB --flight DIR --out poses.csv [--rate HZ] [--no-gyro]
      [--max-landmarks 300] [--min-inliers 8] [--max-height-jump 450]
      [--init-sigma-m 1200] [--init-sigma-deg 2] [--ncc mask|interior]

Per image:
  1. Pose guess: position of the last accepted fix, moved by the velocity
     (least-squares slope of the fixes of the last 2 s); attitude carried by
     the gyro (imu.csv, exact quaternion integration per sample, Earth rate
     taken out, camera mounting q_cam_imu from camera.json), or held with
     --no-gyro. Uncertainty: the init sigmas at the start (the defaults,
     1200 m and 2 deg, searched to 2.5 sigma, cover a 3 km / 5 deg seed),
     10 m / 0.05 deg after a fix, plus the velocity's error over the gap
     (20 m/s once the fixes span 1 s, 300 m/s before) and 0.01 deg/s of gyro
     drift. After 8 frames in a row without a fix the search is as wide as at
     the start again, without the velocity.
  2. Footprint: image corners (and edge midpoints, centre) projected onto the
     WGS84 ellipsoid raised to the terrain height (first frame: the median
     template height around the init position; then the mean height of the
     last fix's inliers); corners that see sky or ground steeper than 75 deg
     from the normal walk toward the opposite corner. Also the finest and
     coarsest ground resolution over these points.
  3. Landmarks: templates in the lat/lon box from the templates_rtree R*Tree,
     of every level that may fit; each is kept where its level is the best
     fit for the ground resolution at its own place (range and incidence; the
     image GSD times the pyramid level's scale), or one level finer when it
     still spans >= 14 image pixels there; spread over an 8 x 6 grid of image
     cells, best quality first, --max-landmarks at most (300: trn navigate
     takes 450, which steadies its nadir views on real relief, but 450 moved
     this script's realistic means by -1.7 to 0 m and lost it the synthetic
     oblique flight, 7% of its frames fixed).
  4. Prediction: each template is warped into the image with
     cv2.warpPerspective, by the homography of its four corner ground points
     (terrain plane) projected with cv2.projectPoints (with distortion); a
     validity mask comes with it.
  5. Correlation: cv2.matchTemplate(TM_CCOEFF_NORMED, masked) over a search
     window sized from the pose uncertainty (2.5 sigma), on a 2x-reduced image
     pyramid level when the window is wide (the coarsest level with a radius
     <= 16 px, as long as templates of the coarsest database level span
     >= 12 px there, the reduced image keeps >= 48 rows and >= 20 templates
     are in view), then refined at full resolution (via level 1 from level 3)
     with a 6 px radius (a coarse stage that ends without a pose of
     --min-inliers is tried again one pyramid level finer); minMaxLoc,
     parabola sub-pixel peak, peaks below 0.5
     or not distinct from the second peak are dropped.
     Acquisition (no fix yet, or a search radius above a quarter of the focal
     length): the radius is not capped at fx/4 but at 4 image sizes, the
     footprint box is widened by it, landmarks predicted up to that far outside
     the image are correlated too (1500 at most, and no more than fit 3e8
     correlation positions: bounded cost while lost), and the matches vote on one
     common image shift (the densest cluster, radius 6% of the image diagonal)
     before RANSAC (5000 iterations); the full-resolution refinement from the
     acquired pose checks it.
  6. Pose: cv2.solvePnPRansac(SOLVEPNP_AP3P, 2 px x level scale, confidence
     0.999) on the template centres in a local ECEF frame (offset by the guess
     position), cv2.solvePnPRefineLM on the inliers, re-classification of all
     matches.
  7. Acceptance: at least --min-inliers inliers, and a height within
     --max-height-jump of the guess plus what the time since the last fix
     allows (3 x the velocity error above, and 20 m/s^2 of unmodelled
     acceleration), so a long gap never locks the gate; otherwise the guess
     is reported as `propagated`.

Writes poses.csv in the flight format (t,lat,lon,h,qw,qx,qy,qz,status,inliers,
matches,ms); ms is the wall time from the decoded grey image to the pose, as
trn navigate measures it. Also writes matches.csv next to poses.csv (one row per
correlation match of the final stage, as trn navigate does). Single-threaded
(cv2.setNumThreads(1)). Never reads truth.csv.
"""

import argparse
import csv
import json
import math
import os
import sqlite3
import sys
import time

import cv2
import numpy as np

# ---------------------------------------------------------------- WGS84 ----

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
EARTH_RATE = 7.292115e-5


def geodetic_to_ecef(lat_deg, lon_deg, h):
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl = math.sin(lat), math.cos(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    return np.array([(n + h) * cl * math.cos(lon), (n + h) * cl * math.sin(lon), (n * (1.0 - WGS84_E2) + h) * sl])


def ecef_to_geodetic(p):
    """(lat_deg, lon_deg, h) of an ECEF point (iterative, converges to < 1e-9 m)."""
    x, y, z = float(p[0]), float(p[1]), float(p[2])
    lon = math.atan2(y, x)
    r = math.hypot(x, y)
    lat = math.atan2(z, r * (1.0 - WGS84_E2))
    h = 0.0
    for _ in range(8):
        sl = math.sin(lat)
        n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sl * sl)
        h = r / math.cos(lat) - n if abs(lat) < 1.4 else z / sl - n * (1.0 - WGS84_E2)
        lat_new = math.atan2(z, r * (1.0 - WGS84_E2 * n / (n + h)))
        if abs(lat_new - lat) < 1e-14:
            lat = lat_new
            break
        lat = lat_new
    sl = math.sin(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    h = r / math.cos(lat) - n if abs(lat) < 1.4 else z / sl - n * (1.0 - WGS84_E2)
    return math.degrees(lat), math.degrees(lon), h


def r_ecef_enu(lat_deg, lon_deg):
    """Columns: east, north, up unit vectors in ECEF."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-so, -sl * co, cl * co], [co, -sl * so, cl * so], [0.0, cl, sl]])


def up_ecef(p):
    lat, lon, _ = ecef_to_geodetic(p)
    return r_ecef_enu(lat, lon)[:, 2]


def intersect_ellipsoid(origin, direction, h):
    """First hit of a ray with the ellipsoid raised by h (axes a+h, b+h), or None."""
    s = np.array([1.0 / (WGS84_A + h), 1.0 / (WGS84_A + h), 1.0 / (WGS84_B + h)])
    o, d = origin * s, direction * s
    qa, qb, qc = d @ d, 2.0 * (o @ d), o @ o - 1.0
    disc = qb * qb - 4.0 * qa * qc
    if disc < 0.0 or qa <= 0.0:
        return None
    q = -0.5 * (qb + math.copysign(math.sqrt(disc), qb))
    r0 = q / qa
    r1 = qc / q if q != 0.0 else r0
    t0, t1 = min(r0, r1), max(r0, r1)
    t = t0 if t0 >= 0.0 else (t1 if t1 >= 0.0 else None)
    return None if t is None else origin + t * direction


# ----------------------------------------------------------- quaternions ----
# Hamilton, scalar first, v_a = R(q_a_b) v_b.


def qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


def qconj(q):
    return np.array([q[0], -q[1], -q[2], -q[3]])


def qnorm(q):
    return q / np.linalg.norm(q)


def q_from_rotvec(v):
    a = float(np.linalg.norm(v))
    if a < 1e-12:
        return qnorm(np.array([1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]]))
    s = math.sin(0.5 * a) / a
    return np.array([math.cos(0.5 * a), v[0] * s, v[1] * s, v[2] * s])


def q_to_rot(q):
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rot_to_q(r):
    """Quaternion of a rotation matrix (Shepperd), scalar first, w >= 0."""
    tr = np.trace(r)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = qnorm(np.array(q))
    return q if q[0] >= 0 else -q


def propagate_attitude(q_ecef_imu, t0, t1, imu_t, imu_w):
    """q_ecef_imu at t1 from t0: exact rotation per gyro sample (each the mean
    rate over the interval ending at its time, counted by overlap), with the
    ECEF frame turning under the inertial one at the Earth rate."""
    if t1 <= t0 or len(imu_t) == 0:
        return q_ecef_imu
    body = np.array([1.0, 0.0, 0.0, 0.0])
    k = int(np.searchsorted(imu_t, t0, side="right"))
    n = len(imu_t)
    while k < n:
        end = imu_t[k]
        begin = imu_t[k - 1] if k > 0 else (end - (imu_t[1] - end) if n > 1 else end)
        a, b = max(begin, t0), min(end, t1)
        if b > a:
            body = qmul(body, q_from_rotvec(imu_w[k] * (b - a)))
        if end >= t1:
            break
        k += 1
    earth = q_from_rotvec(np.array([0.0, 0.0, -EARTH_RATE * (t1 - t0)]))
    return qnorm(qmul(qmul(earth, q_ecef_imu), body))


# --------------------------------------------------------------- flight ----


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


class Camera:
    def __init__(self, path):
        c = json.load(open(path))
        self.width, self.height = int(c["width"]), int(c["height"])
        self.fx, self.fy, self.cx, self.cy = float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"])
        d = c.get("distortion") or {}
        self.dist = np.array([d.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")], dtype=np.float64)
        self.q_cam_imu = qnorm(np.array(c.get("q_cam_imu", [1.0, 0.0, 0.0, 0.0]), dtype=np.float64))
        self.K = np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def K_level(self, k):
        """Camera matrix of pyramid level k (INTER_AREA halvings: u_k = (u + 0.5) / 2^k - 0.5)."""
        s = float(1 << k)
        return np.array([[self.fx / s, 0, (self.cx + 0.5) / s - 0.5], [0, self.fy / s, (self.cy + 0.5) / s - 0.5], [0, 0, 1.0]])

    def rays(self, px):
        """Unit camera-frame rays of full-resolution pixels (N x 2)."""
        pts = np.asarray(px, dtype=np.float64).reshape(-1, 1, 2)
        n = cv2.undistortPoints(pts, self.K, self.dist).reshape(-1, 2)
        d = np.hstack([n, np.ones((len(n), 1))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)


# ------------------------------------------------------------ landmarks ----


class LandmarkDb:
    CANDIDATES = (
        "SELECT t.fid, t.gsd_m, t.width_px, t.height_px, t.lat_deg, t.lon_deg, t.h_m, "
        "t.ecef_x_m, t.ecef_y_m, t.ecef_z_m, t.plane_normal_e, t.plane_normal_n, t.plane_normal_u, "
        "t.shi_tomasi, t.second_peak_ncc "
        "FROM templates_rtree AS r CROSS JOIN templates AS t ON t.fid = r.id "
        "WHERE r.max_lon >= ? AND r.min_lon <= ? AND r.max_lat >= ? AND r.min_lat <= ? "
        "AND r.max_level >= ? AND r.min_level <= ?"
    )

    def __init__(self, path):
        self.conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        self.levels = [(int(l), float(g)) for l, g in self.conn.execute("SELECT level, gsd_m FROM trn_levels ORDER BY level")]
        if not self.levels:
            raise SystemExit(f"{path}: the landmark database has no templates")

    def terrain_height_near(self, lat, lon, h_cam, radius_deg=0.1):
        """Median template height around (lat, lon): the first footprint's terrain height."""
        hs = sorted(h for (h,) in self.conn.execute(
            "SELECT t.h_m FROM templates_rtree AS r CROSS JOIN templates AS t ON t.fid = r.id "
            "WHERE r.max_lon >= ? AND r.min_lon <= ? AND r.max_lat >= ? AND r.min_lat <= ?",
            (lon - radius_deg, lon + radius_deg, lat - radius_deg, lat + radius_deg)))
        h = hs[len(hs) // 2] if hs else 0.0
        return min(h, h_cam - 100.0)

    def level_for(self, gsd):
        return min(self.levels, key=lambda lg: abs(math.log(lg[1] / gsd)))[0]

    def level_index(self, gsd):
        """Database levels best fitting an array of ground resolutions."""
        g = np.array([lg[1] for lg in self.levels])
        return np.abs(np.log(np.asarray(gsd, dtype=np.float64)[:, None] / g[None, :])).argmin(axis=1)

    def template_size(self):
        row = self.conn.execute("SELECT width_px FROM templates LIMIT 1").fetchone()
        return int(row[0]) if row else 32

    def candidates(self, box, lo, hi):
        min_lon, min_lat, max_lon, max_lat = box
        return self.conn.execute(self.CANDIDATES, (min_lon, max_lon, min_lat, max_lat, lo, hi)).fetchall()

    def pixels(self, fids):
        q = "SELECT fid, pixels FROM templates WHERE fid IN (%s)" % ",".join("?" * len(fids))
        return dict(self.conn.execute(q, list(fids)).fetchall())


# ----------------------------------------------------------- navigation ----

PYRAMID_LEVELS = 4
MAX_RADIUS_PX = 16       # largest search radius at one pyramid level (when the templates allow)
MIN_COARSE_LANDMARKS = 20  # coarse levels: at least this many templates in view
MIN_COARSE_TEMPLATE_PX = 12  # coarse levels: templates of the coarsest database level span at least this
MIN_COARSE_IMAGE_PX = 48   # coarse levels: the reduced image keeps at least this many rows
FINE_RADIUS_PX = 6       # search radius of each refining stage after a coarse one (at least)
MIN_FINER_TEMPLATE_PX = 14  # a template one level finer than the local fit is used when it spans this
ALPHA_MAX_DEG = 75.0
GRID = (8, 6)
MAX_PATCH = 63
MIN_PEAK = 0.5
MAX_SECOND_RATIO = 0.92  # second peak (outside the main lobe) / peak
RANSAC_PX = 2.0
FIX_SIGMA_M, FIX_SIGMA_DEG = 10.0, 0.05
VELOCITY_SIGMA_M_S = 20.0  # error of the velocity from fixes spanning >= 1 s (1 sigma)
VELOCITY_MIN_SPAN_S = 1.0  # fixes spanning less: velocity error UNKNOWN_SPEED_M_S
UNKNOWN_SPEED_M_S = 300.0  # velocity error before a velocity is known (fixes spanning < 1 s)
MAX_ACCEL_M_S2 = 20.0      # height-jump gate: unmodelled acceleration over the gap
GYRO_DRIFT_DEG_S = 0.01
VELOCITY_WINDOW_S = 2.0    # velocity: least-squares slope of the fixes of the last 2 s
LOST_FRAMES = 8            # this many frames in a row without a fix: search as at the start
# Acquisition (no fix yet, or an uncertainty wider than a quarter of the focal
# length): the whole uncertainty is searched, landmarks predicted outside the
# image by up to the search radius are correlated too, and the matches vote on
# one common image shift before RANSAC.
ACQ_MAX_LANDMARKS = 1500
ACQ_MAX_MARGIN = 4.0       # search radius at most this many image sizes
ACQ_VOTE_RADIUS = 0.06     # shift cluster radius, share of the image diagonal
ACQ_RANSAC_ITERATIONS = 5000
ACQ_CLUSTERS = 3           # shift clusters tried, each refined; the most inliers wins
# Bounded cost while acquiring: landmarks x search-window area at most this
# many correlation positions (about 1-2 s of one core), at least
# ACQ_MIN_LANDMARKS landmarks.
ACQ_WORK_POSITIONS = 3e8
ACQ_MIN_LANDMARKS = 40


class Pose:
    """Camera pose: ECEF position and q_ecef_cam."""

    def __init__(self, pos, q):
        self.pos = np.asarray(pos, dtype=np.float64)
        self.q = qnorm(np.asarray(q, dtype=np.float64))
        self.R = q_to_rot(self.q)  # ECEF <- camera

    def to_cam(self, pts_ecef):
        return (np.asarray(pts_ecef) - self.pos) @ self.R  # rows: R^T (p - c)


class Baseline:
    def __init__(self, db, cam, imu_t, imu_w, init, args):
        self.db, self.cam, self.use_gyro, self.ncc_mode = db, cam, not args.no_gyro, args.ncc
        self.max_landmarks, self.min_inliers, self.max_height_jump = args.max_landmarks, args.min_inliers, args.max_height_jump
        self.imu_t, self.imu_w = imu_t, imu_w
        self.t = float(init["t"])
        self.pose = Pose(geodetic_to_ecef(init["lat"], init["lon"], init["h"]), init["q_ecef_cam"])
        self.sigma_m = args.init_sigma_m
        self.sigma_rad = math.radians(args.init_sigma_deg)
        self.last_fix = None  # (t, Pose)
        self.velocity = np.zeros(3)
        self.have_velocity = False
        self.fixes = []  # (t, ECEF position) of the recent fixes
        self.velocity_sigma = UNKNOWN_SPEED_M_S
        self.misses = 0  # frames in a row without a fix
        self.init_sigma = (args.init_sigma_m, math.radians(args.init_sigma_deg))
        self.terrain_h = db.terrain_height_near(float(init["lat"]), float(init["lon"]), float(init["h"]))
        self.q_imu_cam = qconj(cam.q_cam_imu)
        self.f = min(cam.fx, cam.fy)
        self.tmpl_px = db.template_size()
        self.level_gsd = np.array([g for _, g in db.levels])

    # -- pose guess --
    def guess(self, t):
        dt = t - self.t
        q = self.pose.q
        if self.use_gyro:
            q_cam_imu = self.cam.q_cam_imu
            q_ecef_imu = qmul(q, q_cam_imu)
            q = qmul(propagate_attitude(q_ecef_imu, self.t, t, self.imu_t, self.imu_w), qconj(q_cam_imu))
        g = Pose(self.pose.pos + self.velocity * dt, q)
        g.t = t
        return g

    def carry(self, t, g):
        dt = max(t - self.t, 0.0)
        self.sigma_m += self.velocity_sigma * dt
        if self.use_gyro:
            self.sigma_rad += math.radians(GYRO_DRIFT_DEG_S) * dt
        else:
            self.sigma_rad += math.radians(10.0) * max(dt, 0.5)
        self.pose, self.t = g, t

    # -- footprint --
    def ground(self, pose, px, h):
        d = pose.R @ self.cam.rays([px])[0]
        hit = intersect_ellipsoid(pose.pos, d, h)
        if hit is None:
            return None
        up = up_ecef(hit)
        cos_inc = -d @ up
        if cos_inc <= 0:
            return None
        return hit, math.degrees(math.acos(min(cos_inc, 1.0))), float(np.linalg.norm(hit - pose.pos))

    def footprint(self, pose, margin_m=0.0):
        """Lat/lon box of the image on the terrain (widened by margin_m), the
        ground resolution at the centre, its range and the finest and coarsest
        ground resolution over the corners, edge midpoints and centre."""
        h = self.terrain_h
        if ecef_to_geodetic(pose.pos)[2] <= h:
            return None
        w, hh = self.cam.width, self.cam.height
        corners = [(-0.5, -0.5), (w - 0.5, -0.5), (w - 0.5, hh - 0.5), (-0.5, hh - 0.5)]
        walked, pts = [], []
        for i in range(4):
            a, b = np.array(corners[i]), np.array(corners[(i + 2) % 4])
            length = float(np.linalg.norm(b - a))
            step = (b - a) / length
            k, hit = 0.0, None
            while k <= length:
                p = a + step * k
                g = self.ground(pose, p, h)
                if g is not None and g[1] <= ALPHA_MAX_DEG:
                    hit = (p, g)
                    break
                k += 10.0
            if hit is None:
                return None
            walked.append(hit[0])
            pts.append(hit[1])
        for i in range(4):
            mid = 0.5 * (walked[i] + walked[(i + 1) % 4])
            g = self.ground(pose, mid, h)
            if g is not None and g[1] <= ALPHA_MAX_DEG:
                pts.append(g)
        centre = self.ground(pose, np.array([self.cam.cx, self.cam.cy]), h)
        if centre is None or centre[1] > ALPHA_MAX_DEG:
            centre = self.ground(pose, 0.25 * sum(walked), h)
        if centre is None:
            return None
        pts.append(centre)

        def gsd_of(g):
            return g[2] / self.f / math.sqrt(max(math.cos(math.radians(g[1])), 0.2))

        gsds = [gsd_of(g) for g in pts]
        lls = [ecef_to_geodetic(g[0]) for g in pts]
        lats, lons = [x[0] for x in lls], [x[1] for x in lls]
        dlat = margin_m / 111320.0
        dlon = margin_m / (111320.0 * max(math.cos(math.radians(np.mean(lats))), 0.05))
        box = (min(lons) - dlon, min(lats) - dlat, max(lons) + dlon, max(lats) + dlat)
        return box, gsd_of(centre), centre[2], (min(gsds), max(gsds))

    # -- one frame --
    def process(self, t, img):
        start = time.perf_counter()
        g = self.guess(t)
        sol, n_matches = self.solve(g, img)
        status, inliers, records = "propagated", 0, []
        if sol is not None:
            pose, inliers, h_mean, records = sol
            ok = inliers >= self.min_inliers
            if ok and self.last_fix is not None:
                # Height gate against the guess (last fix moved by the velocity),
                # widened with the time since that fix so a long gap never locks out.
                dt = max(t - self.last_fix[0], 0.0)
                speed = 3.0 * self.velocity_sigma if self.have_velocity else UNKNOWN_SPEED_M_S
                tol = self.max_height_jump + speed * dt + 0.5 * MAX_ACCEL_M_S2 * dt * dt
                ok = abs(ecef_to_geodetic(g.pos)[2] - ecef_to_geodetic(pose.pos)[2]) <= tol
            if ok:
                # Velocity: least-squares slope over the recent fixes (the
                # difference of two fixes a frame apart is mostly their noise).
                self.fixes = [(tf, pf) for tf, pf in self.fixes if t - tf <= VELOCITY_WINDOW_S] + [(t, pose.pos)]
                if len(self.fixes) >= 2:
                    ts = np.array([tf for tf, _ in self.fixes])
                    ps = np.array([pf for _, pf in self.fixes])
                    dt_ = ts - ts.mean()
                    if float(dt_ @ dt_) > 1e-9:
                        self.velocity = dt_ @ (ps - ps.mean(axis=0)) / float(dt_ @ dt_)
                        self.have_velocity = True
                span = self.fixes[-1][0] - self.fixes[0][0]
                self.velocity_sigma = VELOCITY_SIGMA_M_S if span >= VELOCITY_MIN_SPAN_S else UNKNOWN_SPEED_M_S
                self.last_fix = (t, pose)
                self.misses = 0
                self.pose, self.t = pose, t
                self.sigma_m, self.sigma_rad = FIX_SIGMA_M, math.radians(FIX_SIGMA_DEG)
                self.terrain_h = h_mean
                status = "fix"
            else:
                self.carry(t, g)
        else:
            self.carry(t, g)
        if status != "fix":
            self.misses += 1
            if self.misses % LOST_FRAMES == 0:
                # Lost: search as wide as at the start, without the velocity.
                self.sigma_m = max(self.sigma_m, self.init_sigma[0])
                self.sigma_rad = max(self.sigma_rad, self.init_sigma[1])
                self.velocity, self.have_velocity, self.fixes = np.zeros(3), False, []
                self.velocity_sigma = UNKNOWN_SPEED_M_S
        ms = (time.perf_counter() - start) * 1e3
        return self.pose, status, inliers, n_matches, ms, sorted(records)

    def solve(self, guess, img):
        fp = self.footprint(guess)
        if fp is None:
            return None, 0
        _, gsd, rng, _ = fp
        w, h = self.cam.width, self.cam.height
        # Uncertainty of the guess: that of the last estimate, the velocity's
        # error over the gap, the gyro's drift (--no-gyro: the attitude's
        # uncertainty grows only over frames without a fix, in carry()).
        gap = max(guess.t - self.t, 0.0)
        sigma_m = self.sigma_m + self.velocity_sigma * gap
        sigma_rad = self.sigma_rad + (math.radians(GYRO_DRIFT_DEG_S) * gap if self.use_gyro else 0.0)
        radius_full = 2.5 * self.f * (sigma_rad + sigma_m / rng) + 3.0
        # Acquisition: no fix yet, or an uncertainty too wide for tracking.
        acq = self.last_fix is None or self.misses >= LOST_FRAMES or radius_full > 0.25 * self.f
        if acq:
            radius_full = min(radius_full, ACQ_MAX_MARGIN * max(w, h))
            margin_px = radius_full
            fp = self.footprint(guess, margin_px * gsd)
            if fp is None:
                return None, 0
        else:
            margin_px = 0.0
        box, gsd, rng, gsd_range = fp
        cap = ACQ_MAX_LANDMARKS if acq else self.max_landmarks
        # Coarsest pyramid level whose search radius fits, as long as the
        # templates of the coarsest database level still span
        # MIN_COARSE_TEMPLATE_PX there and the reduced image keeps its size.
        coarsest_db_gsd = self.db.levels[-1][1]
        k = 0
        while (k + 1 < PYRAMID_LEVELS and radius_full / (1 << k) > MAX_RADIUS_PX
               and self.tmpl_px * coarsest_db_gsd / (gsd * (1 << (k + 1))) >= MIN_COARSE_TEMPLATE_PX
               and min(w, h) / (1 << (k + 1)) >= MIN_COARSE_IMAGE_PX):
            k += 1
        # ... and with enough templates in view at that level.
        while k > 0 and len(self.select(guess, self.level_candidates(box, gsd_range, k), k, margin_px, cap)) < MIN_COARSE_LANDMARKS:
            k -= 1
        pyr = [img]
        for _ in range(k):
            p = pyr[-1]
            pyr.append(cv2.resize(p[: p.shape[0] // 2 * 2, : p.shape[1] // 2 * 2], (p.shape[1] // 2, p.shape[0] // 2), interpolation=cv2.INTER_AREA))
        # Coarse stage, then refining stages at full resolution (and level 1 in
        # between when starting from level 3); an acquisition is always refined
        # (the refinement re-finds the landmarks from the acquired pose: a check).
        # A coarse stage that finds no pose is tried again one level finer.
        best, best_n = None, 0
        for kk in range(k, -1, -1):
            radius_k = int(math.ceil(radius_full / (1 << kk)))
            cap_k = cap
            if acq:
                cap_k = int(min(cap, max(ACQ_MIN_LANDMARKS, ACQ_WORK_POSITIONS / (2 * radius_k + 1) ** 2)))
            stages = [(kk, radius_k, acq, margin_px, cap_k)]
            if kk >= 3:
                stages.append((1, FINE_RADIUS_PX, False, 0.0, self.max_landmarks))
            if kk > 0 or acq:
                stages.append((0, max(FINE_RADIUS_PX, (1 << min(kk, 2)) + 2), False, 0.0, self.max_landmarks))
            first, rest = stages[0], stages[1:]
            res, n = self.stage(pyr[first[0]], first[0], guess, box, gsd_range, *first[1:])
            best_n = max(best_n, n)
            for r in (res if first[2] else [res]) if res is not None else []:
                out = r
                for level, radius, vote, margin, cap_l in rest:
                    fp = self.footprint(out[0])
                    if fp is None:
                        out = None
                        break
                    fp_box, _, _, fp_range = fp
                    out, n = self.stage(pyr[level], level, out[0], fp_box, fp_range, radius, vote, margin, cap_l)
                    if out is None:
                        break
                if out is not None and (best is None or out[1] > best[1]):
                    best, best_n = out, n
            if best is not None and best[1] >= self.min_inliers:
                break
        return best, best_n

    def level_candidates(self, box, gsd_range, level):
        """Candidates of every database level that may fit the ground
        resolutions of the view at pyramid level `level` (one finer included)."""
        s = float(1 << level)
        lo = max(self.db.level_for(gsd_range[0] * s) - 1, self.db.levels[0][0])
        hi = self.db.level_for(gsd_range[1] * s)
        return self.db.candidates(box, lo, hi)

    def select(self, pose, cands, level=0, margin_px=0.0, cap=None):
        """Candidates in view (the image widened by margin_px) whose level fits
        the local ground resolution (or one finer, when its templates still
        span MIN_FINER_TEMPLATE_PX), spread over image cells, best quality first."""
        if not cands:
            return []
        cap = cap or self.max_landmarks
        s = float(1 << level)
        arr = np.array([c[7:10] for c in cands])
        pc = pose.to_cam(arr)
        ok = pc[:, 2] > 0
        uv = np.full((len(cands), 2), -1e9)
        if ok.any():
            uv[ok] = cv2.projectPoints(pc[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.cam.K, self.cam.dist)[0].reshape(-1, 2)
        # Local ground resolution at each landmark (range, incidence from the local up).
        lat = np.radians(np.array([c[4] for c in cands]))
        lon = np.radians(np.array([c[5] for c in cands]))
        up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=1)
        view = pose.pos - arr
        rng = np.linalg.norm(view, axis=1)
        cos_inc = np.clip(np.einsum("ij,ij->i", view, up) / np.maximum(rng, 1e-9), 0.2, 1.0)
        gsd_l = rng / self.f / np.sqrt(cos_inc) * s
        best = self.level_gsd[self.db.level_index(gsd_l)]
        tg = np.array([c[1] for c in cands])
        tw = np.array([c[2] for c in cands])
        fits = np.isclose(tg, best, rtol=1e-3) | (np.isclose(tg, 0.5 * best, rtol=1e-3) & (tw * tg / gsd_l >= MIN_FINER_TEMPLATE_PX))
        w, h = self.cam.width, self.cam.height
        m = float(margin_px)
        inside = ok & fits & (uv[:, 0] >= -m) & (uv[:, 0] < w + m) & (uv[:, 1] >= -m) & (uv[:, 1] < h + m)
        gx, gy = GRID
        cells = [[] for _ in range(gx * gy)]
        for i in np.flatnonzero(inside):
            c = cands[i]
            u, v = uv[i]
            score = math.sqrt(max(c[13], 0.0)) * max(1.0 - c[14], 0.01)
            cx = min(max(int((u + m) / (w + 2 * m) * gx), 0), gx - 1)
            cy = min(max(int((v + m) / (h + 2 * m) * gy), 0), gy - 1)
            cells[cy * gx + cx].append((score, i))
        for c in cells:
            c.sort(key=lambda x: -x[0])
        out, rnd = [], 0
        while len(out) < cap:
            anyc = False
            for c in cells:
                if rnd < len(c):
                    out.append(c[rnd][1])
                    anyc = True
                    if len(out) == cap:
                        break
            if not anyc:
                break
            rnd += 1
        return [cands[i] for i in out]

    def warp(self, c, pix, pose, K_l, level):
        """Template warped into level-`level` pixels: (patch, mask, origin xy, centre px at level) or None."""
        fid, gsd, tw, th, lat, lon, h_m, ex, ey, ez, ne, nn, nu = c[:13]
        if nu <= 0.1:
            return None
        centre = np.array([ex, ey, ez])
        R = r_ecef_enu(lat, lon)
        view = pose.pos - centre
        view /= np.linalg.norm(view)
        if view @ (R @ np.array([ne, nn, nu])) <= math.cos(math.radians(ALPHA_MAX_DEG)):
            return None
        # Four footprint corners and the centre on the terrain plane.
        src = np.array([[-0.5, -0.5], [tw - 0.5, -0.5], [tw - 0.5, th - 0.5], [-0.5, th - 0.5], [(tw - 1) / 2, (th - 1) / 2]])
        e = (src[:, 0] - (tw - 1) / 2.0) * gsd
        n = ((th - 1) / 2.0 - src[:, 1]) * gsd
        u = -(ne * e + nn * n) / nu
        pts = centre + np.stack([e, n, u], axis=1) @ R.T
        pc = pose.to_cam(pts)
        if (pc[:, 2] <= 0).any():
            return None
        dst = cv2.projectPoints(pc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_l, self.cam.dist)[0].reshape(-1, 2)
        cpx = dst[4]
        lo, hi = dst[:4].min(axis=0), dst[:4].max(axis=0)
        side = int(min(max(math.ceil(max(hi - lo)), 9), MAX_PATCH)) | 1
        half = side // 2
        x0, y0 = int(round(cpx[0])) - half, int(round(cpx[1])) - half
        tmpl = np.frombuffer(pix, dtype=np.uint8).reshape(th, tw)
        s4 = src[:4].copy()
        # Shrinking a lot: box-filter the template first (warpPerspective would alias).
        d1, d2 = dst[2] - dst[0], dst[3] - dst[1]
        quad_area = 0.5 * abs(d1[0] * d2[1] - d1[1] * d2[0])
        scale = math.sqrt(quad_area / (tw * th))
        if scale < 0.6:
            f = max(scale, 1.0 / 8.0)
            nw, nh = max(int(round(tw * f)), 2), max(int(round(th * f)), 2)
            tmpl = cv2.resize(tmpl, (nw, nh), interpolation=cv2.INTER_AREA)
            s4[:, 0] = (s4[:, 0] + 0.5) * nw / tw - 0.5
            s4[:, 1] = (s4[:, 1] + 0.5) * nh / th - 0.5
        H = cv2.getPerspectiveTransform(s4.astype(np.float32), (dst[:4] - [x0, y0]).astype(np.float32))
        patch = cv2.warpPerspective(tmpl, H, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        ones = np.full(tmpl.shape, 255, np.uint8)
        m = cv2.warpPerspective(ones, H, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mask = (m >= 250).astype(np.uint8)
        if mask.sum() < side * side / 3:
            return None
        return patch, mask, (x0, y0), cpx

    def correlate(self, img, patch, mask, origin, radius):
        """Shift (dx, dy) of the patch from its predicted place, or None."""
        ph, pw = patch.shape
        x0, y0 = origin
        H, W = img.shape
        wx0, wy0 = max(x0 - radius, 0), max(y0 - radius, 0)
        wx1, wy1 = min(x0 + pw + radius, W), min(y0 + ph + radius, H)
        if wx1 - wx0 < pw + 2 or wy1 - wy0 < ph + 2:
            return None
        win = img[wy0:wy1, wx0:wx1]
        interior = False
        if self.ncc_mode == "interior":
            # Largest centred square of valid pixels, correlated without a mask
            # (the masked correlation where that square is small).
            c = ph // 2
            lo, hi = 0, c
            while lo < hi:
                mid = (lo + hi + 1) // 2
                if mask[c - mid:c + mid + 1, c - mid:c + mid + 1].all():
                    lo = mid
                else:
                    hi = mid - 1
            interior = 2 * lo + 1 >= 15
        if interior:
            cy0, cy1, cx0, cx1 = c - lo, c + lo + 1, c - lo, c + lo + 1
            t = patch[cy0:cy1, cx0:cx1]
            if float(t.std()) < 2.0:
                return None
            r = cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED)
        else:
            # Template cropped to its valid bounding box (less work), masked.
            ys, xs = np.nonzero(mask)
            cy0, cy1, cx0, cx1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
            t = patch[cy0:cy1, cx0:cx1]
            m = mask[cy0:cy1, cx0:cx1]
            if float(t[m > 0].std()) < 2.0:
                return None
            if m.all():
                r = cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED)
            else:
                r = cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED, mask=m)
        r[~np.isfinite(r)] = -1.0
        _, peak, _, (px, py) = cv2.minMaxLoc(r)
        if peak < MIN_PEAK:
            return None
        rh, rw = r.shape
        if px == 0 or py == 0 or px == rw - 1 or py == rh - 1:
            return None  # on the window border: the true peak may be outside
        # Second peak: best score outside a disk of radius 3 around the peak.
        r2 = r.copy()
        cv2.circle(r2, (px, py), 3, -1.0, -1)
        second = r2.max()
        if second > MAX_SECOND_RATIO * peak:
            return None
        def parab(a, b, c):
            d = a - 2 * b + c
            return 0.0 if d >= 0 else 0.5 * (a - c) / d
        sx = parab(r[py, px - 1], r[py, px], r[py, px + 1])
        sy = parab(r[py - 1, px], r[py, px], r[py + 1, px])
        # Patch top-left found at window (px - cx0 + sx, ...).
        return (wx0 + px + sx - cx0 - x0, wy0 + py + sy - cy0 - y0), peak

    def stage(self, img, level, pose, box, gsd_range, radius, vote=False, margin_px=0.0, cap=None):
        s = float(1 << level)
        chosen = self.select(pose, self.level_candidates(box, gsd_range, level), level, margin_px, cap)
        if not chosen:
            return None, 0
        pix = self.db.pixels([c[0] for c in chosen])
        K_l = self.cam.K_level(level)
        obs, pred, pts, ids = [], [], [], []
        for c in chosen:
            w = self.warp(c, pix[c[0]], pose, K_l, level)
            if w is None:
                continue
            patch, mask, origin, cpx = w
            m = self.correlate(img, patch, mask, origin, radius)
            if m is None:
                continue
            (dx, dy), _ = m
            u_l, v_l = cpx[0] + dx, cpx[1] + dy
            obs.append(((u_l + 0.5) * s - 0.5, (v_l + 0.5) * s - 0.5))
            pred.append(((cpx[0] + 0.5) * s - 0.5, (cpx[1] + 0.5) * s - 0.5))
            pts.append(c[7:10])
            ids.append(c[0])
        n = len(obs)
        if n < 4:
            return None, n
        obs = np.array(obs, dtype=np.float64)
        origin = np.round(pose.pos)
        P = np.array(pts, dtype=np.float64) - origin
        thr = RANSAC_PX * s
        if not vote:
            return self.pnp(obs, P, origin, pts, ids, thr, np.arange(n), 1000), n
        # Acquisition: most matches of a wide search are wrong; the right ones
        # share about one image shift (the pose error). The densest clusters
        # of shifts (ACQ_CLUSTERS, greedily) each give a pose for the caller
        # to refine; the refinement that finds the most inliers wins.
        d = obs - np.array(pred)
        rho = max(ACQ_VOTE_RADIUS * math.hypot(self.cam.width, self.cam.height), 4.0 * s)
        near = np.linalg.norm(d[:, None, :] - d[None, :, :], axis=2) <= rho
        free = np.ones(n, bool)
        out = []
        for _ in range(ACQ_CLUSTERS):
            cnt = (near & free[None, :]).sum(axis=1) * free
            if cnt.max() < 4:
                break
            centre = np.median(d[near[int(cnt.argmax())] & free], axis=0)
            sub = np.flatnonzero((np.linalg.norm(d - centre, axis=1) <= rho) & free)
            free[sub] = False
            r = self.pnp(obs, P, origin, pts, ids, thr, sub, ACQ_RANSAC_ITERATIONS)
            if r is not None:
                out.append(r)
        return out, n

    def pnp(self, obs, P, origin, pts, ids, thr, sub, iterations):
        """RANSAC P3P on the matches `sub`, LM refinement, re-classification of all matches."""
        n = len(obs)
        if len(sub) < 4:
            return None
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            P[sub].reshape(-1, 1, 3), obs[sub].reshape(-1, 1, 2), self.cam.K, self.cam.dist,
            iterationsCount=iterations, reprojectionError=thr, confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        if not ok or inl is None or len(inl) < 4:
            return None
        inl = sub[inl.ravel()]
        rvec, tvec = cv2.solvePnPRefineLM(P[inl].reshape(-1, 1, 3), obs[inl].reshape(-1, 1, 2), self.cam.K, self.cam.dist, rvec, tvec)
        # Re-classify all matches with the refined pose; refine once more on the new set.
        for it in range(2):
            proj = cv2.projectPoints(P.reshape(-1, 1, 3), rvec, tvec, self.cam.K, self.cam.dist)[0].reshape(-1, 2)
            res = np.linalg.norm(proj - obs, axis=1)
            zc = (cv2.Rodrigues(rvec)[0] @ P.T + tvec).T[:, 2]
            inlier = (res <= thr) & (zc > 0)
            if it == 0 and inlier.sum() >= 4 and not np.array_equal(np.flatnonzero(inlier), inl):
                rvec, tvec = cv2.solvePnPRefineLM(P[inlier].reshape(-1, 1, 3), obs[inlier].reshape(-1, 1, 2), self.cam.K, self.cam.dist, rvec, tvec)
            else:
                break
        n_in = int(inlier.sum())
        if n_in < 4:
            return None
        R = cv2.Rodrigues(rvec)[0]  # camera <- local world
        pos = -R.T @ tvec.ravel() + origin
        new = Pose(pos, rot_to_q(R.T))
        h_mean = float(np.mean([ecef_to_geodetic(p)[2] for p in np.array(pts)[inlier]]))
        records = [(ids[i], obs[i, 0], obs[i, 1], proj[i, 0], proj[i, 1], min(res[i], 1e6), int(inlier[i])) for i in range(n)]
        return new, n_in, h_mean, records


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--db", required=True)
    ap.add_argument("--flight", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--rate", type=float, default=None, help="images per second taken from the flight (default: all)")
    ap.add_argument("--no-gyro", action="store_true", help="do not carry the attitude with the gyro")
    ap.add_argument("--ncc", choices=("mask", "interior"), default="mask",
                    help="correlate the whole warped template with a validity mask (default), or its largest valid centred square without one (faster)")
    ap.add_argument("--max-landmarks", type=int, default=300, help="landmarks correlated per image when tracking (trn navigate takes 450; see the docstring)")
    ap.add_argument("--min-inliers", type=int, default=8, help="fewer RANSAC inliers reject the fix")
    ap.add_argument("--max-height-jump", type=float, default=450.0,
                    help="height gate (m) against the guess, widened with the time since the last fix")
    ap.add_argument("--init-sigma-m", type=float, default=1200.0,
                    help="position uncertainty of init.json (m, 1 sigma; searched to 2.5 sigma)")
    ap.add_argument("--init-sigma-deg", type=float, default=2.0,
                    help="attitude uncertainty of init.json (deg, 1 sigma; searched to 2.5 sigma)")
    a = ap.parse_args()
    cv2.setNumThreads(1)
    cv2.setUseOptimized(True)

    cam = Camera(os.path.join(a.flight, "camera.json"))
    init = json.load(open(os.path.join(a.flight, "init.json")))
    frames = read_csv(os.path.join(a.flight, "frames.csv"))
    imu_rows = read_csv(os.path.join(a.flight, "imu.csv"))
    imu_t = np.array([float(r["t"]) for r in imu_rows])
    imu_w = np.array([[float(r["wx"]), float(r["wy"]), float(r["wz"])] for r in imu_rows]).reshape(-1, 3)
    db = LandmarkDb(a.db)
    nav = Baseline(db, cam, imu_t, imu_w, init, a)

    lines, mlines = [], []
    next_due = -math.inf
    for fr in frames:
        t = float(fr["t"])
        if t + 1e-6 < next_due:
            continue
        img = cv2.imread(os.path.join(a.flight, fr["image"]), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SystemExit(f"{fr['image']}: cannot read")
        if img.shape != (cam.height, cam.width):
            raise SystemExit(f"{fr['image']}: {img.shape[1]}x{img.shape[0]} pixels, camera.json says {cam.width}x{cam.height}")
        pose, status, inl, nm, ms, recs = nav.process(t, img)
        mlines.extend(f"{t:.6f},{r[0]},{r[1]:.3f},{r[2]:.3f},{r[3]:.3f},{r[4]:.3f},{r[5]:.4f},{r[6]}" for r in recs)
        next_due = t + 1.0 / a.rate if (status == "fix" and a.rate) else -math.inf
        lat, lon, h = ecef_to_geodetic(pose.pos)
        q = pose.q if pose.q[0] >= 0 else -pose.q
        lines.append(f"{t:.6f},{lat:.10f},{lon:.10f},{h:.4f},{q[0]:.12f},{q[1]:.12f},{q[2]:.12f},{q[3]:.12f},{status},{inl},{nm},{ms:.2f}")
    matches_path = os.path.join(os.path.dirname(os.path.abspath(a.out)), "matches.csv")
    for path, header, rows in ((a.out, "t,lat,lon,h,qw,qx,qy,qz,status,inliers,matches,ms", lines),
                               (matches_path, "t,landmark,u,v,pred_u,pred_v,residual_px,inlier", mlines)):
        tmp = path + ".part"
        with open(tmp, "w") as f:
            f.write(header + "\n")
            f.write("\n".join(rows) + ("\n" if rows else ""))
        os.replace(tmp, path)
    ms = sorted(float(l.rsplit(",", 1)[1]) for l in lines)
    fixes = sum(1 for l in lines if ",fix," in l)
    print(json.dumps({"frames": len(frames), "processed": len(lines), "fixes": fixes, "median_ms": ms[len(ms) // 2] if ms else 0.0}))


if __name__ == "__main__":
    main()
