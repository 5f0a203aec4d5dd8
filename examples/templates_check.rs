use conformd::synth::templates::{self, Kind};
fn main() {
    for kind in [Kind::Pig, Kind::Body] { for n in [5000usize, 50000] {
        let t = std::time::Instant::now();
        let f = templates::build(kind, n);
        let r = conformd::mesh::topology::report(&f.mesh);
        let tiny = (0..f.mesh.triangles.len()).filter(|&t| { let a = f.mesh.face_normal_scaled(t).norm()*0.5; a < 1e-10 }).count();
        let minang = (0..f.mesh.triangles.len()).map(|t| { let [a,b,c] = f.mesh.corners(t); let ang = |o: nalgebra::Vector3<f64>, p: nalgebra::Vector3<f64>, q: nalgebra::Vector3<f64>| (p-o).angle(&(q-o)); ang(a,b,c).min(ang(b,c,a)).min(ang(c,a,b)).to_degrees() }).fold(180.0, f64::min);
        println!("{kind:?} {n}: {:.2}s {:?} tiny {tiny} min angle {minang:.2} groups {:?} landmarks {}", t.elapsed().as_secs_f64(), r, f.mesh.groups.keys().collect::<Vec<_>>(), f.landmarks().len());
    }}
}
