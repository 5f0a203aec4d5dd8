//! `conformd model ...`: the statistical shape model's commands.

use crate::cli::args::ModelCmd;
use conformd::commands;

pub fn run(cmd: ModelCmd) -> Result<(), commands::CommandError> {
    match cmd {
        ModelCmd::Build {
            meshes,
            out,
            align,
            group,
            max_modes,
            quality,
            posture,
        } => {
            let opts = conformd::model::BuildOptions {
                align,
                group,
                max_modes,
                posture,
            };
            let (m, q) = commands::model_build(&meshes, &opts, &out, quality)?;
            println!("{m}");
            if let Some(q) = q {
                println!("{q}");
            }
            println!("wrote {}", out.display());
        }
        ModelCmd::Modes {
            model,
            modes,
            sigma,
            view,
            out,
        } => {
            for f in commands::model_modes(&model, modes, sigma, &view, &out)? {
                println!("wrote {}", f.display());
            }
        }
        ModelCmd::Posture {
            kind,
            vertices,
            postures,
            degrees,
            out,
        } => {
            let m = commands::model_posture(kind, vertices, postures, degrees, &out)?;
            println!("{m}");
            println!("wrote {}", out.display());
        }
        ModelCmd::Weigh {
            fit,
            results,
            features,
            out,
        } => {
            let m = commands::model_weigh(&fit, &results, features, &out)?;
            println!("{m}");
            println!("wrote {}", out.display());
        }
        ModelCmd::Score { model, meshes } => {
            for s in commands::model_score(&model, &meshes)? {
                println!("{s}");
            }
        }
    }
    Ok(())
}
