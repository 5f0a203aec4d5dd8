//! `conformd cameras`: the V4L2 cameras this machine has.

use conformd::jobs;

pub fn run() -> Result<(), jobs::JobError> {
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
    Ok(())
}
