//! The intrinsic Delaunay triangulation of a mesh's surface (Bobenko & Springborn 2007;
//! Fisher et al. 2006) and its cotangent weights: the same surface, the same vertices,
//! edges flipped along the surface until every edge is Delaunay, so the weights are never
//! negative and do not depend on how unevenly the mesh was triangulated.
//!
//! Only edge lengths are kept (no positions): a flipped edge runs across two triangles
//! laid flat, so it may join vertices that no mesh edge joins. Edges on a boundary or
//! shared by more than two triangles are never flipped.

use super::V3;
use std::collections::HashMap;

const NONE: u32 = u32::MAX;

/// Half-edges of a triangulation that can flip edges: ids are stable across flips,
/// the triangle a half-edge belongs to is its `next` cycle.
struct HalfEdges {
    /// the vertex each half-edge leaves
    tail: Vec<u32>,
    next: Vec<u32>,
    /// the opposite half-edge, or `NONE` on a boundary or non-manifold edge
    twin: Vec<u32>,
    /// the edge's length along the surface (equal on both half-edges)
    length: Vec<f64>,
}

impl HalfEdges {
    fn new(v: &[V3], tris: &[[u32; 3]]) -> HalfEdges {
        let m = tris.len() * 3;
        let mut tail = Vec::with_capacity(m);
        let mut next = Vec::with_capacity(m);
        let mut length = Vec::with_capacity(m);
        let mut by_pair: HashMap<(u32, u32), Vec<u32>> = HashMap::with_capacity(m);
        for (f, t) in tris.iter().enumerate() {
            for k in 0..3 {
                let h = (3 * f + k) as u32;
                let (a, b) = (t[k], t[(k + 1) % 3]);
                tail.push(a);
                next.push((3 * f + (k + 1) % 3) as u32);
                length.push((v[a as usize] - v[b as usize]).norm());
                by_pair.entry((a.min(b), a.max(b))).or_default().push(h);
            }
        }
        let mut twin = vec![NONE; m];
        for hs in by_pair.values() {
            // two half-edges running opposite ways: an interior manifold edge
            if let [h, g] = hs[..]
                && tail[h as usize] != tail[g as usize]
            {
                twin[h as usize] = g;
                twin[g as usize] = h;
            }
        }
        HalfEdges {
            tail,
            next,
            twin,
            length,
        }
    }

    /// The cotangent of the angle opposite half-edge `h` in its triangle, from the three
    /// lengths; a degenerate triangle gives a large value of the right sign.
    fn cot_opposite(&self, h: u32) -> f64 {
        let n = self.next[h as usize];
        let p = self.next[n as usize];
        let (a, b, c) = (
            self.length[h as usize],
            self.length[n as usize],
            self.length[p as usize],
        );
        let area = triangle_area(a, b, c);
        (b * b + c * c - a * a) / (4.0 * area).max(1e-300)
    }

    /// Flips the edge of `h` (interior) when that leaves two proper triangles; returns
    /// whether it did. Triangles (i j k) and (j i l) become (k l j) and (l k i).
    fn flip(&mut self, h: u32) -> bool {
        let t = self.twin[h as usize];
        let (hn, hp) = (
            self.next[h as usize],
            self.next[self.next[h as usize] as usize],
        );
        let (tn, tp) = (
            self.next[t as usize],
            self.next[self.next[t as usize] as usize],
        );
        let (k, l) = (self.tail[hp as usize], self.tail[tp as usize]);
        if k == l {
            return false;
        }
        // lay the two triangles flat, i at the origin and j on the x axis
        let ij = self.length[h as usize];
        let place = |to_i: f64, to_j: f64, side: f64| {
            let x = (ij * ij + to_i * to_i - to_j * to_j) / (2.0 * ij);
            (x, side * (to_i * to_i - x * x).max(0.0).sqrt())
        };
        let (kx, ky) = place(self.length[hp as usize], self.length[hn as usize], 1.0);
        let (lx, ly) = place(self.length[tn as usize], self.length[tp as usize], -1.0);
        let kl = ((kx - lx).powi(2) + (ky - ly).powi(2)).sqrt();
        // the flat quadrilateral must be convex at i and j, or the new edge leaves it
        let cross = |ax: f64, ay: f64, bx: f64, by: f64| ax * by - ay * bx;
        let at_i = cross(lx, ly, kx, ky);
        let at_j = cross(kx - ij, ky, lx - ij, ly);
        let scale = ij * kl;
        if !(at_i > 1e-12 * scale && at_j > 1e-12 * scale) {
            return false;
        }
        self.tail[h as usize] = k;
        self.tail[t as usize] = l;
        self.length[h as usize] = kl;
        self.length[t as usize] = kl;
        self.next[h as usize] = tp;
        self.next[tp as usize] = hn;
        self.next[hn as usize] = h;
        self.next[t as usize] = hp;
        self.next[hp as usize] = tn;
        self.next[tn as usize] = t;
        true
    }
}

/// A triangle's area from its side lengths (Heron's formula in its stable ordering).
fn triangle_area(a: f64, b: f64, c: f64) -> f64 {
    let mut s = [a, b, c];
    s.sort_unstable_by(|x, y| y.total_cmp(x));
    let [a, b, c] = s;
    let q = (a + (b + c)) * (c - (a - b)) * (c + (a - b)) * (a + (b - c));
    0.25 * q.max(0.0).sqrt()
}

/// The intrinsic Delaunay triangulation's cotangent weights.
///
/// - `v`: #V positions; `tris`: #F triangles
/// - returns `(i, j, w)` with `i < j`, one entry per vertex pair (edges joining the same
///   pair summed), `w = (cot a + cot b) / 2` over the angles opposite the edge, never
///   negative beyond rounding; and the number of flips made
pub fn delaunay_cotan_weights(v: &[V3], tris: &[[u32; 3]]) -> (Vec<(u32, u32, f64)>, usize) {
    let mut he = HalfEdges::new(v, tris);
    let m = he.tail.len();
    let mut queued = vec![true; m];
    let mut stack: Vec<u32> = (0..m as u32).collect();
    let mut flips = 0;
    // a bound that a proper input never reaches, so a degenerate one cannot loop
    let limit = 20 * m + 100;
    while let Some(h) = stack.pop() {
        queued[h as usize] = false;
        let t = he.twin[h as usize];
        if t == NONE || flips >= limit {
            continue;
        }
        queued[t as usize] = false;
        if he.cot_opposite(h) + he.cot_opposite(t) >= -1e-12 {
            continue;
        }
        if !he.flip(h) {
            continue;
        }
        flips += 1;
        let around = [
            he.next[h as usize],
            he.next[he.next[h as usize] as usize],
            he.next[t as usize],
            he.next[he.next[t as usize] as usize],
        ];
        for g in around {
            if !queued[g as usize] {
                queued[g as usize] = true;
                stack.push(g);
            }
        }
    }
    let mut raw: Vec<(u32, u32, f64)> = (0..m as u32)
        .filter_map(|h| {
            let (a, b) = (he.tail[h as usize], he.tail[he.next[h as usize] as usize]);
            (a != b).then(|| (a.min(b), a.max(b), 0.5 * he.cot_opposite(h)))
        })
        .collect();
    raw.sort_unstable_by_key(|&(i, j, _)| (i, j));
    let mut out: Vec<(u32, u32, f64)> = Vec::with_capacity(raw.len() / 2 + 1);
    for (i, j, w) in raw {
        match out.last_mut() {
            Some(last) if last.0 == i && last.1 == j => last.2 += w,
            _ => out.push((i, j, w)),
        }
    }
    (out, flips)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A square split along its long way by a sliver: the edge opposite two obtuse angles
    /// has a negative cotangent weight until flipped.
    #[test]
    fn flips_the_obtuse_diagonal_of_a_kite() {
        // i=0, j=1 the diagonal; k and l close to it on either side
        let v = vec![
            V3::new(0.0, 0.0, 0.0),
            V3::new(2.0, 0.0, 0.0),
            V3::new(1.0, 0.2, 0.0),
            V3::new(1.0, -0.2, 0.0),
        ];
        let tris = vec![[0, 1, 2], [1, 0, 3]];
        let (w, flips) = delaunay_cotan_weights(&v, &tris);
        assert_eq!(flips, 1);
        assert!(w.iter().all(|&(_, _, w)| w >= 0.0), "{w:?}");
        // the diagonal 0-1 is gone, 2-3 is there with its two angles' cotangents
        assert!(!w.iter().any(|&(i, j, _)| (i, j) == (0, 1)));
        let (_, _, w23) = *w.iter().find(|&&(i, j, _)| (i, j) == (2, 3)).unwrap();
        // angles at 0 and 1 opposite 2-3: half-angle atan(0.2) each side
        let cot = 1.0 / (2.0 * 0.2f64.atan()).tan();
        assert!((w23 - cot).abs() < 1e-12, "{w23} against {cot}");
    }

    /// On a Delaunay mesh nothing flips and the weights are the cotangent weights.
    #[test]
    fn a_delaunay_grid_is_left_alone() {
        let n = 5;
        let v: Vec<V3> = (0..n * n)
            .map(|k| V3::new((k % n) as f64, (k / n) as f64, 0.0))
            .collect();
        let mut tris = Vec::new();
        for y in 0..n - 1 {
            for x in 0..n - 1 {
                let a = (y * n + x) as u32;
                tris.push([a, a + 1, a + n as u32 + 1]);
                tris.push([a, a + n as u32 + 1, a + n as u32]);
            }
        }
        let (w, flips) = delaunay_cotan_weights(&v, &tris);
        assert_eq!(flips, 0);
        // the diagonals have weight 0 (two right angles); axis edges inside weigh 1
        let inner = w
            .iter()
            .find(|&&(i, j, _)| (i, j) == (6, 7))
            .map(|t| t.2)
            .unwrap();
        assert!((inner - 1.0).abs() < 1e-12, "{inner}");
        assert!(w.iter().all(|&(_, _, w)| w > -1e-12));
    }

    /// A fan of slivers round a vertex in a plane: after flipping no weight is negative,
    /// and the centre's weights still give a linear function no Laplacian, so the flips
    /// kept the geometry.
    #[test]
    fn linear_functions_stay_harmonic_after_flips() {
        // a planar fan of slivers around an interior vertex
        let mut v = vec![V3::new(0.0, 0.0, 0.0)];
        let k = 12;
        for s in 0..k {
            let a = s as f64 / k as f64 * std::f64::consts::TAU;
            let r = if s % 2 == 0 { 1.0 } else { 0.3 };
            v.push(V3::new(r * a.cos(), r * a.sin(), 0.0));
        }
        let mut tris = Vec::new();
        for s in 0..k as u32 {
            tris.push([0, 1 + s, 1 + (s + 1) % k as u32]);
        }
        let (w, flips) = delaunay_cotan_weights(&v, &tris);
        assert!(flips > 0);
        assert!(w.iter().all(|&(_, _, w)| w > -1e-12), "{w:?}");
        // the centre is interior: a linear function has no Laplacian there
        let lap: V3 = w
            .iter()
            .filter(|&&(i, _, _)| i == 0)
            .map(|&(_, j, w)| (v[j as usize] - v[0]) * w)
            .sum();
        assert!(lap.norm() < 1e-9, "{lap:?}");
    }
}
