//! `conformd reconstruct`: a capture set reconstructed into a fused scan, scored against a truth when given.

use crate::cli::args::ReconstructArgs;
use conformd::commands;

pub fn run(a: ReconstructArgs) -> Result<(), commands::CommandError> {
    let ReconstructArgs {
        capture,
        rig,
        calibration,
        out,
        report,
        mesh,
        truth,
        truth_scale,
        truth_pod,
    } = a;
    let mut station = conformd::stereo::rig::Reconstruction::load(&rig, calibration.as_deref())?;
    let truth = truth.as_deref().map(|file| commands::ScanTruth {
        file,
        scale: truth_scale,
        pod: truth_pod.as_deref(),
    });
    let (r, score) =
        commands::reconstruct_scored(&mut station, &capture, &out, report.as_deref(), mesh, truth)?;
    println!("{r}\nwrote {}", out.display());
    if let Some(score) = score {
        println!("{score}");
    }
    Ok(())
}
