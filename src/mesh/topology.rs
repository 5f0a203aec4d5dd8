//! Connectivity of a triangle mesh: vertex neighbours, edges with their triangle counts,
//! boundary loops, connected components, and the watertight / manifold checks.

use super::Mesh;
use std::collections::HashMap;

/// Sorted, de-duplicated neighbour lists: #V lists of vertex indices.
pub fn vertex_neighbours(nv: usize, tris: &[[u32; 3]]) -> Vec<Vec<u32>> {
    let mut nb: Vec<Vec<u32>> = vec![Vec::new(); nv];
    for t in tris {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            nb[a as usize].push(b);
            nb[b as usize].push(a);
        }
    }
    for l in &mut nb {
        l.sort_unstable();
        l.dedup();
    }
    nb
}

/// The vertices within `rings` steps of `seeds` along `neighbours`, seeds included.
pub fn rings_around(neighbours: &[Vec<u32>], seeds: &[u32], rings: usize) -> Vec<bool> {
    let mut inside = vec![false; neighbours.len()];
    let mut front: Vec<u32> = seeds.to_vec();
    for &s in seeds {
        inside[s as usize] = true;
    }
    for _ in 0..rings {
        let mut next = Vec::new();
        for &v in &front {
            for &w in &neighbours[v as usize] {
                if !inside[w as usize] {
                    inside[w as usize] = true;
                    next.push(w);
                }
            }
        }
        front = next;
    }
    inside
}

/// The connected parts of the vertices marked `inside` (joined along `neighbours`),
/// each a list of vertex indices.
pub fn parts_of(neighbours: &[Vec<u32>], inside: &[bool]) -> Vec<Vec<u32>> {
    let mut seen = vec![false; neighbours.len()];
    let mut parts = Vec::new();
    for s in 0..neighbours.len() {
        if !inside[s] || seen[s] {
            continue;
        }
        seen[s] = true;
        let mut part = vec![s as u32];
        let mut k = 0;
        while k < part.len() {
            for &w in &neighbours[part[k] as usize] {
                if inside[w as usize] && !seen[w as usize] {
                    seen[w as usize] = true;
                    part.push(w);
                }
            }
            k += 1;
        }
        parts.push(part);
    }
    parts
}

/// For each vertex `inside`, the nearest vertex not inside in steps along `neighbours`
/// (ties to the first reached); `None` for the vertices outside and for an inside part
/// with nothing outside it.
pub fn nearest_outside(neighbours: &[Vec<u32>], inside: &[bool]) -> Vec<Option<u32>> {
    // the outside vertices bordering the inside ones, each its own origin
    let mut origin: Vec<Option<u32>> = vec![None; neighbours.len()];
    let mut front: Vec<u32> = Vec::new();
    for (v, nb) in neighbours.iter().enumerate() {
        if !inside[v] && nb.iter().any(|&w| inside[w as usize]) {
            origin[v] = Some(v as u32);
            front.push(v as u32);
        }
    }
    while !front.is_empty() {
        let mut next = Vec::new();
        for &v in &front {
            for &w in &neighbours[v as usize] {
                let w = w as usize;
                if inside[w] && origin[w].is_none() {
                    origin[w] = origin[v as usize];
                    next.push(w as u32);
                }
            }
        }
        front = next;
    }
    for (o, &i) in origin.iter_mut().zip(inside) {
        if !i {
            *o = None;
        }
    }
    origin
}

/// Undirected edges `(a < b)` with the number of triangles using each, sorted. (By
/// sorting, not hashing: several times faster on meshes of 10k-100k vertices, and the
/// conformation report computes it for every result.)
pub fn edge_face_counts(tris: &[[u32; 3]]) -> Vec<([u32; 2], u32)> {
    let mut keys: Vec<u64> = tris
        .iter()
        .flat_map(|t| (0..3).map(move |k| undirected_key(t[k], t[(k + 1) % 3])))
        .collect();
    keys.sort_unstable();
    let mut out: Vec<([u32; 2], u32)> = Vec::with_capacity(keys.len() / 2 + 1);
    for k in keys {
        let e = [(k >> 32) as u32, k as u32];
        match out.last_mut() {
            Some((last, c)) if *last == e => *c += 1,
            _ => out.push((e, 1)),
        }
    }
    out
}

/// An undirected edge as one sortable number, smaller index first.
pub fn undirected_key(a: u32, b: u32) -> u64 {
    ((a.min(b) as u64) << 32) | a.max(b) as u64
}

/// Unique undirected edges `(a < b)`, sorted.
pub fn edges(tris: &[[u32; 3]]) -> Vec<[u32; 2]> {
    edge_face_counts(tris).into_iter().map(|(e, _)| e).collect()
}

/// Closed loops of boundary edges (edges used by exactly one triangle), each as a vertex
/// sequence following the triangles' orientation. Non-manifold boundary vertices may
/// split loops arbitrarily.
pub fn boundary_loops(tris: &[[u32; 3]]) -> Vec<Vec<u32>> {
    let counts: HashMap<[u32; 2], u32> = edge_face_counts(tris).into_iter().collect();
    // directed boundary half-edges a -> b
    let mut next: HashMap<u32, Vec<u32>> = HashMap::new();
    for t in tris {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            if counts[&[a.min(b), a.max(b)]] == 1 {
                next.entry(a).or_default().push(b);
            }
        }
    }
    let mut starts: Vec<u32> = next.keys().copied().collect();
    starts.sort_unstable();
    let mut loops = Vec::new();
    for s in starts {
        while let Some(b) = next.get_mut(&s).and_then(|v| v.pop()) {
            let mut lp = vec![s];
            let mut cur = b;
            while cur != s {
                lp.push(cur);
                match next.get_mut(&cur).and_then(|v| v.pop()) {
                    Some(n) => cur = n,
                    None => break,
                }
                if lp.len() > tris.len() * 3 {
                    break;
                }
            }
            loops.push(lp);
        }
    }
    loops
}

/// Vertices that lie on a boundary edge (#V flags).
pub fn boundary_vertices(nv: usize, tris: &[[u32; 3]]) -> Vec<bool> {
    let mut b = vec![false; nv];
    for ([x, y], c) in edge_face_counts(tris) {
        if c == 1 {
            b[x as usize] = true;
            b[y as usize] = true;
        }
    }
    b
}

/// Connected components over triangle connectivity: (#V component label, count).
/// Isolated vertices form components of their own.
pub fn components(nv: usize, tris: &[[u32; 3]]) -> (Vec<u32>, usize) {
    let mut parent: Vec<u32> = (0..nv as u32).collect();
    fn find(p: &mut [u32], mut x: u32) -> u32 {
        while p[x as usize] != x {
            p[x as usize] = p[p[x as usize] as usize];
            x = p[x as usize];
        }
        x
    }
    for t in tris {
        for k in 1..3 {
            let (a, b) = (find(&mut parent, t[0]), find(&mut parent, t[k]));
            if a != b {
                parent[a.max(b) as usize] = a.min(b);
            }
        }
    }
    let mut label = vec![u32::MAX; nv];
    let mut of_root = vec![u32::MAX; nv];
    let mut count = 0u32;
    for v in 0..nv as u32 {
        let r = find(&mut parent, v) as usize;
        if of_root[r] == u32::MAX {
            of_root[r] = count;
            count += 1;
        }
        label[v as usize] = of_root[r];
    }
    (label, count as usize)
}

/// See [`enclosed_parts`].
pub const ENCLOSED_PARTS_MAX_COMPONENTS: usize = 64;
/// A part larger than this share of the mesh's area is a layer of its own (a body
/// inside its clothes), not a loose part: [`enclosed_parts`] leaves it out.
pub const ENCLOSED_PART_MAX_AREA_SHARE: f64 = 0.1;

/// The loose parts a mesh holds inside itself (a body model's eyeballs, teeth or
/// tongue): each connected component whose area-weighted centre lies inside the rest of
/// the mesh (generalised winding number over the other components' triangles above a
/// half), and at most [`ENCLOSED_PART_MAX_AREA_SHARE`] of the area. Each part is its
/// vertices, sorted. A camera never sees such a part from
/// outside, so no scan can say where it goes; it follows what surrounds it. A mesh in
/// more than [`ENCLOSED_PARTS_MAX_COMPONENTS`] pieces (a scan triangulated per pod) is
/// not searched: each piece costs a pass over every triangle.
pub fn enclosed_parts(v: &[crate::mesh::V3], tris: &[[u32; 3]]) -> Vec<Vec<u32>> {
    use crate::mesh::V3;
    use rayon::prelude::*;
    let (label, count) = components(v.len(), tris);
    if !(2..=ENCLOSED_PARTS_MAX_COMPONENTS).contains(&count) {
        return Vec::new();
    }
    let mut centre = vec![(V3::zeros(), 0.0); count];
    for t in tris {
        let [a, b, c] = t.map(|i| v[i as usize]);
        let area = (b - a).cross(&(c - a)).norm() / 2.0;
        let k = label[t[0] as usize] as usize;
        centre[k].0 += (a + b + c) / 3.0 * area;
        centre[k].1 += area;
    }
    // the solid angle of each other component's triangles seen from the centre
    // (Van Oosterom and Strackee), summed over 4 pi
    let winding = |k: usize, p: &V3| -> f64 {
        tris.par_iter()
            .filter(|t| label[t[0] as usize] as usize != k)
            .map(|t| {
                let [a, b, c] = t.map(|i| v[i as usize] - p);
                let (la, lb, lc) = (a.norm(), b.norm(), c.norm());
                let num = a.dot(&b.cross(&c));
                let den = la * lb * lc + a.dot(&b) * lc + b.dot(&c) * la + c.dot(&a) * lb;
                2.0 * num.atan2(den)
            })
            .sum::<f64>()
            / (4.0 * std::f64::consts::PI)
    };
    let total: f64 = centre.iter().map(|c| c.1).sum();
    let enclosed: Vec<bool> = (0..count)
        .map(|k| {
            let (sum, area) = centre[k];
            area > 0.0
                && area <= ENCLOSED_PART_MAX_AREA_SHARE * total
                && winding(k, &(sum / area)).abs() > 0.5
        })
        .collect();
    let mut parts = vec![Vec::new(); count];
    for (i, &l) in label.iter().enumerate() {
        if enclosed[l as usize] {
            parts[l as usize].push(i as u32);
        }
    }
    parts.retain(|p| !p.is_empty());
    parts
}

/// Bridges between the separate pieces of a fragmented mesh (a scan triangulated per
/// camera pod, a template with loose parts): each vertex is joined to its nearest vertex
/// of another component when that lies within `radius`. With them, springs and filling
/// reach across the gaps, so a piece without data or landmarks cannot drift or slide on
/// its own. Empty for a connected mesh.
pub fn bridges(v: &[crate::mesh::V3], tris: &[[u32; 3]], radius: f64) -> Vec<[u32; 2]> {
    use kiddo::{ImmutableKdTree, SquaredEuclidean};
    let (label, count) = components(v.len(), tris);
    if count < 2 || !(radius > 0.0) {
        return Vec::new();
    }
    let arr: Vec<[f64; 3]> = v.iter().map(|p| [p.x, p.y, p.z]).collect();
    let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);
    let mut out: Vec<[u32; 2]> = (0..v.len())
        .filter_map(|i| {
            tree.within_unsorted::<SquaredEuclidean>(&arr[i], radius * radius)
                .iter()
                .filter(|m| label[m.item as usize] != label[i])
                .min_by(|a, b| a.distance.total_cmp(&b.distance))
                .map(|m| {
                    let j = m.item as u32;
                    [(i as u32).min(j), (i as u32).max(j)]
                })
        })
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// Distances along the mesh's edges from the nearest of `sources` (multi-source
/// Dijkstra), and which source is nearest (its index in `sources`). Vertices no source
/// reaches stay at infinity with `u32::MAX`.
pub fn edge_distances(
    vertices: &[crate::mesh::V3],
    neighbours: &[Vec<u32>],
    sources: &[u32],
) -> (Vec<f64>, Vec<u32>) {
    edge_distances_while(vertices, neighbours, sources, |_, _| true)
}

/// `edge_distances`, expanding a vertex reached at distance `d` only while
/// `expand(vertex, d)`: distances are exact where every vertex before them on the
/// shortest path was expanded, upper bounds or infinity elsewhere.
pub fn edge_distances_while(
    vertices: &[crate::mesh::V3],
    neighbours: &[Vec<u32>],
    sources: &[u32],
    expand: impl Fn(usize, f64) -> bool,
) -> (Vec<f64>, Vec<u32>) {
    use std::cmp::Ordering;
    #[derive(PartialEq)]
    struct Item(f64, u32);
    impl Eq for Item {}
    impl Ord for Item {
        fn cmp(&self, o: &Self) -> Ordering {
            o.0.total_cmp(&self.0)
        }
    }
    impl PartialOrd for Item {
        fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
            Some(self.cmp(o))
        }
    }
    let n = vertices.len();
    let mut dist = vec![f64::INFINITY; n];
    let mut nearest = vec![u32::MAX; n];
    let mut heap = std::collections::BinaryHeap::new();
    for (k, &s) in sources.iter().enumerate() {
        dist[s as usize] = 0.0;
        nearest[s as usize] = k as u32;
        heap.push(Item(0.0, s));
    }
    while let Some(Item(d, i)) = heap.pop() {
        let i = i as usize;
        if d > dist[i] || !expand(i, d) {
            continue;
        }
        for &j in &neighbours[i] {
            let j = j as usize;
            let dj = d + (vertices[i] - vertices[j]).norm();
            if dj < dist[j] {
                dist[j] = dj;
                nearest[j] = nearest[i];
                heap.push(Item(dj, j as u32));
            }
        }
    }
    (dist, nearest)
}

/// A summary of a mesh's topology, as the CLI and tests report it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TopologyReport {
    pub vertices: usize,
    pub triangles: usize,
    pub components: usize,
    pub boundary_edges: usize,
    pub non_manifold_edges: usize,
    /// Edges whose two triangles traverse it in the same direction.
    pub inconsistent_edges: usize,
    pub degenerate_triangles: usize,
    /// vertices whose triangles do not form one fan (two cones touching at a point)
    pub non_manifold_vertices: usize,
    pub watertight: bool,
}

/// Checks a mesh: watertight means every edge has exactly two triangles that traverse it
/// in opposite directions, and no triangle is degenerate.
pub fn report(mesh: &Mesh) -> TopologyReport {
    let tris = &mesh.triangles;
    let mut directed: Vec<u64> = tris
        .iter()
        .flat_map(|t| (0..3).map(move |k| ((t[k] as u64) << 32) | t[(k + 1) % 3] as u64))
        .collect();
    directed.sort_unstable();
    let times = |a: u32, b: u32| {
        let k = ((a as u64) << 32) | b as u64;
        directed.partition_point(|&d| d <= k) - directed.partition_point(|&d| d < k)
    };
    let counts = edge_face_counts(tris);
    let boundary_edges = counts.iter().filter(|(_, c)| *c == 1).count();
    let non_manifold_edges = counts.iter().filter(|(_, c)| *c > 2).count();
    let inconsistent_edges = counts
        .iter()
        .filter(|([a, b], c)| *c == 2 && (times(*a, *b) != 1 || times(*b, *a) != 1))
        .count();
    let degenerate_triangles = degenerate_triangles(mesh);
    let (_, components) = components(mesh.vertices.len(), tris);
    let non_manifold_vertices = non_manifold_vertices(mesh.vertices.len(), tris);
    let report = TopologyReport {
        non_manifold_vertices,
        vertices: mesh.vertices.len(),
        triangles: tris.len(),
        components,
        boundary_edges,
        non_manifold_edges,
        inconsistent_edges,
        degenerate_triangles,
        watertight: false,
    };
    TopologyReport {
        watertight: report.closed_manifold() && degenerate_triangles == 0,
        ..report
    }
}

impl TopologyReport {
    /// The report of a mesh with the same triangles as the one this report is of, moved:
    /// only degeneracy depends on the positions (a conformed result is its template moved).
    pub fn moved(&self, mesh: &Mesh) -> TopologyReport {
        debug_assert_eq!(mesh.triangles.len(), self.triangles);
        let degenerate_triangles = degenerate_triangles(mesh);
        TopologyReport {
            degenerate_triangles,
            watertight: self.closed_manifold() && degenerate_triangles == 0,
            ..self.clone()
        }
    }

    /// Watertight but for degenerate triangles: a property of the triangles alone.
    fn closed_manifold(&self) -> bool {
        self.triangles > 0
            && self.boundary_edges == 0
            && self.non_manifold_edges == 0
            && self.inconsistent_edges == 0
            && self.non_manifold_vertices == 0
    }
}

/// Triangles with a repeated corner or no area.
fn degenerate_triangles(mesh: &Mesh) -> usize {
    mesh.triangles
        .iter()
        .enumerate()
        .filter(|(i, t)| {
            t[0] == t[1]
                || t[1] == t[2]
                || t[0] == t[2]
                || mesh.face_normal_scaled(*i).norm() == 0.0
        })
        .count()
}

/// Counts vertices whose link (the edges opposite them in their triangles) is not one
/// connected fan or cycle.
pub fn non_manifold_vertices(nv: usize, tris: &[[u32; 3]]) -> usize {
    let mut link: Vec<Vec<[u32; 2]>> = vec![Vec::new(); nv];
    for t in tris {
        for k in 0..3 {
            link[t[k] as usize].push([t[(k + 1) % 3], t[(k + 2) % 3]]);
        }
    }
    link.iter()
        .filter(|edges| {
            if edges.is_empty() {
                return false;
            }
            // the link's edges, followed through shared vertices, must reach all of them
            let mut seen = vec![false; edges.len()];
            let mut stack = vec![0usize];
            seen[0] = true;
            while let Some(e) = stack.pop() {
                for (j, f) in edges.iter().enumerate() {
                    if !seen[j]
                        && (f[0] == edges[e][0]
                            || f[0] == edges[e][1]
                            || f[1] == edges[e][0]
                            || f[1] == edges[e][1])
                    {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
            seen.iter().any(|s| !s)
        })
        .count()
}

/// The vertex nearest the centroid of `v` (where geodesic extremities are measured from)
/// and every vertex's distance along the edges from it.
pub fn centre_distances(v: &[crate::mesh::V3], neighbours: &[Vec<u32>]) -> (u32, Vec<f64>) {
    let c = v.iter().sum::<crate::mesh::V3>() / v.len().max(1) as f64;
    let centre = (0..v.len())
        .min_by(|&a, &b| (v[a] - c).norm().total_cmp(&(v[b] - c).norm()))
        .unwrap_or(0) as u32;
    (centre, edge_distances(v, neighbours, &[centre]).0)
}

/// The next farthest-point sample: the vertex farthest (finite, above 0) from every
/// sample so far, `nearest` holding each vertex's distance to the nearest of them.
pub fn farthest_sample(nearest: &[f64]) -> Option<usize> {
    (0..nearest.len())
        .filter(|&i| nearest[i].is_finite())
        .max_by(|&a, &b| nearest[a].total_cmp(&nearest[b]))
        .filter(|&i| nearest[i] > 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::V3;

    #[test]
    fn tetrahedron_is_watertight_and_open_one_is_not() {
        let v = vec![
            V3::new(0., 0., 0.),
            V3::new(1., 0., 0.),
            V3::new(0., 1., 0.),
            V3::new(0., 0., 1.),
        ];
        let closed = Mesh::new(v.clone(), vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]);
        assert!(report(&closed).watertight);
        let open = Mesh::new(v, vec![[0, 2, 1], [0, 1, 3], [0, 3, 2]]);
        let r = report(&open);
        assert!(!r.watertight);
        assert_eq!(r.boundary_edges, 3);
        assert_eq!(boundary_loops(&open.triangles).len(), 1);
        assert_eq!(boundary_loops(&open.triangles)[0].len(), 3);
        assert_eq!(vertex_neighbours(4, &open.triangles)[0], vec![1, 2, 3]);
        // two tetrahedra sharing only vertex 0: that vertex is not manifold
        let mut v2 = closed.vertices.clone();
        v2.extend([
            V3::new(-1., 0., 0.),
            V3::new(0., -1., 0.),
            V3::new(0., 0., -1.),
        ]);
        let mut t2 = closed.triangles.clone();
        t2.extend([[0, 4, 5], [0, 5, 6], [0, 6, 4], [4, 6, 5]]);
        let r = report(&Mesh::new(v2, t2));
        assert_eq!(r.non_manifold_vertices, 1);
        assert!(!r.watertight);
    }

    #[test]
    fn pruned_distances_give_the_same_farthest_point_update() {
        let m = crate::synth::icosphere(4);
        let nb = vertex_neighbours(m.vertices.len(), &m.triangles);
        let near = edge_distances(&m.vertices, &nb, &[0]).0;
        let far = (0..near.len())
            .max_by(|&a, &b| near[a].total_cmp(&near[b]))
            .unwrap();
        let full = edge_distances(&m.vertices, &nb, &[far as u32]).0;
        let (pruned, _) = edge_distances_while(&m.vertices, &nb, &[far as u32], |i, d| d < near[i]);
        let skipped = pruned.iter().filter(|d| d.is_infinite()).count();
        assert!(skipped > 0, "the pruning left out nothing");
        for i in 0..near.len() {
            assert_eq!(near[i].min(full[i]), near[i].min(pruned[i]), "vertex {i}");
        }
    }

    #[test]
    fn a_part_inside_the_mesh_is_found_and_one_beside_it_is_not() {
        let outer = crate::synth::icosphere(2);
        let small = crate::synth::icosphere(1);
        let mut m = outer.clone();
        // an eye: inside, its front poking out through the surface
        let eye = m.append(&small, |p| V3::new(0.85, 0.0, 0.0) + p * 0.2);
        // a part beside the sphere, outside it
        m.append(&small, |p| V3::new(3.0, 0.0, 0.0) + p * 0.5);
        let parts = enclosed_parts(&m.vertices, &m.triangles);
        let n = small.vertices.len() as u32;
        assert_eq!(parts, vec![(eye..eye + n).collect::<Vec<u32>>()]);
        assert!(enclosed_parts(&outer.vertices, &outer.triangles).is_empty());
        // a whole layer inside (a body inside its clothes) is not a loose part
        let mut layered = outer.clone();
        layered.append(&outer, |p| p * 0.9);
        assert!(enclosed_parts(&layered.vertices, &layered.triangles).is_empty());
    }
}
