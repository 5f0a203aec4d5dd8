//! `conformd simulate`: capture sets (or calibration views) rendered as the rig's cameras would see them.

use crate::cli::args::SimulateArgs;
use conformd::commands;

pub fn run(a: SimulateArgs) -> Result<(), commands::CommandError> {
    let SimulateArgs {
        rig,
        subject,
        chessboard,
        square,
        views,
        placement,
        board_yaw,
        pose,
        captures,
        noise,
        out,
    } = a;
    let written = match (chessboard, subject) {
        (Some(board), _) if placement => {
            vec![commands::simulate_placement(
                &rig, &board, square, board_yaw, noise, &out,
            )?]
        }
        (Some(board), _) => commands::simulate_chessboard(&rig, &board, square, views, &out)?,
        (None, Some(subject)) => {
            let mut d = commands::simulate(&rig, &subject, &pose, captures, noise, &out)?;
            d.push(out.join("calibration"));
            d
        }
        (None, None) => unreachable!("clap requires --subject without --chessboard"),
    };
    for d in written {
        println!("wrote {}", d.display());
    }
    Ok(())
}
