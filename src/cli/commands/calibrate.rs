//! `conformd calibrate`: one pod's stereo calibration, or every pod's placement in the rig.

use crate::cli::args::CalibrateArgs;
use conformd::commands;

pub fn run(a: CalibrateArgs) -> Result<(), commands::CommandError> {
    let CalibrateArgs {
        images,
        placement,
        rig,
        calibration,
        board_origin,
        board_yaw,
        board,
        square,
        out,
    } = a;
    match (images, placement, rig) {
        (_, Some(capture), Some(rig)) => {
            let placement = conformd::stereo::calibrate::BoardPlacement {
                origin: parse_point(&board_origin)?,
                yaw: board_yaw,
            };
            let found = commands::calibrate_placement(
                &capture,
                &rig,
                calibration.as_deref(),
                &board,
                square,
                &placement,
                &out,
            )?;
            for p in &found {
                println!("{p}");
            }
        }
        (Some(images), _, _) => {
            println!("{}", commands::calibrate(&images, &board, square, &out)?)
        }
        _ => unreachable!("clap requires --images or --placement with --rig"),
    }
    println!("wrote {}", out.display());
    Ok(())
}

/// Parses `x,y,z`.
fn parse_point(s: &str) -> Result<[f64; 3], commands::CommandError> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| commands::CommandError::Usage(format!("'{s}': expected x,y,z in metres")))?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        _ => Err(commands::CommandError::Usage(format!(
            "'{s}': expected x,y,z in metres"
        ))),
    }
}
