use conformd::conform::{ConformOptions, Method, conform};
use conformd::synth::cases;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let which = args.get(1).map(String::as_str).unwrap_or("art");
    let nv: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(6000);
    let t = std::time::Instant::now();
    let case = match which {
        "cube" => cases::sphere_to_cube(4),
        "box" => cases::sphere_to_box_with_missing(nv as u32),
        "turned" => cases::articulated(&cases::ArticulatedSpec { template_vertices: nv, turned: true, ..Default::default() }),
        _ => cases::articulated(&cases::ArticulatedSpec { template_vertices: nv, ..Default::default() }),
    };
    eprintln!("case built in {:.2}s: template {} v, scan {} pts, holes {}", t.elapsed().as_secs_f64(), case.template.vertices.len(), case.scan.vertices.len(), case.in_hole.iter().filter(|h| **h).count());
    if let (Some(truth), "turned") = (&case.truth, which) {
        use conformd::mesh::transform::fit_similarity;
        let diag = conformd::mesh::Mesh::new(truth.clone(), vec![]).diagonal();
        let surf = conformd::conform::correspond::ScanSurface::new(&case.scan).unwrap();
        let t = std::time::Instant::now();
        let (sim, rep) = conformd::conform::align::auto_align(&case.template.vertices, &surf, &Default::default());
        let e: f64 = case.template.vertices.iter().zip(truth).map(|(p, q)| (sim.apply(p) - q).norm()).sum::<f64>() / truth.len() as f64 / diag;
        let best = fit_similarity(&case.template.vertices, truth, None, true);
        let eb: f64 = case.template.vertices.iter().zip(truth).map(|(p, q)| (best.apply(p) - q).norm()).sum::<f64>() / truth.len() as f64 / diag;
        println!("ALIGN {:.3}s err {:.3}% (best similarity {:.3}%) rot diff {:.2}deg {:?}", t.elapsed().as_secs_f64(), e*100., eb*100., (sim.rotation.inverse()*best.rotation).angle().to_degrees(), rep);
    }
    for method in [Method::Paper, Method::Default] {
        let mut opts = if method == Method::Paper { ConformOptions::paper() } else { ConformOptions::default() };
        for kv in args.iter().skip(3) {
            let (k, v) = kv.split_once('=').unwrap();
            let mut t: toml::Table = toml::from_str(&toml::to_string(&opts).unwrap()).unwrap();
            t.insert(k.into(), toml::from_str::<toml::Table>(&format!("x = {v}")).unwrap()["x"].clone());
            opts = t.try_into().unwrap();
        }
        let lm = (which != "turned").then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
        let r = conform(&case.template, &case.scan, lm, &opts, &mut |_| {}).unwrap();
        let rep = &r.report;
        println!("== {:?}: {} its, converged {}, {:.3}s (coarse {:.3} corr {:.3} rot {:.3} solve {:.3} global {:.3})", method, rep.iterations.len(), rep.converged, rep.seconds.total, rep.seconds.coarse, rep.seconds.correspond, rep.seconds.rotations, rep.seconds.solve, rep.seconds.global);
        for it in &rep.iterations { println!("  it {:2} eps {:6.2} lenstd {:.3} angstd {:.3} areastd {:.3} matched {} filled {} dist {:.5} upd {:.5} cg {}", it.iteration, it.epsilon, it.variation.edge_length.std, it.variation.angle.std, it.variation.area.std, it.matched, it.filled, it.mean_distance_relative, it.max_update_relative, it.solver_iterations); }
        println!("  folded {} watertight {} mean dist rel {:.5}", rep.folded_triangles, rep.watertight_result, rep.mean_distance_relative);
        if let Some(truth) = &case.truth {
            let e = cases::correspondence_error(&r.mesh.vertices, truth, &case.in_hole, &case.template.triangles);
            let diag = conformd::mesh::Mesh::new(truth.clone(), vec![]).diagonal();
            for g in ["legs", "feet"] { for side in [1.0f64, -1.0] { let vs: Vec<u32> = case.template.groups[g].iter().copied().filter(|&v| case.template.vertices[v as usize].y * side > 0.0).collect(); let m: f64 = vs.iter().map(|&v| (r.mesh.vertices[v as usize] - truth[v as usize]).norm()).sum::<f64>() / vs.len() as f64 / diag; let mt: f64 = vs.iter().map(|&v| { let p = r.mesh.vertices[v as usize]; vs.iter().map(|&u| (truth[u as usize]-p).norm()).fold(f64::INFINITY, f64::min) }).sum::<f64>() / vs.len() as f64 / diag; print!("{g}{}:{:.2}%(surf {:.2}%) ", if side>0.0 {"L"} else {"R"}, m*100., mt*100.); } } println!();
            for (g, vs) in &case.template.groups { let m: f64 = vs.iter().map(|&v| (r.mesh.vertices[v as usize] - truth[v as usize]).norm()).sum::<f64>() / vs.len() as f64 / diag; print!("{g}:{:.3}% ", m*100.); } println!();
            if std::env::var("HEADDBG").is_ok() { let mut bins = vec![(0.0,0usize);12]; for &v in &case.template.groups["head"] { let z = case.template.vertices[v as usize].z; let b = (((z-1.40)/0.04) as isize).clamp(0,11) as usize; bins[b].0 += (r.mesh.vertices[v as usize]-truth[v as usize]).norm()/diag; bins[b].1+=1; } for (i,(s,c)) in bins.iter().enumerate() { if *c>0 { println!("    z {:.2} n {} err {:.3}%", 1.40+0.04*i as f64, c, s/ *c as f64*100.); } } }
            if std::env::var("HEADDBG").is_ok() { for (tl, sl) in case.template_landmarks.iter().zip(&case.scan_landmarks) { if let (conformd::mesh::LandmarkPos::Vertex(v), conformd::mesh::LandmarkPos::Point(p)) = (tl.pos, sl.pos) { println!("    lm {} res {:.3}% truth-vs-scanlm {:.3}%", tl.name, (r.mesh.vertices[v as usize]-p).norm()/diag*100., (truth[v as usize]-p).norm()/diag*100.); } } }
            if std::env::var("HEADDBG").is_ok() { let tn = conformd::mesh::vertex_normals(truth, &case.template.triangles); let (mut nsum, mut tsum, mut vsum) = (0.0, 0.0, nalgebra::Vector3::zeros()); let hv = &case.template.groups["head"]; for &v in hv { let e = r.mesh.vertices[v as usize]-truth[v as usize]; let n = tn[v as usize]; nsum += e.dot(&n).abs(); tsum += (e - n*e.dot(&n)).norm(); vsum += e; } let k = hv.len() as f64; println!("    head normal {:.3}% tangential {:.3}% mean vec {:?}", nsum/k/diag*100., tsum/k/diag*100., (vsum/k/diag*100.).as_slice()); }
            if std::env::var("HEADDBG").is_ok() { use conformd::mesh::transform::fit_similarity; let hv: Vec<usize> = case.template.groups["head"].iter().map(|&v| v as usize).filter(|&v| case.template.vertices[v].z > 1.6).collect(); let rest: Vec<_> = hv.iter().map(|&v| case.template.vertices[v]).collect(); let res: Vec<_> = hv.iter().map(|&v| r.mesh.vertices[v]).collect(); let tr: Vec<_> = hv.iter().map(|&v| truth[v]).collect(); let a = fit_similarity(&rest, &res, None, true); let b = fit_similarity(&rest, &tr, None, true); let d = b.rotation.inverse() * a.rotation; println!("    head rot result {:.2}deg truth {:.2}deg diff {:.2}deg axis {:?} scale res {:.4} truth {:.4}", a.rotation.angle().to_degrees(), b.rotation.angle().to_degrees(), d.angle().to_degrees(), d.axis().map(|x| x.into_inner()), a.scale, b.scale); let ra: Vec<_> = rest.iter().map(|p| a.apply(p)).collect(); let rigid_res: f64 = ra.iter().zip(&res).map(|(p,q)| (p-q).norm()).sum::<f64>()/ra.len() as f64/diag; let rb: Vec<_> = rest.iter().map(|p| b.apply(p)).collect(); let rigid_tr: f64 = rb.iter().zip(&tr).map(|(p,q)| (p-q).norm()).sum::<f64>()/rb.len() as f64/diag; println!("    non-rigid part: result {:.3}% truth {:.3}%", rigid_res*100., rigid_tr*100.); }
            println!("  CORR mean {:.4}% holes {:.4}% p95 {:.4}% max {:.3}% flipped {}", e.mean*100., e.mean_in_holes*100., e.p95*100., e.max*100., e.flipped);
        }
        if which == "box" {
            let size = nalgebra::Vector3::from(cases::BOX_SIZE);
            let diag = size.norm();
            let d: Vec<f64> = r.mesh.vertices.iter().map(|p| conformd::synth::distance_to_box_surface(p, &size) / diag).collect();
            let missing: Vec<f64> = r.mesh.vertices.iter().zip(&d).filter(|(p, _)| { let q = nearest_on_box(p, &size); cases::in_box_hole(&q) }).map(|(_, d)| *d).collect();
            if std::env::var("BOXDBG").is_ok() { for (p, dd) in r.mesh.vertices.iter().zip(&d) { if *dd > 0.02 { println!("    bad {:.3} {:.3} {:.3} d {:.3}%", p.x, p.y, p.z, dd*100.); } } }
            let mut m2 = missing.clone(); m2.sort_by(f64::total_cmp);
            println!("  BOX missing p50 {:.3}% p90 {:.3}% p99 {:.3}% over2% {}", m2[m2.len()/2]*100., m2[m2.len()*9/10]*100., m2[m2.len()*99/100]*100., m2.iter().filter(|x| **x > 0.02).count());
            println!("  BOX all max {:.4}% missing n={} mean {:.4}% max {:.4}%", d.iter().cloned().fold(0.0, f64::max)*100., missing.len(), missing.iter().sum::<f64>()/missing.len().max(1) as f64*100., missing.iter().cloned().fold(0.0, f64::max)*100.);
        }
        if which == "cube" {
            let size = nalgebra::Vector3::new(2.0, 2.0, 2.0);
            let d: Vec<f64> = r.mesh.vertices.iter().map(|p| conformd::synth::distance_to_box_surface(p, &size)).collect();
            println!("  CUBE mean dist {:.4}% of edge, max {:.4}%", d.iter().sum::<f64>()/d.len() as f64/2.0*100., d.iter().cloned().fold(0.0, f64::max)/2.0*100.);
        }
    }
}
fn nearest_on_box(p: &nalgebra::Vector3<f64>, size: &nalgebra::Vector3<f64>) -> nalgebra::Vector3<f64> {
    let h = size / 2.0;
    let mut q = p.zip_map(&h, |a, b| a.clamp(-b, b));
    // push to the nearest face
    let gaps = [h.x - q.x.abs(), h.y - q.y.abs(), h.z - q.z.abs()];
    let k = (0..3).min_by(|&a, &b| gaps[a].total_cmp(&gaps[b])).unwrap();
    q[k] = h[k].copysign(q[k]);
    q
}
