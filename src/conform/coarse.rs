//! The coarse stage of the default method: a deformation graph (embedded deformation,
//! Sumner et al. 2007, with as-rigid-as-possible node rotations). A few hundred nodes
//! sampled over the template carry the deformation; every vertex follows the nodes near
//! it along the surface. A bent leg or a turned head then moves as a whole in a few
//! iterations, where per-vertex springs would pass the rotation on one ring at a time.

use super::correspond::{MatchLimits, ScanSurface};
use crate::mesh::{V3, vertex_normals};
use nalgebra::{Matrix3, UnitQuaternion};
use rayon::prelude::*;
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// Nodes, their graph, and each vertex's blend of nodes.
pub struct Graph {
    /// #N rest positions of the nodes
    pub rest: Vec<V3>,
    /// #N neighbour lists (nodes whose surface regions touch)
    pub edges: Vec<Vec<u32>>,
    /// #V lists of (node, weight), weights summing to 1
    pub blend: Vec<Vec<(u32, f64)>>,
}

/// Samples `count` nodes by farthest-point sampling and binds each vertex to up to four
/// nodes that are near along the surface (its own Voronoi cell's node and that node's
/// graph neighbours), so an arm is never bound to the torso beside it.
///
/// - `rest`: #V positions; `neighbours`: #V vertex neighbour lists
pub fn build(rest: &[V3], neighbours: &[Vec<u32>], count: usize) -> Graph {
    let n = rest.len();
    let count = count.max(4).min(n);
    // farthest-point sampling, Euclidean
    let mut nodes = vec![0usize];
    let mut dist: Vec<f64> = rest.iter().map(|p| (p - rest[0]).norm_squared()).collect();
    while nodes.len() < count {
        let (far, _) = dist
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap();
        nodes.push(far);
        for (d, p) in dist.iter_mut().zip(rest) {
            *d = d.min((p - rest[far]).norm_squared());
        }
    }
    // geodesic Voronoi cells: multi-source Dijkstra over mesh edges
    let mut owner = vec![u32::MAX; n];
    let mut gd = vec![f64::INFINITY; n];
    let mut heap = BinaryHeap::new();
    for (k, &v) in nodes.iter().enumerate() {
        gd[v] = 0.0;
        owner[v] = k as u32;
        heap.push(Reverse((Ordered(0.0), v)));
    }
    while let Some(Reverse((Ordered(d), v))) = heap.pop() {
        if d > gd[v] {
            continue;
        }
        for &u in &neighbours[v] {
            let u = u as usize;
            let nd = d + (rest[u] - rest[v]).norm();
            if nd < gd[u] {
                gd[u] = nd;
                owner[u] = owner[v];
                heap.push(Reverse((Ordered(nd), u)));
            }
        }
    }
    let mut edges: Vec<Vec<u32>> = vec![Vec::new(); count];
    for v in 0..n {
        for &u in &neighbours[v] {
            let (a, b) = (owner[v], owner[u as usize]);
            if a != b && a != u32::MAX && b != u32::MAX {
                edges[a as usize].push(b);
            }
        }
    }
    for e in &mut edges {
        e.sort_unstable();
        e.dedup();
    }
    let node_rest: Vec<V3> = nodes.iter().map(|&v| rest[v]).collect();
    let blend = (0..n)
        .into_par_iter()
        .map(|v| {
            let o = owner[v];
            if o == u32::MAX {
                return vec![];
            }
            let mut cand: Vec<(u32, f64)> = std::iter::once(o)
                .chain(edges[o as usize].iter().copied())
                .map(|k| (k, (rest[v] - node_rest[k as usize]).norm()))
                .collect();
            cand.sort_by(|a, b| a.1.total_cmp(&b.1));
            cand.truncate(5);
            let dmax = cand.last().map_or(1.0, |c| c.1).max(1e-12);
            let mut w: Vec<(u32, f64)> = cand[..cand.len().min(4)]
                .iter()
                .map(|&(k, d)| (k, (1.0 - d / dmax).powi(2).max(1e-6)))
                .collect();
            let s: f64 = w.iter().map(|x| x.1).sum();
            for x in &mut w {
                x.1 /= s;
            }
            w
        })
        .collect();
    Graph {
        rest: node_rest,
        edges,
        blend,
    }
}

/// A distance ordered by `total_cmp`, for the Dijkstra heap.
#[derive(Clone, Copy)]
struct Ordered(f64);
impl PartialEq for Ordered {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o).is_eq()
    }
}
impl Eq for Ordered {}
impl PartialOrd for Ordered {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Ordered {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&o.0)
    }
}

/// State of the graph: node positions and rotations.
pub struct Deformation {
    pub pos: Vec<V3>,
    pub rot: Vec<UnitQuaternion<f64>>,
}

impl Graph {
    /// Vertex positions under a deformation: `x_v = sum_k w_vk (p_k + R_k (r_v - r_k))`.
    pub fn apply(&self, d: &Deformation, rest: &[V3]) -> Vec<V3> {
        let rm: Vec<Matrix3<f64>> = d
            .rot
            .iter()
            .map(|q| *q.to_rotation_matrix().matrix())
            .collect();
        (0..rest.len())
            .into_par_iter()
            .map(|v| {
                self.blend[v]
                    .iter()
                    .map(|&(k, w)| {
                        (d.pos[k as usize] + rm[k as usize] * (rest[v] - self.rest[k as usize])) * w
                    })
                    .sum()
            })
            .collect()
    }
}

/// Settings of the coarse stage, taken from the conformation options.
pub struct CoarseSettings {
    pub iterations: usize,
    pub epsilon_start: f64,
    pub epsilon_end: f64,
    pub max_distance_start: f64,
    pub max_distance_end: f64,
    pub min_normal_cos: f64,
    pub point_to_point: f64,
    /// weight of the scan-to-template pulls against the template-to-scan matches
    pub scan_to_template: f64,
}

/// Runs the coarse stage from vertex positions `x0` (the global mapping) and returns
/// the deformed vertex positions and per-vertex rotations (blended from the nodes) to
/// seed the fine stage.
///
/// - `rest`: #V spring rest positions; `tris`: #F triangles
/// - `landmarks`: #V (weight, target) pairs, weight 0 where a vertex has none
#[allow(clippy::too_many_arguments)]
pub fn run(
    graph: &Graph,
    rest: &[V3],
    x0: &[V3],
    tris: &[[u32; 3]],
    scan: &ScanSurface,
    diag: f64,
    landmark_weight: &[f64],
    landmark_target: &[V3],
    s: &CoarseSettings,
) -> (Vec<V3>, Vec<UnitQuaternion<f64>>) {
    let nn = graph.rest.len();
    let n = rest.len();
    let mut def = start(graph, rest, x0);
    let mut x = graph.apply(&def, rest);
    let mut system = NodeSystem::new(graph);
    for it in 0..s.iterations {
        let f = if s.iterations > 1 {
            it as f64 / (s.iterations - 1) as f64
        } else {
            1.0
        };
        let eps = s.epsilon_start * (s.epsilon_end / s.epsilon_start).powf(f);
        let lim = MatchLimits {
            max_distance: s.max_distance_start
                * (s.max_distance_end / s.max_distance_start).powf(f)
                * diag,
            min_normal_cos: s.min_normal_cos,
        };
        // two samples a node: more samples per matching were measured to help less than
        // more matchings for the same time (articulated, no landmarks: 4,000 samples x 30
        // iterations 0.90%, 600 x 90 0.71%; posed pig 0.52% -> 0.39%)
        let stride = (n / (2 * nn)).max(1);
        let terms = data_terms(
            scan,
            &x,
            tris,
            stride,
            &lim,
            (landmark_weight, landmark_target),
            s,
        );
        let sampled = n.div_ceil(stride);
        let springs = Springs {
            graph,
            eps,
            per_node: sampled as f64 / nn as f64,
        };
        // Global step: node positions with rotations fixed. Each vertex is linear in the
        // node positions, x_v = sum_k w_vk p_k + c_v(R), so the system matrix does not
        // depend on the rotations: one factorisation serves every local-global round.
        springs.assemble(&mut system, &terms);
        let Some(ch) = system.factor() else {
            continue;
        };
        // one local-global round per matching: more rounds on the same matches were
        // measured to change nothing (0.900% -> 0.906% on the articulated case)
        let b = springs.right_hand_sides(&def, rest, &terms);
        let sol = b.map(|rhs| ch.solve(&rhs));
        for (k, p) in def.pos.iter_mut().enumerate() {
            *p = V3::new(sol[0][k], sol[1][k], sol[2][k]);
        }
        fit_node_rotations(graph, &mut def);
        x = graph.apply(&def, rest);
    }
    (x, vertex_rotations(graph, &def, n))
}

/// The start: each node where the global mapping `x0` put its vertices, rotations
/// fitted.
fn start(graph: &Graph, rest: &[V3], x0: &[V3]) -> Deformation {
    let nn = graph.rest.len();
    let mut def = Deformation {
        pos: vec![V3::zeros(); nn],
        rot: vec![UnitQuaternion::identity(); nn],
    };
    let mut acc = vec![(V3::zeros(), 0.0); nn];
    for v in 0..rest.len() {
        for &(k, w) in &graph.blend[v] {
            acc[k as usize].0 += (x0[v] - rest[v] + graph.rest[k as usize]) * w;
            acc[k as usize].1 += w;
        }
    }
    for (k, (p, w)) in acc.into_iter().enumerate() {
        def.pos[k] = if w > 0.0 { p / w } else { graph.rest[k] };
    }
    fit_node_rotations(graph, &mut def);
    def
}

/// The data terms of one matching, (vertex, weight, target): every `stride`-th vertex
/// matched onto the scan, the landmarks, and scan samples pulling their nearest
/// compatible vertex (data a part has moved away from, a lifted leg, still reaches
/// that part this way).
fn data_terms(
    scan: &ScanSurface,
    x: &[V3],
    tris: &[[u32; 3]],
    stride: usize,
    lim: &MatchLimits,
    (landmark_weight, landmark_target): (&[f64], &[V3]),
    s: &CoarseSettings,
) -> Vec<(usize, f64, V3)> {
    let n = x.len();
    let normals = vertex_normals(x, tris);
    let matches: Vec<_> = (0..n)
        .into_par_iter()
        .map(|v| {
            if v % stride == 0 {
                scan.query(&x[v], &normals[v], lim)
            } else {
                None
            }
        })
        .collect();
    let sampled = n.div_ceil(stride);
    let mut terms: Vec<(usize, f64, V3)> = Vec::new();
    for v in 0..n {
        if let Some(m) = &matches[v] {
            let foot = x[v] - m.normal * m.normal.dot(&(x[v] - m.point));
            terms.push((
                v,
                m.weight,
                foot * (1.0 - s.point_to_point) + m.point * s.point_to_point,
            ));
        }
        if landmark_weight[v] > 0.0 {
            terms.push((v, landmark_weight[v], landmark_target[v]));
        }
    }
    if s.scan_to_template > 0.0 {
        let pulls = scan.pulls(x, &normals, sampled, lim);
        let w = s.scan_to_template * (sampled as f64 / pulls.len().max(1) as f64).min(4.0);
        for (v, p, sn) in pulls {
            let foot = x[v] - sn * sn.dot(&(x[v] - p));
            terms.push((v, w, foot * (1.0 - s.point_to_point) + p * s.point_to_point));
        }
    }
    terms
}

/// The graph's springs at one matching: sum over node edges
/// |p_i - p_j - (R_i + R_j)/2 (r_i - r_j)|^2, scaled per node by the vertices it carries
/// (`per_node` samples a node) so epsilon keeps its meaning.
struct Springs<'a> {
    graph: &'a Graph,
    eps: f64,
    per_node: f64,
}

impl Springs<'_> {
    fn weight(&self, i: usize) -> f64 {
        self.eps * self.per_node / self.graph.edges[i].len() as f64
    }

    /// The system matrix of the data `terms` and the springs.
    fn assemble(&self, system: &mut NodeSystem, terms: &[(usize, f64, V3)]) {
        let graph = self.graph;
        system.clear();
        for &(v, weight, _) in terms {
            let bl = &graph.blend[v];
            for &(i, wi) in bl {
                for &(j, wj) in bl {
                    system.add(i as usize, j as usize, weight * wi * wj);
                }
            }
        }
        for i in 0..graph.rest.len() {
            for &j in &graph.edges[i] {
                let (j, w) = (j as usize, self.weight(i));
                system.add(i, i, w);
                system.add(j, j, w);
                system.add(i, j, -w);
                system.add(j, i, -w);
            }
            // keep the system definite where a node has no data at all
            system.add(i, i, 1e-6 * self.per_node);
        }
    }

    /// One right-hand side per coordinate, the nodes' rotations in `def` held.
    fn right_hand_sides(
        &self,
        def: &Deformation,
        rest: &[V3],
        terms: &[(usize, f64, V3)],
    ) -> [Vec<f64>; 3] {
        let graph = self.graph;
        let nn = graph.rest.len();
        let rm: Vec<Matrix3<f64>> = def
            .rot
            .iter()
            .map(|q| *q.to_rotation_matrix().matrix())
            .collect();
        let mut b = [vec![0.0; nn], vec![0.0; nn], vec![0.0; nn]];
        for &(v, weight, target) in terms {
            let bl = &graph.blend[v];
            let c: V3 = bl
                .iter()
                .map(|&(k, w)| rm[k as usize] * (rest[v] - graph.rest[k as usize]) * w)
                .sum();
            for &(i, wi) in bl {
                for d in 0..3 {
                    b[d][i as usize] += weight * wi * (target[d] - c[d]);
                }
            }
        }
        for i in 0..nn {
            for &j in &graph.edges[i] {
                let (j, w) = (j as usize, self.weight(i));
                let e = (rm[i] + rm[j]) * (graph.rest[i] - graph.rest[j]) * 0.5;
                for d in 0..3 {
                    b[d][i] += w * e[d];
                    b[d][j] -= w * e[d];
                }
            }
            for (bd, p) in b.iter_mut().zip(def.pos[i].iter()) {
                bd[i] += 1e-6 * self.per_node * p;
            }
        }
        b
    }
}

/// Each vertex's rotation, blended from its nodes' (to seed the fine stage).
fn vertex_rotations(graph: &Graph, def: &Deformation, n: usize) -> Vec<UnitQuaternion<f64>> {
    (0..n)
        .map(|v| {
            let m: Matrix3<f64> = graph.blend[v]
                .iter()
                .map(|&(k, w)| def.rot[k as usize].to_rotation_matrix().matrix() * w)
                .sum();
            super::solve::polar_rotation(
                &m,
                graph.blend[v]
                    .first()
                    .map_or(UnitQuaternion::identity(), |b| def.rot[b.0 as usize]),
            )
        })
        .collect()
}

/// The coarse stage's normal equations over the nodes: sparse (a node couples only with
/// its graph neighbours and the nodes it shares a vertex with), their pattern fixed for
/// the whole stage, so the fill-reducing order and the symbolic factorisation are found
/// once and every matching refactors the values only.
struct NodeSystem {
    matrix: sprs::CsMat<f64>,
    factor: Option<sprs_ldl::LdlNumeric<f64, usize>>,
}

impl NodeSystem {
    fn new(graph: &Graph) -> Self {
        let nn = graph.rest.len();
        let mut pattern: Vec<std::collections::BTreeSet<usize>> = (0..nn)
            .map(|i| std::collections::BTreeSet::from([i]))
            .collect();
        for (i, e) in graph.edges.iter().enumerate() {
            for &j in e {
                pattern[i].insert(j as usize);
                pattern[j as usize].insert(i);
            }
        }
        for bl in &graph.blend {
            for &(i, _) in bl {
                for &(j, _) in bl {
                    pattern[i as usize].insert(j as usize);
                }
            }
        }
        let mut indptr = vec![0];
        let mut indices = Vec::new();
        for row in &pattern {
            indices.extend(row.iter().copied());
            indptr.push(indices.len());
        }
        let data = vec![0.0; indices.len()];
        NodeSystem {
            matrix: sprs::CsMat::new((nn, nn), indptr, indices, data),
            factor: None,
        }
    }

    fn clear(&mut self) {
        self.matrix.data_mut().iter_mut().for_each(|x| *x = 0.0);
    }

    /// Adds `w` at (`i`, `j`), which the pattern holds.
    fn add(&mut self, i: usize, j: usize, w: f64) {
        if let Some(x) = self.matrix.get_mut(i, j) {
            *x += w;
        }
    }

    /// The factorisation of the values added since [`NodeSystem::clear`], or `None`
    /// when it fails.
    fn factor(&mut self) -> Option<&sprs_ldl::LdlNumeric<f64, usize>> {
        let ok = match &mut self.factor {
            Some(f) => f.update(self.matrix.view()).is_ok(),
            None => {
                self.factor = sprs_ldl::Ldl::new()
                    .check_symmetry(sprs::SymmetryCheck::DontCheckSymmetry)
                    .numeric(self.matrix.view())
                    .ok();
                self.factor.is_some()
            }
        };
        let f = self.factor.as_ref().filter(|_| ok)?;
        // a zero or negative pivot: the system is not definite
        f.d().iter().all(|&d| d > 0.0).then_some(f)
    }
}

/// Local step on the graph: each node's rotation best maps its rest edges to the current
/// ones.
fn fit_node_rotations(graph: &Graph, def: &mut Deformation) {
    let pos = &def.pos;
    let rots: Vec<UnitQuaternion<f64>> = (0..pos.len())
        .into_par_iter()
        .map(|i| {
            let mut a = Matrix3::zeros();
            for &j in &graph.edges[i] {
                let j = j as usize;
                a += (pos[i] - pos[j]) * (graph.rest[i] - graph.rest[j]).transpose();
            }
            super::solve::polar_rotation(&a, def.rot[i])
        })
        .collect();
    def.rot = rots;
}
