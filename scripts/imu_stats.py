"""What a flight's IMU log does from one sample to the next, and through a gap.

Usage: .venv/bin/python scripts/imu_stats.py FLIGHT_DIR [FLIGHT_DIR ...]

Per flight: the largest step between two consecutive samples of the gyro
(deg/s) and of the accelerometer (m/s^2), against which `trn navigate
--gyro-max-jump` and `--accel-max-jump` are set; and, for gaps of 1, 3 and
10 s placed every quarter of their length along the log, how far the angle
the gyro integrates departs from that of the rate interpolated linearly
between the samples either side (what `trn navigate` does through a gap;
`--imu-gap-doubt` sizes its doubt), rms and largest (deg), with the same for
the sample after the gap taken as the mean rate (the older rule). Angles are
summed rate vectors (small-angle), enough for a doubt's scale.
"""
import sys

import numpy as np


def stats(flight):
    a = np.loadtxt(f"{flight}/imu.csv", delimiter=",", skiprows=1)
    t, w, f = a[:, 0], a[:, 1:4], a[:, 4:7]
    dt = float(np.median(np.diff(t)))
    gyro_step = np.degrees(np.linalg.norm(np.diff(w, axis=0), axis=1)).max()
    accel_step = np.linalg.norm(np.diff(f, axis=0), axis=1).max()
    print(f"{flight}: {dt * 1e3:.1f} ms samples; largest step gyro {gyro_step:.3f} deg/s, "
          f"accelerometer {accel_step:.3f} m/s^2")
    for gap_s in (1, 3, 10):
        n = int(round(gap_s / dt))
        if n >= len(t):
            continue
        interp, after = [], []
        frac = (np.arange(1, n + 1) - 0.5) / n
        for s in range(0, len(t) - n, max(1, n // 4)):
            seg = w[s:s + n + 1]
            true = seg[1:].sum(0) * dt
            lin = ((1 - frac)[:, None] * seg[0] + frac[:, None] * seg[-1]).sum(0) * dt
            interp.append(np.linalg.norm(true - lin))
            after.append(np.linalg.norm(true - seg[-1] * gap_s))
        interp, after = np.degrees(interp), np.degrees(after)
        print(f"  {gap_s:>2} s gap: interpolated rms {np.sqrt((interp ** 2).mean()):.2f} deg, "
              f"largest {interp.max():.2f}; the sample after as the mean rate: "
              f"rms {np.sqrt((after ** 2).mean()):.2f}, largest {after.max():.2f}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for d in sys.argv[1:]:
        stats(d)
