//! `conformd disparity`: the disparity (and confidence) of a rectified pair, scored against a truth when given.

use crate::cli::args::DisparityArgs;
use conformd::commands;

pub fn run(a: DisparityArgs) -> Result<(), commands::CommandError> {
    let DisparityArgs {
        left,
        right,
        out,
        num_disparities,
        block_size,
        profile,
        truth,
        truth_scale,
        truth_from_x,
        confidence,
        min_confidence,
    } = a;
    use conformd::stereo::disparity::{Profile, SgbmOptions};
    let profile = match profile.as_str() {
        "speckle" => Profile::Speckle,
        "natural" => Profile::Natural,
        other => {
            return Err(commands::CommandError::Usage(format!(
                "--profile {other}: expected speckle or natural"
            )));
        }
    };
    let defaults = SgbmOptions::for_profile(profile);
    let o = SgbmOptions {
        num_disparities,
        block_size,
        min_confidence: min_confidence.unwrap_or(defaults.min_confidence),
        ..defaults
    };
    let truth = truth.as_deref().map(|file| commands::TruthArgs {
        file,
        scale: truth_scale,
        min_x: truth_from_x,
    });
    let (d, score) =
        commands::disparity_scored(&left, &right, &o, &out, truth, confidence.as_deref())?;
    println!(
        "{:.1}% of pixels have a disparity\nwrote {}",
        d.valid_share() * 100.0,
        out.display()
    );
    if let Some(c) = &confidence {
        println!("wrote {} (confidence, 0 to 1)", c.display());
    }
    if let Some(s) = score {
        println!("{s}");
    }
    Ok(())
}
