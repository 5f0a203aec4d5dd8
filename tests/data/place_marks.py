#!/usr/bin/env python3
"""Places the quadrupeds' semantic marks (tests/data/README.md, "Semantic marks") by rule.

Usage: python3 place_marks.py MESH.obj FORWARD > MESH.marks
FORWARD: the way the animal faces in the loader's z-up frame, e.g. 0,-1,0.
Needs numpy. Reproduces koala.marks exactly and cow.marks but for rump_top (a vertex
0.1 away at the same height, 0.9% of the diagonal; both marks were placed by hand
with the rule before this script).
"""
import sys

import numpy as np


def load_z_up(path):
    v = []
    for line in open(path):
        t = line.split()
        if t and t[0] == "v":
            v.append([float(x) for x in t[1:4]])
    v = np.array(v)
    # stored y-up; the loader (devset::load) turns it z-up
    return np.c_[v[:, 0], -v[:, 2], v[:, 1]]


def marks(z, forward):
    forward = np.asarray(forward, float)
    up = np.array([0.0, 0.0, 1.0])
    left = np.cross(up, forward)
    h, f, s = z[:, 2], z @ forward, z @ left
    height = h.max() - h.min()
    out = {}
    # hooves: the lowest 4% of the height, split front/hind and left/right about their
    # centre; in each quarter the most forward vertex of its lowest 2%
    low = np.where(h < h.min() + 0.04 * height)[0]
    cf, cs = f[low].mean(), s[low].mean()
    for name, front, on_left in (
        ("hoof_fl", True, True),
        ("hoof_fr", True, False),
        ("hoof_hl", False, True),
        ("hoof_hr", False, False),
    ):
        quarter = low[((f[low] > cf) == front) & ((s[low] > cs) == on_left)]
        lowest = quarter[h[quarter] < h[quarter].min() + 0.02 * height]
        out[name] = int(lowest[np.argmax(f[lowest])])
    out["snout_tip"] = int(np.argmax(f))
    # withers (rump top): the highest vertex within 8% of the width of the midline and
    # 4% of the length of the front (hind) hooves' place along the body
    width, length = s.max() - s.min(), f.max() - f.min()
    for name, (a, b) in (("withers", ("hoof_fl", "hoof_fr")), ("rump_top", ("hoof_hl", "hoof_hr"))):
        at = (f[out[a]] + f[out[b]]) / 2
        near = np.where((np.abs(s - cs) < 0.08 * width) & (np.abs(f - at) < 0.04 * length))[0]
        out[name] = int(near[np.argmax(h[near])])
    return out


if __name__ == "__main__":
    z = load_z_up(sys.argv[1])
    m = marks(z, [float(x) for x in sys.argv[2].split(",")])
    for name in ("hoof_fl", "hoof_fr", "hoof_hl", "hoof_hr", "snout_tip", "withers", "rump_top"):
        print(name, m[name])
