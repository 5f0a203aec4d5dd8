//! `conformd import-pair`: a recorded rectified pair made into a rig file, a calibration and a capture set.

use crate::cli::args::ImportPairArgs;
use conformd::commands;

pub fn run(a: ImportPairArgs) -> Result<(), commands::CommandError> {
    let ImportPairArgs {
        left,
        right,
        calib,
        truth,
        num_disparities,
        out,
    } = a;
    let p = commands::import_pair(
        &left,
        &right,
        &calib,
        truth.as_deref(),
        num_disparities,
        &out,
    )?;
    println!(
        "wrote {} (rig file), {} (pod calibration) and the capture set {}",
        p.rig.display(),
        p.calibration.display(),
        p.capture.display()
    );
    let truth = p
        .truth
        .map(|t| format!(" --truth {}", t.display()))
        .unwrap_or_default();
    println!(
        "reconstruct it: conformd reconstruct {} --rig {} --calibration {} --out scan.ply{truth}",
        p.capture.display(),
        p.rig.display(),
        p.calibration.display()
    );
    Ok(())
}
