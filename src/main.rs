//! The `conformd` command line: turns flags into one library call each and prints the
//! call's summary. Errors are printed as one sentence naming the file and what was wrong.

mod cli;

use clap::Parser;
use cli::args::{Cli, Cmd, DemoKind, ModelCmd};
use cli::progress;
use conformd::conform::Method;
use conformd::jobs;
use conformd::template::TemplateSource;
use indicatif::ProgressBar;
use std::process::ExitCode;

fn run(cli: Cli) -> Result<(), jobs::JobError> {
    match cli.cmd {
        Cmd::Conform {
            template,
            template_groups,
            template_rig,
            scan,
            template_landmarks,
            scan_landmarks,
            config,
            method,
            out,
            report,
        } => {
            let opts = jobs::conform_options(config.as_deref(), method)?;
            let mut template = match (template, &config) {
                (Some(t), _) => {
                    TemplateSource::named(&t, template_groups).map_err(jobs::JobError::Usage)?
                }
                (None, Some(c)) => jobs::template_from_config(c)?,
                (None, None) => {
                    return Err(jobs::JobError::Usage(
                        "--template is needed (or a --config with a [template] table)".into(),
                    ));
                }
            };
            if template_rig.is_some() {
                if template.generic.is_some() {
                    return Err(jobs::JobError::Usage(
                        "--template-rig is for a template mesh: a generic template brings its own rig".into(),
                    ));
                }
                template.rig = template_rig;
            }
            let files = jobs::ConformFiles {
                template,
                scan,
                template_landmarks,
                scan_landmarks,
                out: out.clone(),
                report: report.clone(),
            };
            let pb = progress::iterations(opts.max_iterations, "conform");
            let r = jobs::conform_files(&files, &opts, &mut |it| progress::tick(&pb, it));
            pb.finish_and_clear();
            println!("{}\nwrote {}", r?, out.display());
            if let Some(p) = report {
                println!("wrote {}", p.display());
            }
        }
        Cmd::Check { config } => {
            let cfg = jobs::check(&config)?;
            println!("{} is a valid station file; resolved:", config.display());
            print!(
                "{}",
                toml::to_string(&cfg.shown()).expect("a station config serialises")
            );
        }
        Cmd::Process {
            capture,
            config,
            out,
            json,
            parent,
            stage,
            landmarks,
            template_cache,
        } => {
            if let Some(pid) = parent {
                cli::exit_with_parent(pid);
            }
            cli::crash_hook(&capture);
            let write = if stage {
                jobs::Write::Stage
            } else {
                jobs::Write::Publish
            };
            let landmarks = landmarks.as_deref();
            let run = |tick: &mut (dyn FnMut(conformd::station::pipeline::Progress) + Send)| {
                jobs::process(
                    &capture,
                    &config,
                    &out,
                    landmarks,
                    write,
                    template_cache.as_deref(),
                    tick,
                )
            };
            if json {
                let r = run(&mut |_| {});
                let line = serde_json::to_string(&jobs::process_outcome(&r, write));
                println!("{}", line.expect("an outcome serialises"));
                r?;
            } else {
                let (pb, mut tick) = progress::pipeline(30);
                let r = run(&mut tick);
                pb.finish_and_clear();
                let (dir, report) = r?;
                println!("{report}\nwrote {}", dir.display());
            }
        }
        Cmd::Daemon { config } => {
            let cfg = jobs::check(&config)?;
            conformd::daemon::run(cfg)?;
        }
        Cmd::Worker { config } => {
            let cfg = jobs::check(&config)?;
            conformd::daemon::worker::run(cfg)?;
        }
        Cmd::Demo {
            which: DemoKind::Station,
            out,
            keep_running,
        } => {
            let pb = progress::iterations(12, "render");
            pb.set_style(
                indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} captures")
                    .expect("valid template")
                    .progress_chars("=> "),
            );
            let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
            if keep_running {
                let s = stop.clone();
                let _ = std::thread::spawn(move || {
                    let _ = std::io::stdin().read_line(&mut String::new());
                    s.store(true, std::sync::atomic::Ordering::SeqCst);
                });
            }
            let d = jobs::demo_station(
                &out,
                &mut |stage, done, total| {
                    pb.set_prefix(stage.to_string());
                    pb.set_length(total);
                    pb.set_position(done);
                },
                &mut |d| {
                    pb.finish_and_clear();
                    println!("{d}");
                    if keep_running {
                        println!("the daemon keeps running; press Enter or Ctrl-C to stop it");
                    }
                },
                &mut || keep_running && !stop.load(std::sync::atomic::Ordering::SeqCst),
            );
            pb.finish_and_clear();
            d?;
        }
        Cmd::Demo { out, .. } => {
            let mut bars: Vec<(Method, ProgressBar)> = Vec::new();
            let s = jobs::demo_paper(&out, &mut |m, it| {
                if bars.last().map(|b| b.0) != Some(m) {
                    if let Some((_, b)) = bars.last() {
                        b.finish_and_clear();
                    }
                    let name = format!("{m:?}").to_lowercase();
                    bars.push((m, progress::iterations(30, &name)));
                }
                if let Some((_, b)) = bars.last() {
                    progress::tick(b, it);
                }
            });
            if let Some((_, b)) = bars.last() {
                b.finish_and_clear();
            }
            println!("{}", s?);
        }
        Cmd::Template {
            kind,
            vertices,
            pose,
            shape,
            out,
        } => {
            let s = jobs::template(kind, vertices, &pose, &shape, &out)?;
            println!("{kind:?} template: {s}");
        }
        Cmd::Autorig {
            mesh,
            limbs,
            out,
            preview,
        } => {
            let out = out.unwrap_or_else(|| mesh.with_extension("rig.json"));
            println!("{}", jobs::autorig(&mesh, limbs, &out, preview.as_deref())?);
        }
        Cmd::Render {
            mesh,
            colour_by,
            views,
            width,
            height,
            out,
        } => {
            jobs::render(&mesh, &colour_by, &views, width, height, &out)?;
            println!("wrote {}", out.display());
        }
        Cmd::Capture { config, subject } => {
            println!("{}", jobs::capture(&config, subject.as_deref())?);
        }
        Cmd::Simulate {
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
        } => {
            let written = match (chessboard, subject) {
                (Some(board), _) if placement => {
                    vec![jobs::simulate_placement(
                        &rig, &board, square, board_yaw, noise, &out,
                    )?]
                }
                (Some(board), _) => jobs::simulate_chessboard(&rig, &board, square, views, &out)?,
                (None, Some(subject)) => {
                    let mut d = jobs::simulate(&rig, &subject, &pose, captures, noise, &out)?;
                    d.push(out.join("calibration"));
                    d
                }
                (None, None) => unreachable!("clap requires --subject without --chessboard"),
            };
            for d in written {
                println!("wrote {}", d.display());
            }
        }
        Cmd::Calibrate {
            images,
            placement,
            rig,
            calibration,
            board_origin,
            board_yaw,
            board,
            square,
            out,
        } => {
            match (images, placement, rig) {
                (_, Some(capture), Some(rig)) => {
                    let placement = conformd::stereo::calibrate::BoardPlacement {
                        origin: parse_point(&board_origin)?,
                        yaw: board_yaw,
                    };
                    let found = jobs::calibrate_placement(
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
                    println!("{}", jobs::calibrate(&images, &board, square, &out)?)
                }
                _ => unreachable!("clap requires --images or --placement with --rig"),
            }
            println!("wrote {}", out.display());
        }
        Cmd::Reconstruct {
            capture,
            rig,
            calibration,
            out,
            report,
            mesh,
            truth,
            truth_scale,
            truth_pod,
        } => {
            let mut station =
                conformd::stereo::rig::Reconstruction::load(&rig, calibration.as_deref())?;
            let truth = truth.as_deref().map(|file| jobs::ScanTruth {
                file,
                scale: truth_scale,
                pod: truth_pod.as_deref(),
            });
            let (r, score) = jobs::reconstruct_scored(
                &mut station,
                &capture,
                &out,
                report.as_deref(),
                mesh,
                truth,
            )?;
            println!("{r}\nwrote {}", out.display());
            if let Some(score) = score {
                println!("{score}");
            }
        }
        Cmd::ImportPair {
            left,
            right,
            calib,
            truth,
            num_disparities,
            out,
        } => {
            let p = jobs::import_pair(
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
        }
        Cmd::Disparity {
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
        } => {
            use conformd::stereo::disparity::{Profile, SgbmOptions};
            let profile = match profile.as_str() {
                "speckle" => Profile::Speckle,
                "natural" => Profile::Natural,
                other => {
                    return Err(jobs::JobError::Usage(format!(
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
            let truth = truth.as_deref().map(|file| jobs::TruthArgs {
                file,
                scale: truth_scale,
                min_x: truth_from_x,
            });
            let (d, score) =
                jobs::disparity_scored(&left, &right, &o, &out, truth, confidence.as_deref())?;
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
        }
        Cmd::Cameras => {
            let (list, unusable) = conformd::rig::v4l2::list_all();
            if list.is_empty() && unusable.is_empty() {
                println!("no V4L2 cameras found (no /dev/video* device on this machine)");
            }
            for d in list {
                println!("{d}");
            }
            for (path, why) in unusable {
                println!("{}: {why}", path.display());
            }
        }
        Cmd::Model { cmd } => match cmd {
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
                let (m, q) = jobs::model_build(&meshes, &opts, &out, quality)?;
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
                for f in jobs::model_modes(&model, modes, sigma, &view, &out)? {
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
                let m = jobs::model_posture(kind, vertices, postures, degrees, &out)?;
                println!("{m}");
                println!("wrote {}", out.display());
            }
            ModelCmd::Weigh {
                fit,
                results,
                features,
                out,
            } => {
                let m = jobs::model_weigh(&fit, &results, features, &out)?;
                println!("{m}");
                println!("wrote {}", out.display());
            }
            ModelCmd::Score { model, meshes } => {
                for s in jobs::model_score(&model, &meshes)? {
                    println!("{s}");
                }
            }
        },
        Cmd::Measure {
            meshes,
            template,
            vertices,
            template_landmarks,
            template_groups,
            definitions,
            model,
            normalise_posture,
            csv,
            repeatability,
        } => {
            let mut source =
                TemplateSource::named(&template, template_groups).map_err(jobs::JobError::Usage)?;
            if template_landmarks.is_some() {
                source.landmarks = template_landmarks;
            }
            if source.generic.is_some() {
                source.vertices = vertices;
            }
            let resolved = jobs::resolve_measurements(&source, definitions.as_deref())?;
            let posture = normalise_posture
                .then(|| jobs::posture_removal(&source, model.as_deref(), &resolved))
                .transpose()?;
            let reports = meshes
                .iter()
                .map(|m| jobs::measure(m, &resolved, posture.as_ref()))
                .collect::<Result<Vec<_>, _>>()?;
            if repeatability {
                print!("{}", jobs::repeatability(&reports)?);
            } else {
                println!(
                    "{}",
                    serde_json::to_string_pretty(&reports).expect("serialises")
                );
            }
            if let Some(p) = csv {
                conformd::files::write_atomic(&p, jobs::measurements_csv(&reports).as_bytes())?;
                eprintln!("wrote {}", p.display());
            }
        }
        Cmd::Export {
            results,
            out,
            repeatability,
        } => {
            for p in out.iter().chain(&repeatability) {
                conformd::files::refuse_inside(p, &results, "the results folder")?;
            }
            let export = jobs::export_csv(&results)?;
            for (file, why) in &export.skipped {
                eprintln!("warning: {file} left out: {why}");
            }
            if !export.rejected.is_empty() {
                eprintln!(
                    "{} rejected result(s) left out (review.json)",
                    export.rejected.len()
                );
            }
            if let Some(p) = &repeatability {
                let csv = conformd::station::export::spreads_csv(&export.subjects);
                conformd::files::write_atomic(p, csv.as_bytes())?;
                eprintln!(
                    "wrote {} ({} subject(s) with two results or more)",
                    p.display(),
                    export.subjects.len()
                );
            }
            let csv = export.csv;
            match out {
                Some(p) => {
                    conformd::files::write_atomic(&p, csv.as_bytes())?;
                    eprintln!("wrote {}", p.display());
                }
                None => print!("{csv}"),
            }
        }
        Cmd::Info { mesh, original } => {
            let i = jobs::info(&mesh, original.as_deref())?;
            println!("{}", serde_json::to_string_pretty(&i).expect("serialises"));
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("conformd: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Parses `x,y,z`.
fn parse_point(s: &str) -> Result<[f64; 3], jobs::JobError> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| jobs::JobError::Usage(format!("'{s}': expected x,y,z in metres")))?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        _ => Err(jobs::JobError::Usage(format!(
            "'{s}': expected x,y,z in metres"
        ))),
    }
}
