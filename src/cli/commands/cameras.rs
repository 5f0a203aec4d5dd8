//! `conformd cameras`: the V4L2 cameras this machine has.

use conformd::commands;

pub fn run() -> Result<(), commands::CommandError> {
    let (list, unusable) = conformd::devices::v4l2::list_all();
    if list.is_empty() && unusable.is_empty() {
        println!("no V4L2 cameras found (no /dev/video* device on this machine)");
    }
    for d in list {
        println!("{d}");
    }
    for (path, why) in unusable {
        println!("{}: {why}", path.display());
    }
    Ok(())
}
