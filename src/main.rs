//! The `conformd` command line: turns flags into one library call each and prints the
//! outcome. Errors are printed as one sentence naming the file and what was wrong.

use clap::{Parser, Subcommand};
use conformd::conform::{ConformOptions, IterationReport, Method};
use conformd::jobs;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "conformd",
    version,
    about = "Photogrammetry station daemon: conform a template mesh onto scans"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Conform a template mesh onto a scan (Ju et al. 2004, or conformd's default method).
    Conform {
        /// template mesh (.obj, .ply or .off), or `pig` / `body` for a generic template
        /// (10,000 vertices, with its own landmarks); without it the config's [template]
        #[arg(long)]
        template: Option<String>,
        /// vertex groups of a template mesh: lines `name i j k ...`
        #[arg(long)]
        template_groups: Option<PathBuf>,
        /// scan: a mesh with holes or a point cloud (.ply, .obj or .off)
        #[arg(long)]
        scan: PathBuf,
        /// template landmarks: `name vertex_index` lines (or `name x y z`, or MeshLab .pp)
        #[arg(long)]
        template_landmarks: Option<PathBuf>,
        /// scan landmarks: `name x y z` lines or MeshLab .pp; without landmarks the
        /// template is aligned automatically
        #[arg(long)]
        scan_landmarks: Option<PathBuf>,
        /// conformation options (TOML: a conform.toml, or a station config's [conform])
        #[arg(long)]
        config: Option<PathBuf>,
        /// method: `paper` (as published) or `default` (conformd's); overrides the config
        #[arg(long)]
        method: Option<Method>,
        /// output mesh (.ply or .obj)
        #[arg(long)]
        out: PathBuf,
        /// JSON report with the per-iteration figures
        #[arg(long)]
        report: Option<PathBuf>,
    },
    /// Run the paper's sphere-to-box case with missing data, both methods.
    Demo {
        #[arg(long, default_value = "demo-output")]
        out: PathBuf,
    },
    /// Write a generic pig or body template (OBJ with groups, or PLY) and its landmarks.
    Template {
        /// `pig` or `body`
        kind: conformd::synth::templates::Kind,
        /// about how many vertices (2,000 to 100,000 is usual)
        #[arg(long, default_value_t = 10_000)]
        vertices: usize,
        /// pose, degrees per joint group, e.g. `swing=12,nod=-8,twist=5`
        #[arg(long, default_value = "")]
        pose: String,
        /// shape factors, e.g. `length=1.1,girth=0.95`
        #[arg(long, default_value = "")]
        shape: String,
        /// output mesh (.obj keeps the groups); landmarks go beside it as .landmarks
        #[arg(long)]
        out: PathBuf,
    },
    /// Render a shaded preview PNG of a mesh.
    Render {
        mesh: PathBuf,
        /// `none`, `group`, or `distance-to=SCAN`
        #[arg(long, default_value = "none")]
        colour_by: jobs::ColourBy,
        /// comma-separated views: front, back, left, right, side, top, three-quarter
        #[arg(long, default_value = "three-quarter,side", value_delimiter = ',')]
        views: Vec<String>,
        #[arg(long, default_value_t = 800)]
        width: u32,
        #[arg(long, default_value_t = 600)]
        height: u32,
        #[arg(long)]
        out: PathBuf,
    },
    /// Capture one set with the station's cameras and trigger (atomically).
    Capture {
        /// station config with [capture], [[cameras]] and optionally [trigger]
        #[arg(long)]
        config: PathBuf,
        /// the animal's or person's id, recorded in the manifest
        #[arg(long)]
        subject: Option<String>,
    },
    /// Render capture sets of a subject as the rig's cameras would see it (speckle
    /// projector, lens distortion, sensor noise), with ground truth and calibrations.
    Simulate {
        #[arg(long)]
        rig: PathBuf,
        /// a mesh file, or `pig` / `body` (posed with --pose)
        #[arg(long, required_unless_present = "chessboard")]
        subject: Option<String>,
        /// render chessboard calibration views instead (inner corners, e.g. 9x6)
        #[arg(long)]
        chessboard: Option<String>,
        /// chessboard square size (m)
        #[arg(long, default_value_t = 0.03)]
        square: f64,
        /// chessboard views per pod
        #[arg(long, default_value_t = 15)]
        views: usize,
        /// with --chessboard: one capture set of the board lying on the rig's floor, seen
        /// by every pod (for `calibrate --placement`), instead of calibration views
        #[arg(long, requires = "chessboard")]
        placement: bool,
        /// with --placement: the board's long side turned this many degrees from the rig's
        /// x towards its y
        #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
        board_yaw: f64,
        #[arg(long, default_value = "")]
        pose: String,
        #[arg(long, default_value_t = 1)]
        captures: usize,
        /// sensor noise, grey levels (standard deviation)
        #[arg(long, default_value_t = 2.0)]
        noise: f64,
        #[arg(long)]
        out: PathBuf,
    },
    /// Stereo calibration of one pod from chessboard pairs (leftNN/rightNN images); or,
    /// with --placement, every pod's pose in the rig frame from one capture set of a
    /// board that all pods see (writes the rig file with measured poses).
    Calibrate {
        /// chessboard pairs of one pod
        #[arg(
            long,
            required_unless_present = "placement",
            conflicts_with = "placement"
        )]
        images: Option<PathBuf>,
        /// a capture set of the board lying in the rig, seen by every pod
        #[arg(long, requires = "rig")]
        placement: Option<PathBuf>,
        /// the rig file whose pod poses --placement measures
        #[arg(long)]
        rig: Option<PathBuf>,
        /// folder of pod calibrations (`<pod>.yml`) for --placement's lenses
        #[arg(long)]
        calibration: Option<PathBuf>,
        /// for --placement: where the board's origin lies in the rig frame, x,y,z (m). The
        /// board lies face up; the origin is the outer corner of the dark corner square
        /// from which the long side runs along the yaw direction and the short side to its
        /// right (seen from above)
        #[arg(long, default_value = "0,0,0", allow_hyphen_values = true)]
        board_origin: String,
        /// for --placement: the board's long side turned this many degrees from the rig's
        /// x towards its y
        #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
        board_yaw: f64,
        /// inner corners, e.g. 9x6
        #[arg(long)]
        board: String,
        /// square size (m)
        #[arg(long)]
        square: f64,
        /// the pod's calibration (OpenCV YAML), or with --placement the measured rig file
        #[arg(long)]
        out: PathBuf,
    },
    /// Reconstruct a capture set into a fused scan in the rig frame (OpenCV SGBM).
    Reconstruct {
        capture: PathBuf,
        #[arg(long)]
        rig: PathBuf,
        /// folder of pod calibrations (`<pod>.yml`, OpenCV YAML) replacing the rig file's
        #[arg(long)]
        calibration: Option<PathBuf>,
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        report: Option<PathBuf>,
        /// triangulate each pod's depth grid (cut at depth jumps) into a mesh with holes
        /// instead of fusing a point cloud
        #[arg(long)]
        mesh: bool,
    },
    /// Disparity of an already-rectified pair (PFM, or 16-bit PNG x16 for .png).
    Disparity {
        left: PathBuf,
        right: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 128)]
        num_disparities: i32,
        #[arg(long, default_value_t = 5)]
        block_size: i32,
    },
    /// List V4L2 cameras with their stable names, formats, sizes and controls.
    Cameras,
    /// Statistical shape model over conformed meshes.
    Model {
        #[command(subcommand)]
        cmd: ModelCmd,
    },
    /// Describe a mesh: topology, watertightness, folded triangles, and with --original
    /// the paper's variation figures against it.
    Info {
        mesh: PathBuf,
        #[arg(long)]
        original: Option<PathBuf>,
    },
}

#[derive(Subcommand)]
enum ModelCmd {
    /// Build a model from conformed meshes (one template).
    Build {
        /// conformed meshes
        #[arg(required = true)]
        meshes: Vec<PathBuf>,
        #[arg(long)]
        out: PathBuf,
        /// procrustes (shape only), rigid (size kept) or none
        #[arg(long, default_value = "procrustes")]
        align: conformd::model::Align,
        /// model one vertex group alone (e.g. torso)
        #[arg(long)]
        group: Option<String>,
        #[arg(long, default_value_t = 30)]
        max_modes: usize,
        /// also compute compactness, generalisation and specificity (slower)
        #[arg(long)]
        quality: bool,
    },
    /// Mean and mean +/- k sigma along the first modes, as meshes and a PNG sheet.
    Modes {
        #[arg(long)]
        model: PathBuf,
        #[arg(long, default_value_t = 3)]
        modes: usize,
        #[arg(long, default_value_t = 3.0)]
        sigma: f64,
        #[arg(long, default_value = "three-quarter")]
        view: String,
        #[arg(long)]
        out: PathBuf,
    },
    /// Mode scores, reconstruction residual and Mahalanobis distance of meshes.
    Score {
        #[arg(long)]
        model: PathBuf,
        #[arg(required = true)]
        meshes: Vec<PathBuf>,
    },
}

fn progress_bar(len: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len as u64);
    pb.set_style(
        ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} iterations {msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    pb.set_prefix(what.to_string());
    pb
}

fn tick(pb: &ProgressBar, it: &IterationReport) {
    pb.set_position(it.iteration as u64);
    pb.set_message(format!(
        "matched {} filled {} update {:.2e}",
        it.matched, it.filled, it.max_update_relative
    ));
}

fn run(cli: Cli) -> Result<(), jobs::JobError> {
    match cli.cmd {
        Cmd::Conform {
            template,
            template_groups,
            scan,
            template_landmarks,
            scan_landmarks,
            config,
            method,
            out,
            report,
        } => {
            let mut opts = match &config {
                Some(p) => jobs::load_conform_options(p)?,
                None => ConformOptions::default(),
            };
            if let Some(m) = method {
                if config.is_none() && m == Method::Paper {
                    opts = ConformOptions::paper();
                }
                opts.method = m;
            }
            let template = match (template, &config) {
                (Some(t), _) => match t.parse::<conformd::synth::templates::Kind>() {
                    Ok(kind) if !std::path::Path::new(&t).exists() => jobs::TemplateSource {
                        generic: Some(kind),
                        ..Default::default()
                    },
                    _ => jobs::TemplateSource {
                        mesh: Some(t.into()),
                        groups: template_groups,
                        ..Default::default()
                    },
                },
                (None, Some(c)) => jobs::TemplateSource::from_config(c)?.ok_or_else(|| {
                    jobs::JobError::Usage(format!(
                        "no --template, and {} has no [template] table",
                        c.display()
                    ))
                })?,
                (None, None) => {
                    return Err(jobs::JobError::Usage(
                        "--template is needed (or a --config with a [template] table)".into(),
                    ));
                }
            };
            let files = jobs::ConformFiles {
                template,
                scan,
                template_landmarks,
                scan_landmarks,
                out: out.clone(),
                report: report.clone(),
            };
            let pb = progress_bar(opts.max_iterations, "conform");
            let r = jobs::conform_files(&files, &opts, &mut |it| tick(&pb, it));
            pb.finish_and_clear();
            let r = r?;
            println!(
                "conformed {} vertices onto {} scan points in {} iterations, {:.2} s ({:?} method{})",
                r.template_vertices,
                r.scan_points,
                r.iterations.len(),
                r.seconds.total,
                r.method,
                if r.converged {
                    ""
                } else {
                    ", iteration limit reached"
                }
            );
            println!(
                "mean distance to the scan {:.3e} ({:.3}% of the diagonal); {} vertices matched, {} filled; {} folded triangles; watertight {}",
                r.mean_distance,
                r.mean_distance_relative * 100.0,
                r.matched,
                r.filled,
                r.folded_triangles,
                r.watertight_result
            );
            println!("wrote {}", out.display());
            if let Some(p) = report {
                println!("wrote {}", p.display());
            }
        }
        Cmd::Demo { out } => {
            let mut bars: Vec<(Method, ProgressBar)> = Vec::new();
            let s = jobs::demo(&out, &mut |m, it| {
                if bars.last().map(|b| b.0) != Some(m) {
                    if let Some((_, b)) = bars.last() {
                        b.finish_and_clear();
                    }
                    bars.push((m, progress_bar(30, &format!("{m:?}").to_lowercase())));
                }
                tick(&bars.last().unwrap().1, it);
            })?;
            if let Some((_, b)) = bars.last() {
                b.finish_and_clear();
            }
            println!(
                "The paper's sphere-to-box case with missing data (the +x face and a disc on top removed):"
            );
            for m in &s.methods {
                println!(
                    "  {:<8} {:>2} iterations {:.2} s: missing region ({} vertices) mean {:.2}%, 90th percentile {:.2}% of the box diagonal from the true box; watertight {}, folded {}",
                    format!("{:?}", m.method).to_lowercase(),
                    m.iterations,
                    m.seconds,
                    m.missing_vertices,
                    m.missing_mean * 100.0,
                    m.missing_p90 * 100.0,
                    m.watertight,
                    m.folded_triangles
                );
            }
            for f in &s.files {
                println!("wrote {}", f.display());
            }
        }
        Cmd::Template {
            kind,
            vertices,
            pose,
            shape,
            out,
        } => {
            let s = jobs::template(kind, vertices, &pose, &shape, &out)?;
            println!(
                "{kind:?} template: {} vertices, {} triangles, {} landmarks, groups {}; watertight {}",
                s.vertices,
                s.triangles,
                s.landmark_count,
                s.groups
                    .iter()
                    .map(|(g, n)| format!("{g} ({n})"))
                    .collect::<Vec<_>>()
                    .join(", "),
                s.watertight
            );
            println!(
                "wrote {}\nwrote {}",
                s.mesh.display(),
                s.landmarks.display()
            );
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
            let set = jobs::capture(&config, subject.as_deref())?;
            println!(
                "captured {} ({} cameras, {} attempt{})",
                set.id,
                set.manifest.cameras.len(),
                set.attempts,
                if set.attempts == 1 { "" } else { "s" }
            );
            println!("wrote {}", set.dir.display());
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
            if let (true, Some(board)) = (placement, &chessboard) {
                let d = jobs::simulate_placement(&rig, board, square, board_yaw, noise, &out)?;
                println!("wrote {}", d.display());
            } else if let Some(board) = chessboard {
                for d in jobs::simulate_chessboard(&rig, &board, square, views, &out)? {
                    println!("wrote {}", d.display());
                }
            } else {
                let subject = subject.expect("clap requires it");
                for d in jobs::simulate(&rig, &subject, &pose, captures, noise, &out)? {
                    println!("wrote {}", d.display());
                }
                println!("wrote {}", out.join("calibration").display());
            }
        }
        Cmd::Calibrate {
            images: None,
            placement: Some(capture),
            rig,
            calibration,
            board_origin,
            board_yaw,
            board,
            square,
            out,
        } => {
            let placement = conformd::stereo::calibrate::BoardPlacement {
                origin: parse_point(&board_origin)?,
                yaw: board_yaw,
            };
            let rig = rig.expect("clap requires --rig with --placement");
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
                println!(
                    "pod {}: left camera at ({:.4}, {:.4}, {:.4}) m; corner RMS {:.3} / {:.3} px; left-right check {:.2} mm, {:.3} deg",
                    p.pod,
                    p.position[0],
                    p.position[1],
                    p.position[2],
                    p.rms_left,
                    p.rms_right,
                    p.left_right_mm,
                    p.left_right_deg
                );
            }
            println!("wrote {}", out.display());
        }
        Cmd::Calibrate {
            images,
            board,
            square,
            out,
            ..
        } => {
            let images = images.expect("clap requires --images without --placement");
            let r = jobs::calibrate(&images, &board, square, &out)?;
            println!(
                "RMS reprojection error {:.3} px over {} of {} views; baseline {:.4}",
                r.rms,
                r.used.len(),
                r.views,
                r.baseline
            );
            for (v, e) in r.used.iter().zip(&r.per_view_left) {
                println!("  view {v:>2}: {e:.3} px");
            }
            if !r.skipped.is_empty() {
                println!(
                    "  skipped (board not found in both images): {:?}",
                    r.skipped
                );
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
        } => {
            let r = jobs::reconstruct(
                &capture,
                &rig,
                calibration.as_deref(),
                &out,
                report.as_deref(),
                mesh,
            )?;
            for p in &r.pods {
                println!(
                    "pod {}: {} points, {:.0}% valid disparity (rectify {:.2} s, disparity {:.2} s, reproject {:.2} s)",
                    p.pod,
                    p.points,
                    p.valid_disparity_share * 100.0,
                    p.seconds_rectify,
                    p.seconds_disparity,
                    p.seconds_reproject
                );
            }
            if mesh {
                println!(
                    "mesh of {} vertices, {} triangles; {:.2} s",
                    r.fused_points, r.triangles, r.seconds_total
                );
            } else {
                println!(
                    "fused {} points, {} in the working volume, {} after voxels, {} after outliers; {:.2} s",
                    r.fused_points, r.after_crop, r.after_voxel, r.after_outliers, r.seconds_total
                );
            }
            println!("wrote {}", out.display());
        }
        Cmd::Disparity {
            left,
            right,
            out,
            num_disparities,
            block_size,
        } => {
            let o = conformd::stereo::disparity::SgbmOptions {
                num_disparities,
                block_size,
                ..Default::default()
            };
            let share = jobs::disparity(&left, &right, &o, &out)?;
            println!(
                "{:.1}% of pixels have a disparity\nwrote {}",
                share * 100.0,
                out.display()
            );
        }
        Cmd::Cameras => {
            let list = conformd::rig::v4l2::list_devices();
            if list.is_empty() {
                println!("no V4L2 cameras found (no usable /dev/video* device on this machine)");
            }
            for d in list {
                println!("{} ({}, driver {})", d.path.display(), d.name, d.driver);
                for b in &d.by_id {
                    println!("  by-id: /dev/v4l/by-id/{b}");
                }
                for f in &d.formats {
                    println!("  format {f}");
                }
                for c in &d.controls {
                    println!("  control {c}");
                }
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
            } => {
                let opts = conformd::model::BuildOptions {
                    align,
                    group,
                    max_modes,
                };
                let (m, q) = jobs::model_build(&meshes, &opts, &out, quality)?;
                println!(
                    "model of {} meshes, {} vertices, {} modes",
                    m.samples.len(),
                    m.indices.len(),
                    m.modes.len()
                );
                let mut cum = 0.0;
                for (i, e) in m.explained.iter().enumerate().take(10) {
                    cum += e;
                    println!(
                        "  mode {:>2}: {:5.1}% of the variance ({:5.1}% cumulative)",
                        i + 1,
                        e * 100.0,
                        cum * 100.0
                    );
                }
                if let Some(q) = q {
                    println!("  modes  compactness  generalisation  specificity");
                    for i in 0..q.modes.len() {
                        println!(
                            "  {:>5}  {:>11.3}  {:>14.4e}  {:>11.4e}",
                            q.modes[i], q.compactness[i], q.generalisation[i], q.specificity[i]
                        );
                    }
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
            ModelCmd::Score { model, meshes } => {
                for s in jobs::model_score(&model, &meshes)? {
                    let z: Vec<String> = s
                        .scores_sd
                        .iter()
                        .take(5)
                        .map(|z| format!("{z:+.2}"))
                        .collect();
                    println!(
                        "{}: scores (sd) [{}], residual {:.3e}, mahalanobis {:.2}",
                        s.name,
                        z.join(", "),
                        s.residual,
                        s.mahalanobis
                    );
                }
            }
        },
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
