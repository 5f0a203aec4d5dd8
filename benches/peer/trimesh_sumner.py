#!/usr/bin/env python3
"""The peer on the development set: trimesh's Sumner-Popovic non-rigid ICP
(trimesh.registration.nricp_sumner, default steps) on the cases that
`cargo bench --bench devset -- --export DIR` writes. Prints, per case, the same figures as
the devset bench: mean correspondence error, in holes, p95 (% of the truth's diagonal),
triangles flipped against the truth, seconds.

Needs: pip install trimesh numpy scipy rtree.  Run: python3 trimesh_sumner.py DIR
Without landmarks the peer gets a rigid ICP with scale first (trimesh.registration.icp),
as it has no global stage of its own.  Coordinates are scaled so the template's diagonal
is 1, as trimesh's default thresholds assume.
"""
import os
import sys
import time

import numpy as np
import trimesh
from trimesh.registration import icp, nricp_sumner


def read_landmarks(path):
    out = {}
    for line in open(path):
        p = line.split("#")[0].split()
        if len(p) == 2:
            out[p[0]] = int(p[1])
        elif len(p) == 4:
            out[p[0]] = np.array([float(x) for x in p[1:]])
    return out


def flipped(a, b, faces):
    na = np.cross(a[faces[:, 1]] - a[faces[:, 0]], a[faces[:, 2]] - a[faces[:, 0]])
    nb = np.cross(b[faces[:, 1]] - b[faces[:, 0]], b[faces[:, 2]] - b[faces[:, 0]])
    return int(((na * nb).sum(1) <= 0).sum())


def run(d):
    tpl = trimesh.load(os.path.join(d, "template.obj"), process=False)
    scan = trimesh.load(os.path.join(d, "scan.ply"), process=False)
    truth = trimesh.load(os.path.join(d, "truth.obj"), process=False).vertices
    in_hole = np.loadtxt(os.path.join(d, "in_hole.txt")).astype(bool)
    pts = np.asarray(scan.vertices)
    lo, hi = tpl.bounds
    c, s = (lo + hi) / 2, np.linalg.norm(hi - lo)
    src = trimesh.Trimesh((tpl.vertices - c) / s, tpl.faces, process=False)
    tgt = (pts - c) / s
    t0 = time.time()
    lm = None
    if os.path.exists(os.path.join(d, "template.lm")):
        tl, sl = read_landmarks(os.path.join(d, "template.lm")), read_landmarks(os.path.join(d, "scan.lm"))
        names = [n for n in tl if n in sl]
        idx = np.array([tl[n] for n in names])
        pos = (np.array([sl[n] for n in names]) - c) / s
        lm = (idx, pos)
        # landmarks place the template first, as the peer's users would
        m, _, _ = trimesh.registration.procrustes(src.vertices[idx], pos, scale=True)
        src = trimesh.Trimesh(trimesh.transform_points(src.vertices, m), src.faces, process=False)
    else:
        m, _, _ = icp(src.vertices, tgt, scale=True, max_iterations=50)
        src = trimesh.Trimesh(trimesh.transform_points(src.vertices, m), src.faces, process=False)
    # nricp_sumner queries its target as a mesh; a mesh without faces is matched to its
    # vertices (a point cloud), normals estimated from neighbours
    cloud = trimesh.Trimesh(vertices=tgt, faces=np.zeros((0, 3), dtype=np.int64), process=False)
    if lm is None:
        res = nricp_sumner(src, cloud)
    else:
        res = nricp_sumner(src, cloud, source_landmarks=lm[0], target_positions=lm[1])
    secs = time.time() - t0
    res = res * s + c
    diag = np.linalg.norm(truth.max(0) - truth.min(0))
    e = np.linalg.norm(res - truth, axis=1) / diag
    holes = e[in_hole].mean() if in_hole.any() else 0.0
    return e.mean(), holes, np.percentile(e, 95), flipped(res, truth, tpl.faces), secs


def main():
    root = sys.argv[1]
    for name in sorted(os.listdir(root)):
        d = os.path.join(root, name)
        if not os.path.isdir(d):
            continue
        mean, holes, p95, flips, secs = run(d)
        print(f"{name:<34} mean {mean*100:6.3f}%  holes {holes*100:6.3f}%  p95 {p95*100:6.3f}%  flipped {flips:5d}  {secs:6.1f} s", flush=True)


if __name__ == "__main__":
    main()
