//! Synthetic shapes with ground truth, for tests, benchmarks and the demo: simple solids
//! (icosphere, tessellated box), an articulated figure built from a skeleton and posed
//! with the vertex order unchanged, and a virtual scanner that sees a mesh from a few
//! viewpoints (occluded triangles removed) and resamples it as a noisy point cloud.

pub mod cases;
pub mod scanner;
pub mod trigger_box;
pub mod v4l2_driver;
pub mod virtual_rig;

use crate::mesh::{Mesh, V3};
use std::collections::HashMap;

/// A unit icosphere: the icosahedron subdivided `level` times, projected to the sphere.
/// Vertices: 10 * 4^level + 2.
pub fn icosphere(level: u32) -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut v: Vec<V3> = [
        (-1., t, 0.),
        (1., t, 0.),
        (-1., -t, 0.),
        (1., -t, 0.),
        (0., -1., t),
        (0., 1., t),
        (0., -1., -t),
        (0., 1., -t),
        (t, 0., -1.),
        (t, 0., 1.),
        (-t, 0., -1.),
        (-t, 0., 1.),
    ]
    .iter()
    .map(|&(x, y, z)| V3::new(x, y, z).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut nf = Vec::with_capacity(f.len() * 4);
        let mut midpoint = |a: u32, b: u32, v: &mut Vec<V3>| -> u32 {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a as usize] + v[b as usize]) * 0.5).normalize());
                (v.len() - 1) as u32
            })
        };
        for [a, b, c] in f {
            let ab = midpoint(a, b, &mut v);
            let bc = midpoint(b, c, &mut v);
            let ca = midpoint(c, a, &mut v);
            nf.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = nf;
    }
    Mesh::new(v, f)
}

/// A closed box centred at the origin with sides `size`, each face a grid of
/// `n x n` squares split into triangles, outward-facing, watertight.
pub fn tessellated_box(size: V3, n: usize) -> Mesh {
    let n = n.max(1);
    let mut index: HashMap<[i64; 3], u32> = HashMap::new();
    let mut mesh = Mesh::default();
    // grid coordinates in [-n, n] (step 2) keep shared edge vertices exact
    let mut vid = |g: [i64; 3], mesh: &mut Mesh| -> u32 {
        *index.entry(g).or_insert_with(|| {
            mesh.vertices.push(V3::new(
                g[0] as f64 / n as f64 * size.x / 2.0,
                g[1] as f64 / n as f64 * size.y / 2.0,
                g[2] as f64 / n as f64 * size.z / 2.0,
            ));
            (mesh.vertices.len() - 1) as u32
        })
    };
    let ni = n as i64;
    for axis in 0..3 {
        for side in [-1i64, 1] {
            let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
            for i in 0..ni {
                for j in 0..ni {
                    let corner = |di: i64, dj: i64| {
                        let mut g = [0i64; 3];
                        g[axis] = side * ni;
                        g[u] = -ni + 2 * (i + di);
                        g[w] = -ni + 2 * (j + dj);
                        g
                    };
                    let q = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)]
                        .map(|g| vid(g, &mut mesh));
                    // u x w = axis direction: counter-clockwise seen from +axis
                    if side > 0 {
                        mesh.triangles
                            .extend([[q[0], q[1], q[2]], [q[0], q[2], q[3]]]);
                    } else {
                        mesh.triangles
                            .extend([[q[0], q[2], q[1]], [q[0], q[3], q[2]]]);
                    }
                }
            }
        }
    }
    mesh
}

/// Distance from `p` to the surface of an axis-aligned box centred at the origin.
pub fn distance_to_box_surface(p: &V3, size: &V3) -> f64 {
    let h = size / 2.0;
    let q = p.abs() - h;
    let outside = q.sup(&V3::zeros()).norm();
    let inside = q.max().min(0.0);
    (outside + inside).abs()
}
