//! Shape model and preview speed (issue 3's targets): building a model over 100 meshes of
//! 20,000 vertices, scoring one mesh, rendering an 800x600 preview. The meshes are posed
//! and reshaped pig templates with noise: the same topology and size as conformed meshes,
//! which is all the model sees. Run: `cargo bench --bench model`.

use conformd::model::{BuildOptions, ShapeModel};
use conformd::render::{Colouring, RenderOptions, render};
use conformd::template::{self as templates, Kind};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;
use std::time::Instant;

fn median(mut t: Vec<f64>) -> f64 {
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn main() {
    let fig = templates::build(Kind::Pig, 20_000);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let samples: Vec<(String, conformd::mesh::Mesh)> = (0..100)
        .map(|i| {
            let mut pose = BTreeMap::new();
            for (p, r) in [
                ("swing", 20.0),
                ("nod", 14.0),
                ("twist", 8.0),
                ("head_turn", 10.0),
            ] {
                pose.insert(p.to_string(), rng.random_range(-r..r));
            }
            let mut shape = BTreeMap::new();
            shape.insert("length".to_string(), rng.random_range(0.9..1.1));
            shape.insert("girth".to_string(), rng.random_range(0.9..1.1));
            let m = templates::subject(&fig, Kind::Pig, &shape, &templates::pose(Kind::Pig, &pose))
                .unwrap();
            (format!("s{i}"), m)
        })
        .collect();
    println!(
        "conformd model benchmark ({} threads), {} meshes of {} vertices",
        rayon::current_num_threads(),
        samples.len(),
        fig.mesh.vertices.len()
    );
    let build: Vec<f64> = (0..3)
        .map(|_| {
            let t = Instant::now();
            let m = ShapeModel::build(&samples, &BuildOptions::default()).unwrap();
            std::hint::black_box(m);
            t.elapsed().as_secs_f64()
        })
        .collect();
    let b = median(build);
    println!(
        "model build (Procrustes + PCA, 30 modes kept): median {b:.3} s (target 2 s: {})",
        if b <= 2.0 { "met" } else { "MISSED" }
    );
    let model = ShapeModel::build(&samples, &BuildOptions::default()).unwrap();
    let score: Vec<f64> = (0..50)
        .map(|i| {
            let t = Instant::now();
            std::hint::black_box(model.score("x", &samples[i % 100].1).unwrap());
            t.elapsed().as_secs_f64()
        })
        .collect();
    let s = median(score) * 1000.0;
    println!(
        "score one mesh: median {s:.2} ms (target 10 ms: {})",
        if s <= 10.0 { "met" } else { "MISSED" }
    );
    let opts = RenderOptions {
        width: 800,
        height: 600,
        ..Default::default()
    };
    let render_t: Vec<f64> = (0..10)
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(render(&samples[0].1, &Colouring::Plain, &opts));
            t.elapsed().as_secs_f64()
        })
        .collect();
    let r = median(render_t) * 1000.0;
    println!(
        "800x600 preview, two views, {} triangles: median {r:.1} ms (target 200 ms: {})",
        fig.mesh.triangles.len(),
        if r <= 200.0 { "met" } else { "MISSED" }
    );
}
