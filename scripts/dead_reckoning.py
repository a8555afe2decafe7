#!/usr/bin/env python3
"""Dead reckoning without vision: the flight's initial guess carried to every
frame by the gyro alone (exact strapdown integration, Earth rate removed),
position held at the initial guess. Writes a poses.csv (status `propagated`)
that `trn evaluate` scores: the reference a terrain relative navigator must
beat, and a way to see the evaluation plots before any navigator runs.

Usage: scripts/dead_reckoning.py FLIGHT_DIR OUT_POSES_CSV
"""
import csv
import json
import os
import sys

import numpy as np

EARTH_RATE = 7.292115e-5


def qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


def qexp(v):
    a = np.linalg.norm(v)
    if a < 1e-300:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[np.cos(a / 2)], np.sin(a / 2) * v / a])


def conj(q):
    return np.array([q[0], -q[1], -q[2], -q[3]])


def main():
    flight, out = sys.argv[1], sys.argv[2]
    cam = json.load(open(os.path.join(flight, "camera.json")))
    q_cam_imu = np.array(cam.get("q_cam_imu", [1, 0, 0, 0]), float)
    init = json.load(open(os.path.join(flight, "init.json")))
    frames = [float(r["t"]) for r in csv.DictReader(open(os.path.join(flight, "frames.csv")))]
    imu = [(float(r["t"]), np.array([float(r["wx"]), float(r["wy"]), float(r["wz"])]))
           for r in csv.DictReader(open(os.path.join(flight, "imu.csv")))]
    q = qmul(np.array(init["q_ecef_cam"], float), q_cam_imu)  # q_ecef_imu
    t, k = init["t"], 0
    rows = []
    for tf in frames:
        # Samples describe the interval that ends at their time.
        while k < len(imu) and imu[k][0] <= tf + 1e-9:
            tk, w = imu[k]
            if tk > t:
                dt = tk - t
                q = qmul(qmul(qexp(np.array([0, 0, -EARTH_RATE * dt])), q), qexp(w * dt))
                q /= np.linalg.norm(q)
                t = tk
            k += 1
        qc = qmul(q, conj(q_cam_imu))
        rows.append(f"{tf:.6f},{init['lat']:.10f},{init['lon']:.10f},{init['h']:.4f},"
                    f"{qc[0]:.12f},{qc[1]:.12f},{qc[2]:.12f},{qc[3]:.12f},propagated,0,0,0.00")
    tmp = out + ".part"
    with open(tmp, "w") as f:
        f.write("t,lat,lon,h,qw,qx,qy,qz,status,inliers,matches,ms\n")
        f.write("\n".join(rows) + "\n")
    os.replace(tmp, out)


if __name__ == "__main__":
    main()
