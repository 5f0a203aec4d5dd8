//! Decimation by half-edge collapse, ordered by Garland and Heckbert's quadric error plus
//! an edge-length term: a coarse mesh whose vertices are a subset of the original's, so
//! that a fit on it carries back to every original vertex through its nearest kept one
//! (`owner`). Boundaries, non-manifold edges and protected vertices (landmarks) stay; a
//! collapse that would fold a triangle, pinch the surface or make a sliver is refused.

use super::{Mesh, V3};
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// A coarse copy of a mesh and the maps between the two.
#[derive(Debug, Clone)]
pub struct Decimated {
    /// the kept vertices (in their original order) and the remaining triangles; groups
    /// keep their kept members
    pub mesh: Mesh,
    /// coarse index -> original index
    pub kept: Vec<u32>,
    /// original index -> the coarse index of the nearest kept vertex along the edges
    pub owner: Vec<u32>,
}

/// Quadric `Q` of squared distances to planes, as the 10 distinct entries of a symmetric
/// 4x4 matrix.
#[derive(Debug, Clone, Copy, Default)]
struct Quadric([f64; 10]);

impl Quadric {
    /// `w (n.p + d)^2` for the plane with unit normal `n` through `p0`.
    fn plane(n: V3, p0: V3, w: f64) -> Self {
        let d = -n.dot(&p0);
        let (a, b, c) = (n.x, n.y, n.z);
        Quadric([
            w * a * a,
            w * a * b,
            w * a * c,
            w * a * d,
            w * b * b,
            w * b * c,
            w * b * d,
            w * c * c,
            w * c * d,
            w * d * d,
        ])
    }

    fn add(&mut self, o: &Quadric) {
        for (a, b) in self.0.iter_mut().zip(o.0) {
            *a += b;
        }
    }

    fn eval(&self, p: &V3) -> f64 {
        let q = &self.0;
        let (x, y, z) = (p.x, p.y, p.z);
        q[0] * x * x
            + 2.0 * q[1] * x * y
            + 2.0 * q[2] * x * z
            + 2.0 * q[3] * x
            + q[4] * y * y
            + 2.0 * q[5] * y * z
            + 2.0 * q[6] * y
            + q[7] * z * z
            + 2.0 * q[8] * z
            + q[9]
    }
}

/// A vertex's cheapest collapse, valid while its stamp is unchanged (a change of that
/// cost bumps the stamp and queues it afresh): one live entry per vertex, not per
/// half-edge.
#[derive(Debug, PartialEq)]
struct Candidate {
    cost: f64,
    from: u32,
    to: u32,
    stamp: u32,
    /// when it was queued: equal costs (a flat, even region) go first come, first served
    order: u64,
}

impl Eq for Candidate {}
impl Ord for Candidate {
    fn cmp(&self, o: &Self) -> Ordering {
        // the cheapest first out of the max-heap
        o.cost.total_cmp(&self.cost).then(o.order.cmp(&self.order))
    }
}
impl PartialOrd for Candidate {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}

/// Shape quality of a triangle: 1 for equilateral, 0 for degenerate.
fn quality(a: &V3, b: &V3, c: &V3) -> f64 {
    let s = (b - a).norm_squared() + (c - b).norm_squared() + (a - c).norm_squared();
    if s > 0.0 {
        2.0 * 3f64.sqrt() * (b - a).cross(&(c - a)).norm() / s
    } else {
        0.0
    }
}

struct State<'a> {
    v: &'a [V3],
    tris: Vec<[u32; 3]>,
    alive_tri: Vec<bool>,
    faces: Vec<Vec<u32>>,
    quadric: Vec<Quadric>,
    stamp: Vec<u32>,
    /// each vertex's cheapest collapse (cost, target) as last queued
    best: Vec<(f64, u32)>,
    /// vertices whose every collapse was refused: tried again when a neighbour collapses
    waiting: Vec<bool>,
    /// candidates queued so far
    queued: u64,
    alive: Vec<bool>,
    /// never removed: protected, or on a non-manifold edge
    locked: Vec<bool>,
    boundary: Vec<bool>,
    /// weight of the edge-length term, in the quadric's units (area x distance^2)
    length_weight: f64,
}

impl State<'_> {
    fn neighbours(&self, u: u32) -> Vec<u32> {
        let faces = &self.faces[u as usize];
        let mut nb: Vec<u32> = Vec::with_capacity(3 * faces.len());
        for &f in faces {
            nb.extend(self.tris[f as usize].iter().filter(|&&w| w != u));
        }
        nb.sort_unstable();
        nb.dedup();
        nb
    }

    /// Live triangles that use the edge `u`-`v`.
    fn shared_faces(&self, u: u32, v: u32) -> usize {
        self.faces[u as usize]
            .iter()
            .filter(|&&f| self.tris[f as usize].contains(&v))
            .count()
    }

    fn cost(&self, from: u32, to: u32) -> f64 {
        let mut q = self.quadric[from as usize];
        q.add(&self.quadric[to as usize]);
        let l2 = (self.v[from as usize] - self.v[to as usize]).norm_squared();
        q.eval(&self.v[to as usize]).max(0.0) + self.length_weight * l2 * l2
    }

    /// Where `u` may collapse to, cheapest first (a boundary vertex only slides along its
    /// boundary; a locked one goes nowhere).
    fn targets(&self, u: u32) -> Vec<(f64, u32)> {
        if self.locked[u as usize] {
            return Vec::new();
        }
        let mut t: Vec<(f64, u32)> = self
            .neighbours(u)
            .into_iter()
            .filter(|&w| self.may_collapse_to(u, w))
            .map(|w| (self.cost(u, w), w))
            .collect();
        t.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        t
    }

    /// Whether `u` may collapse along its edge to `w`: a boundary vertex only along its
    /// boundary.
    fn may_collapse_to(&self, u: u32, w: u32) -> bool {
        !self.locked[u as usize] && (!self.boundary[u as usize] || self.shared_faces(u, w) == 1)
    }

    fn enqueue(&mut self, heap: &mut BinaryHeap<Candidate>, u: u32, best: (f64, u32)) {
        self.stamp[u as usize] += 1;
        self.best[u as usize] = best;
        if best.0.is_finite() {
            heap.push(Candidate {
                cost: best.0,
                from: u,
                to: best.1,
                stamp: self.stamp[u as usize],
                order: self.queued,
            });
            self.queued += 1;
        }
    }

    /// Queues `u`'s cheapest collapse, all its edges priced afresh.
    fn push(&mut self, heap: &mut BinaryHeap<Candidate>, u: u32) {
        let mut best = (f64::INFINITY, u32::MAX);
        if !self.locked[u as usize] {
            let boundary = self.boundary[u as usize];
            for &f in &self.faces[u as usize] {
                let t = self.tris[f as usize];
                let k = t.iter().position(|&w| w == u).unwrap_or(0);
                // inside a consistently wound fan every neighbour follows u in exactly
                // one triangle; a boundary vertex's last neighbour only precedes it
                let next = t[(k + 1) % 3];
                let prev = t[(k + 2) % 3];
                for w in [next, prev].into_iter().take(if boundary { 2 } else { 1 }) {
                    if w != u && (!boundary || self.shared_faces(u, w) == 1) {
                        let c = self.cost(u, w);
                        if c < best.0 {
                            best = (c, w);
                        }
                    }
                }
            }
        }
        self.enqueue(heap, u, best);
    }

    /// After `u` collapsed into `v`: `v`'s quadric changed, so its own collapses and its
    /// neighbours' collapses onto it are priced again; a neighbour's other edges keep
    /// their cost, so it is queued again only when its best changes (or it was waiting).
    fn requeue_after(&mut self, heap: &mut BinaryHeap<Candidate>, u: u32, v: u32) {
        self.push(heap, v);
        for w in self.neighbours(v) {
            let (cost, to) = self.best[w as usize];
            if to == u || to == v || self.waiting[w as usize] {
                self.waiting[w as usize] = false;
                self.push(heap, w);
            } else if self.may_collapse_to(w, v) {
                let c = self.cost(w, v);
                if c < cost {
                    self.enqueue(heap, w, (c, v));
                }
            }
        }
    }

    /// Whether removing `u` into `v` keeps the surface a manifold without folds or slivers.
    fn allowed(&self, u: u32, v: u32) -> bool {
        let shared: Vec<u32> = self.faces[u as usize]
            .iter()
            .copied()
            .filter(|&f| self.tris[f as usize].contains(&v))
            .collect();
        if shared.is_empty() {
            return false;
        }
        // link condition: the only common neighbours are the shared triangles' corners
        let nu = self.neighbours(u);
        let nv = self.neighbours(v);
        let common = nu.iter().filter(|w| nv.binary_search(w).is_ok()).count();
        if common != shared.len() {
            return false;
        }
        // a closed piece must keep a volume: no collapse below a tetrahedron
        if nu.len() + nv.len() < 6 {
            return false;
        }
        let pv = self.v[v as usize];
        for &f in &self.faces[u as usize] {
            let t = self.tris[f as usize];
            if t.contains(&v) {
                continue;
            }
            let p = t.map(|w| self.v[w as usize]);
            let moved = t.map(|w| if w == u { pv } else { self.v[w as usize] });
            let n_old = (p[1] - p[0]).cross(&(p[2] - p[0]));
            let n_new = (moved[1] - moved[0]).cross(&(moved[2] - moved[0]));
            let (lo, ln) = (n_old.norm(), n_new.norm());
            if !(ln > 0.0) || (lo > 0.0 && n_old.dot(&n_new) < 0.5 * lo * ln) {
                return false;
            }
            let q_new = quality(&moved[0], &moved[1], &moved[2]);
            if q_new < 0.1f64.min(quality(&p[0], &p[1], &p[2])) {
                return false;
            }
        }
        true
    }

    fn collapse(&mut self, u: u32, v: u32) {
        let faces_u = std::mem::take(&mut self.faces[u as usize]);
        for f in faces_u {
            let t = self.tris[f as usize];
            if t.contains(&v) {
                self.alive_tri[f as usize] = false;
                for w in t {
                    if w != u {
                        self.faces[w as usize].retain(|&g| g != f);
                    }
                }
            } else {
                for w in self.tris[f as usize].iter_mut() {
                    if *w == u {
                        *w = v;
                    }
                }
                self.faces[v as usize].push(f);
            }
        }
        let q = self.quadric[u as usize];
        self.quadric[v as usize].add(&q);
        self.alive[u as usize] = false;
    }
}

/// Decimates `mesh` to about `target` vertices (never below what its pieces, boundaries
/// and `protected` vertices allow). Vertices without triangles are kept.
pub fn decimate(mesh: &Mesh, target: usize, protected: &[u32]) -> Decimated {
    let n = mesh.vertices.len();
    let v = &mesh.vertices[..];
    let tris = mesh.triangles.clone();
    let mut faces: Vec<Vec<u32>> = vec![Vec::new(); n];
    for (f, t) in tris.iter().enumerate() {
        for w in t {
            faces[*w as usize].push(f as u32);
        }
    }
    let edge_faces = super::topology::edge_face_counts(&tris);
    let boundary_edge = |a: u32, b: u32| {
        let e = [a.min(b), a.max(b)];
        edge_faces
            .binary_search_by(|(k, _)| k.cmp(&e))
            .is_ok_and(|i| edge_faces[i].1 == 1)
    };
    let mut locked = vec![false; n];
    let mut boundary = vec![false; n];
    for p in protected {
        if let Some(l) = locked.get_mut(*p as usize) {
            *l = true;
        }
    }
    let mut quadric = vec![Quadric::default(); n];
    let mut area_sum = 0.0;
    for t in &tris {
        let p = t.map(|w| v[w as usize]);
        let nrm = (p[1] - p[0]).cross(&(p[2] - p[0]));
        let area = 0.5 * nrm.norm();
        area_sum += area;
        if !(area > 0.0) {
            continue;
        }
        let q = Quadric::plane(nrm / (2.0 * area), p[0], area);
        for w in t {
            quadric[*w as usize].add(&q);
        }
        // boundary edges hold their place through a stiff plane across the edge
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            if boundary_edge(a, b) {
                let e = v[b as usize] - v[a as usize];
                if let Some(m) = e.cross(&nrm).try_normalize(0.0) {
                    let q = Quadric::plane(m, v[a as usize], 10.0 * e.norm_squared());
                    quadric[a as usize].add(&q);
                    quadric[b as usize].add(&q);
                }
            }
        }
    }
    for &([a, b], c) in &edge_faces {
        match c {
            1 => {
                boundary[a as usize] = true;
                boundary[b as usize] = true;
            }
            2 => {}
            _ => {
                locked[a as usize] = true;
                locked[b as usize] = true;
            }
        }
    }
    let mean_area = area_sum / tris.len().max(1) as f64;
    let mut s = State {
        v,
        alive_tri: vec![true; tris.len()],
        tris,
        faces,
        quadric,
        stamp: vec![0; n],
        best: vec![(f64::INFINITY, u32::MAX); n],
        waiting: vec![false; n],
        queued: 0,
        alive: vec![true; n],
        locked,
        boundary,
        // comparable to a typical triangle's quadric at a tenth of an edge's deviation:
        // flat regions collapse their shortest edges first and stay even
        length_weight: 0.1 / mean_area.max(f64::MIN_POSITIVE),
    };
    let mut heap = BinaryHeap::new();
    for u in 0..n as u32 {
        s.push(&mut heap, u);
    }
    let mut alive = n;
    while alive > target {
        let Some(c) = heap.pop() else { break };
        let u = c.from;
        if !s.alive[u as usize] || c.stamp != s.stamp[u as usize] {
            continue;
        }
        // the cheapest target that keeps the surface sound; none: u waits until its
        // neighbourhood changes
        let v = if s.allowed(u, c.to) {
            Some(c.to)
        } else {
            s.targets(u)
                .into_iter()
                .map(|(_, w)| w)
                .find(|&w| w != c.to && s.allowed(u, w))
        };
        let Some(v) = v else {
            s.waiting[u as usize] = true;
            continue;
        };
        s.collapse(u, v);
        alive -= 1;
        s.requeue_after(&mut heap, u, v);
    }
    finish(mesh, &s)
}

fn finish(mesh: &Mesh, s: &State) -> Decimated {
    let n = mesh.vertices.len();
    let kept: Vec<u32> = (0..n as u32).filter(|&i| s.alive[i as usize]).collect();
    let mut index = vec![u32::MAX; n];
    for (c, &i) in kept.iter().enumerate() {
        index[i as usize] = c as u32;
    }
    let triangles: Vec<[u32; 3]> = s
        .tris
        .iter()
        .zip(&s.alive_tri)
        .filter(|(_, a)| **a)
        .map(|(t, _)| t.map(|w| index[w as usize]))
        .collect();
    let mut coarse = Mesh::new(
        kept.iter().map(|&i| mesh.vertices[i as usize]).collect(),
        triangles,
    );
    coarse.groups = mesh
        .groups
        .iter()
        .map(|(g, members)| {
            let m: Vec<u32> = members
                .iter()
                .filter_map(|&i| index.get(i as usize).copied().filter(|&c| c != u32::MAX))
                .collect();
            (g.clone(), m)
        })
        .collect();
    let owner = nearest_kept(mesh, &index);
    Decimated {
        mesh: coarse,
        kept,
        owner,
    }
}

/// For every vertex, the coarse index of the nearest kept vertex along the original
/// edges.
fn nearest_kept(mesh: &Mesh, index: &[u32]) -> Vec<u32> {
    let kept: Vec<u32> = (0..index.len() as u32)
        .filter(|&i| index[i as usize] != u32::MAX)
        .collect();
    let nb = super::topology::vertex_neighbours(mesh.vertices.len(), &mesh.triangles);
    let (_, nearest) = super::topology::edge_distances(&mesh.vertices, &nb, &kept);
    // kept vertices are numbered in order, so the k-th source is coarse vertex k
    nearest
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{quality as q, topology};

    fn grid(k: usize) -> Mesh {
        let mut v = Vec::new();
        let mut t = Vec::new();
        for j in 0..=k {
            for i in 0..=k {
                v.push(V3::new(i as f64, j as f64, 0.0));
            }
        }
        let id = |i: usize, j: usize| (j * (k + 1) + i) as u32;
        for j in 0..k {
            for i in 0..k {
                t.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
                t.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
            }
        }
        Mesh::new(v, t)
    }

    #[test]
    fn a_closed_surface_stays_closed_unfolded_and_near_its_size() {
        // (synth is above mesh, but only this test uses it)
        let m = crate::synth::icosphere(4);
        let before = topology::report(&m);
        assert!(before.watertight);
        let d = decimate(&m, m.vertices.len() / 5, &[7, 100]);
        let after = topology::report(&d.mesh);
        assert!(after.watertight, "{after:?}");
        assert!(d.mesh.vertices.len() <= m.vertices.len() / 5 + 1);
        assert_eq!(q::folded_triangles(&d.mesh), 0);
        // protected vertices survive, and own themselves
        for p in [7u32, 100] {
            let c = d.owner[p as usize] as usize;
            assert_eq!(d.kept[c], p);
        }
        // the coarse sphere's area is within 3% of the fine one's
        let ratio = d.mesh.area() / m.area();
        assert!((0.97..=1.0).contains(&ratio), "{ratio}");
    }

    #[test]
    fn boundaries_stay_and_every_vertex_has_a_nearby_owner() {
        let m = grid(30);
        let d = decimate(&m, 200, &[]);
        let rep = topology::report(&d.mesh);
        assert_eq!(rep.non_manifold_edges, 0);
        // the square's outline is unchanged: the four corners and its area
        assert!((d.mesh.area() - 900.0).abs() < 1e-9, "{}", d.mesh.area());
        for corner in [0u32, 30, 930, 960] {
            assert!(d.kept.contains(&corner));
        }
        let max_owner_distance = (0..m.vertices.len())
            .map(|i| (m.vertices[i] - d.mesh.vertices[d.owner[i] as usize]).norm())
            .fold(0.0, f64::max);
        assert!(max_owner_distance < 4.0, "{max_owner_distance}");
        assert!(d.mesh.vertices.len() <= 200);
    }
}
