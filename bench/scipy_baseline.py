#!/usr/bin/env python3
"""Baseline for `make bench`: the thesis' per-segment HPPC method (Scripts 3.2-3.6, eqs. 3.2-3.19) done the
way the thesis does it, in Python with scipy's curve_fit, on the same BDF file `cellbench fit` reads.

It times the whole process (parse + segment + 4 fits per pulse set) and prints the discharge/charge
parameters per pulse set so they can be compared with cellbench's. This is a reference implementation for
the benchmark only; cellbench itself has no Python.
"""
import sys
import time

import numpy as np
from scipy.optimize import curve_fit


def runs(mask):
    """[begin, end) index pairs of True runs."""
    d = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def main(path):
    t0 = time.perf_counter()
    with open(path) as f:
        header = f.readline().strip().split(",")
    cols = [header.index(c) for c in ("Test Time / s", "Voltage / V", "Current / A")]
    data = np.loadtxt(path, delimiter=",", skiprows=1, usecols=cols)
    t, v, i = data[:, 0], data[:, 1], data[:, 2]
    t_parse = time.perf_counter() - t0

    dis = [r for r in runs(i < -0.5) if 20 <= t[r[1] - 1] - t[r[0]] <= 60]
    chg = [r for r in runs(i > 0.5) if 5 <= t[r[1] - 1] - t[r[0]] <= 60]
    lo, hi = [1e-5, 0.05, 1e-5, 5, -1], [1.0, 5, 1.0, 200.0, 1]
    p0 = [0.05, 0.5, 0.05, 30.0, 0]

    def rise(x, a, tau1, b, tau2, c):  # eq. 3.6
        return -a * (1 - np.exp(-x / tau1)) - b * (1 - np.exp(-x / tau2)) + c

    def decay(x, a, tau1, b, tau2, c):  # eq. 3.10 / 3.18
        return a * np.exp(-x / tau1) + b * np.exp(-x / tau2) + c

    results = []
    for d0, d1 in dis:
        nxt = [c for c in chg if c[0] > d1 and t[c[0]] - t[d1] < 120]
        if not nxt:
            continue
        c0, c1 = nxt[0]
        ocv = v[d0 - 1]
        idis, ichg = abs(i[d0 + 1]), abs(i[c0 + 1])
        r0_d = (ocv - v[d0]) / idis
        try:
            # discharge pulse BC
            x = t[d0:d1] - t[d0]
            y = v[d0:d1] - v[d0]
            pd, _ = curve_fit(rise, x, y, p0=p0, bounds=(lo, hi), maxfev=20000)
            # discharge relaxation DE
            x = t[d1:c0] - t[d1]
            y = v[d1:c0] - ocv
            pdr, _ = curve_fit(decay, x, -y, p0=p0, bounds=(lo, hi), maxfev=20000)
            # charge pulse FG
            x = t[c0:c1] - t[c0]
            y = v[c0:c1] - v[c0]
            pc, _ = curve_fit(rise, x, -y, p0=p0, bounds=(lo, hi), maxfev=20000)
            # charge relaxation HI
            e = min(c1 + int(40 / max(t[c1] - t[c1 - 1], 1e-3)), len(t))
            x = t[c1:e] - t[c1]
            y = v[c1:e] - ocv
            pcr, _ = curve_fit(decay, x, y, p0=p0, bounds=(lo, hi), maxfev=20000)
        except RuntimeError:
            continue
        r1_d = 0.5 * (pd[0] / idis + pdr[0] / idis)
        r2_d = 0.5 * (pd[2] / idis + pdr[2] / idis)
        results.append((ocv, r0_d, r1_d, pd[1] / (pd[0] / idis), r2_d, pd[3] / (pd[2] / idis),
                        pc[0] / ichg, pcr[0] / ichg))
    total = time.perf_counter() - t0
    print(f"scipy curve_fit baseline: {len(results)} pulse sets, parse {t_parse:.2f} s, whole process {total:.2f} s")
    print(f"  per pulse set (fits only): {(total - t_parse) / max(len(results), 1) * 1000:.1f} ms")
    print("  OCV_V   R0d_mohm  R1d_mohm  C1d_F    R2d_mohm  C2d_F")
    for r in results:
        print(f"  {r[0]:.4f}  {r[1]*1e3:7.3f}  {r[2]*1e3:7.3f}  {r[3]:7.0f}  {r[4]*1e3:7.3f}  {r[5]:7.0f}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/p45b/hppc_1c_30degC.bdf.csv")
