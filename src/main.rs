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
        /// template mesh (.obj, .ply or .off); its vertex order and triangles are kept
        #[arg(long)]
        template: PathBuf,
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
    /// Describe a mesh: topology, watertightness, folded triangles, and with --original
    /// the paper's variation figures against it.
    Info {
        mesh: PathBuf,
        #[arg(long)]
        original: Option<PathBuf>,
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
