use conformd::conform::{ConformOptions, conform};
use conformd::synth::cases::{self, ArticulatedSpec};
fn main() {
    let case = cases::articulated(&ArticulatedSpec {
        template_vertices: 11000,
        scan_points: 100000,
        turned: false,
        ..Default::default()
    });
    let opts = ConformOptions::default();
    let lm = Some((&case.template_landmarks[..], &case.scan_landmarks[..]));
    let t = std::time::Instant::now();
    for _ in 0..10 {
        let _ = conform(&case.template, &case.scan, lm, &opts, &mut |_| {}).unwrap();
    }
    println!("{:.3}", t.elapsed().as_secs_f64() / 10.0);
}
