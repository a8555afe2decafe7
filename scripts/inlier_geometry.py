#!/usr/bin/env python3
"""What a navigated flight's inlier matches say, with the true camera.

Usage: inlier_geometry.py FLIGHT_DIR RUN_DIR [DATABASE]
  FLIGHT_DIR  a simulated flight (camera.json, scenario.json, truth.csv)
  RUN_DIR     a `trn navigate` run on it (poses.csv, matches.csv beside it)
  DATABASE    the database it navigated on (a GeoPackage of `trn build`):
              adds the inliers' offsets per landmark, by shading share

The true camera is camera.json with the scenario's `camera_error` applied (as
the simulator rendered the images). Prints one JSON object:
  offset_u_px, offset_v_px, rms_px   the inliers' matched pixel minus the true
                                     pose's projection of their landmark, mean
                                     and rms over every inlier of every fix;
  pnp_mean_m                         OpenCV's PnP (SQPNP, then Levenberg-
                                     Marquardt) on each fix's inliers alone,
                                     its mean 3D error: what the matches of one
                                     frame tell without any prior;
  pnp_early_m, pnp_late_m            the same over the first and second half
                                     of the fixes;
  by_shading_share                   (with DATABASE) per bin of the landmarks'
                                     shading share (how much of a template's
                                     contrast relief shading could make, as
                                     `trn build` stores it): the landmarks, the
                                     inliers, `systematic_px` (the rms over
                                     landmarks of each one's mean offset,
                                     weighted by its inliers: the part that
                                     repeats in every frame the landmark is
                                     seen in) and `rms_px` (over the inliers).
"""
import csv
import json
import math
import os
import sqlite3
import sys

import cv2
import numpy as np

# The baseline's WGS84 and quaternion helpers (this folder is on sys.path).
from baseline_opencv import geodetic_to_ecef, q_to_rot


def ecef(row):
    return geodetic_to_ecef(float(row["lat"]), float(row["lon"]), float(row["h"]))


def r_ecef_cam(row):
    return q_to_rot([float(row[k]) for k in ("qw", "qx", "qy", "qz")])


def main():
    flight, run = sys.argv[1], sys.argv[2]
    cam = json.load(open(os.path.join(flight, "camera.json")))
    err = json.load(open(os.path.join(flight, "scenario.json"))).get("camera_error") or {}
    scale = 1.0 + err.get("focal_rel", 0.0)
    k = np.array(
        [
            [cam["fx"] * scale, 0.0, cam["cx"] + err.get("principal_du_px", 0.0)],
            [0.0, cam["fy"] * scale, cam["cy"] + err.get("principal_dv_px", 0.0)],
            [0.0, 0.0, 1.0],
        ]
    )
    d = cam["distortion"]
    dist = np.array(
        [d["k1"] + err.get("k1", 0.0), d["k2"] + err.get("k2", 0.0), d["p1"], d["p2"], d["k3"]]
    )
    truth = {round(float(r["t"]), 3): r for r in csv.DictReader(open(os.path.join(flight, "truth.csv")))}
    frames = {}
    for r in csv.DictReader(open(os.path.join(run, "matches.csv"))):
        if r["inlier"] == "1":
            frames.setdefault(round(float(r["t"]), 3), []).append(r)
    offsets, pnp = [], []
    per_landmark = {}
    for t in sorted(frames):
        rows, true = frames[t], truth[t]
        pts = np.array([[float(r[c]) for c in ("x_m", "y_m", "z_m")] for r in rows])
        px = np.array([[float(r["u"]), float(r["v"])] for r in rows])
        c_true, r_true = ecef(true), r_ecef_cam(true)
        # The landmarks in the true camera frame, projected through the true lens.
        cam_pts = (pts - c_true) @ r_true
        proj, _ = cv2.projectPoints(cam_pts, np.zeros(3), np.zeros(3), k, dist)
        frame_off = px - proj.reshape(-1, 2)
        offsets.extend(frame_off)
        for r, o in zip(rows, frame_off):
            per_landmark.setdefault(int(r["landmark"]), []).append(o)
        if len(rows) < 4:
            continue
        origin = pts.mean(axis=0)
        ok, rvec, tvec = cv2.solvePnP(pts - origin, px, k, dist, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            continue
        ok, rvec, tvec = cv2.solvePnP(
            pts - origin, px, k, dist, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
        )
        rot, _ = cv2.Rodrigues(rvec)
        centre = origin - rot.T @ tvec.ravel()
        pnp.append(float(np.linalg.norm(centre - c_true)))
    off = np.array(offsets).reshape(-1, 2)
    half = len(pnp) // 2
    mean = lambda xs: float(np.mean(xs)) if len(xs) else math.nan
    out = {
        "inliers": len(off),
        "offset_u_px": mean(off[:, 0]),
        "offset_v_px": mean(off[:, 1]),
        "rms_px": math.sqrt(mean((off**2).sum(axis=1))),
        "pnp_fixes": len(pnp),
        "pnp_mean_m": mean(pnp),
        "pnp_early_m": mean(pnp[:half]),
        "pnp_late_m": mean(pnp[half:]),
    }
    if len(sys.argv) > 3:
        out["by_shading_share"] = by_shading_share(sys.argv[3], per_landmark)
    print(json.dumps(out))


# Bins of the shading share (upper bounds; the last holds 1).
SHARE_BINS = [0.2, 0.4, 0.6, 1.0]


def by_shading_share(database, per_landmark):
    """The inliers' offsets per landmark, binned by the landmark's shading share."""
    con = sqlite3.connect(f"file:{database}?mode=ro", uri=True)
    share = dict(con.execute("SELECT fid, shading_share FROM templates"))
    bins = [{"share_below": b, "landmarks": 0, "inliers": 0, "sys2": 0.0, "all2": 0.0} for b in SHARE_BINS]
    for landmark, offs in per_landmark.items():
        s = share.get(landmark)
        if s is None:
            raise SystemExit(f"{database}: no template {landmark} (matches.csv names it): another database?")
        b = next(b for b, top in zip(bins, SHARE_BINS) if s < top or top == SHARE_BINS[-1])
        o = np.array(offs)
        b["landmarks"] += 1
        b["inliers"] += len(o)
        b["sys2"] += len(o) * float((o.mean(axis=0) ** 2).sum())
        b["all2"] += float((o**2).sum())
    return [
        {
            "share_below": b["share_below"],
            "landmarks": b["landmarks"],
            "inliers": b["inliers"],
            "systematic_px": math.sqrt(b["sys2"] / b["inliers"]) if b["inliers"] else math.nan,
            "rms_px": math.sqrt(b["all2"] / b["inliers"]) if b["inliers"] else math.nan,
        }
        for b in bins
    ]


if __name__ == "__main__":
    main()
