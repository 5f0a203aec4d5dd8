//! `conformd process`: one capture set through the station's pipeline; with `--json`, the outcome line the daemon reads.

use crate::cli::args::ProcessArgs;
use crate::cli::progress;
use conformd::commands;

pub fn run(a: ProcessArgs) -> Result<(), commands::CommandError> {
    let ProcessArgs {
        capture,
        config,
        out,
        json,
        parent,
        stage,
        landmarks,
        template_cache,
    } = a;
    if let Some(pid) = parent {
        crate::cli::exit_with_parent(pid);
    }
    let write = if stage {
        commands::Write::Stage
    } else {
        commands::Write::Publish
    };
    let landmarks = landmarks.as_deref();
    let run = |tick: &mut (dyn FnMut(conformd::station::pipeline::Progress) + Send)| {
        commands::process(
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
        let line = serde_json::to_string(&commands::process_outcome(&r, write));
        println!("{}", line.expect("an outcome serialises"));
        r?;
    } else {
        let (pb, mut tick) = progress::pipeline(30);
        let r = run(&mut tick);
        pb.finish_and_clear();
        let (dir, report) = r?;
        println!("{report}\nwrote {}", dir.display());
    }
    Ok(())
}
