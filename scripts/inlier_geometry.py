#!/usr/bin/env python3
"""What a navigated flight's inlier matches say, with the true camera.

Usage: inlier_geometry.py FLIGHT_DIR RUN_DIR
  FLIGHT_DIR  a simulated flight (camera.json, scenario.json, truth.csv)
  RUN_DIR     a `trn navigate` run on it (poses.csv, matches.csv beside it)

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
                                     of the fixes.
"""
import csv
import json
import math
import os
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
    for t in sorted(frames):
        rows, true = frames[t], truth[t]
        pts = np.array([[float(r[c]) for c in ("x_m", "y_m", "z_m")] for r in rows])
        px = np.array([[float(r["u"]), float(r["v"])] for r in rows])
        c_true, r_true = ecef(true), r_ecef_cam(true)
        # The landmarks in the true camera frame, projected through the true lens.
        cam_pts = (pts - c_true) @ r_true
        proj, _ = cv2.projectPoints(cam_pts, np.zeros(3), np.zeros(3), k, dist)
        offsets.extend(px - proj.reshape(-1, 2))
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
    print(
        json.dumps(
            {
                "inliers": len(off),
                "offset_u_px": mean(off[:, 0]),
                "offset_v_px": mean(off[:, 1]),
                "rms_px": math.sqrt(mean((off**2).sum(axis=1))),
                "pnp_fixes": len(pnp),
                "pnp_mean_m": mean(pnp),
                "pnp_early_m": mean(pnp[:half]),
                "pnp_late_m": mean(pnp[half:]),
            }
        )
    )


if __name__ == "__main__":
    main()
