//! `conformd demo`: the station on a virtual crate, or the paper's case.

use crate::cli::args::DemoArgs;
use crate::cli::args::DemoKind;
use crate::cli::progress;
use conformd::commands;
use conformd::conform::Method;
use indicatif::ProgressBar;
use std::path::PathBuf;

pub fn run(a: DemoArgs) -> Result<(), commands::CommandError> {
    match a.which {
        DemoKind::Station => station(a.out, a.keep_running, a.captures.into()),
        DemoKind::Paper => paper(a.out),
    }
}

fn station(
    out: PathBuf,
    keep_running: bool,
    captures: usize,
) -> Result<(), commands::CommandError> {
    let pb = progress::iterations(captures, "render");
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
    let d = commands::demo_station(
        &out,
        captures,
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
            } else {
                println!("(the daemon stops with the demo: --keep-running keeps the page up)");
            }
        },
        &mut || keep_running && !stop.load(std::sync::atomic::Ordering::SeqCst),
    );
    pb.finish_and_clear();
    d?;
    Ok(())
}

fn paper(out: PathBuf) -> Result<(), commands::CommandError> {
    let mut bars: Vec<(Method, ProgressBar)> = Vec::new();
    let s = commands::demo_paper(&out, &mut |m, it| {
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
    Ok(())
}
