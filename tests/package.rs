//! The Debian package (`make deb`, `packaging/deb/`): built from the tested binary, its
//! control fields and contents read back, lintian run on it, then installed into a
//! throwaway root with `dpkg --root` (the maintainer scripts honour DPKG_ROOT), its units
//! verified by systemd-analyze, an operator's edit kept over a reinstall, and purged: the
//! configuration goes, the station's data and user stay.

use crate::common::{CHILD_LIMIT, Deadline};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const BIN: &str = env!("CARGO_BIN_EXE_conformd");

fn ok(what: &str, o: Output) -> String {
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{what} failed ({}):\n{out}\n{}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

/// The package built from the binary under test (gzip: quicker than make deb's xz).
fn build(out: &Path) -> PathBuf {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("packaging/deb/build.sh");
    let printed = ok(
        "packaging/deb/build.sh",
        Command::new("sh")
            .arg(script)
            .arg(BIN)
            .arg(out)
            .arg("gzip")
            .output_within(CHILD_LIMIT),
    );
    let deb = PathBuf::from(printed.trim());
    assert!(deb.is_file(), "build.sh printed {printed:?}, no such file");
    deb
}

/// Runs commands as root: as they are when the test is root, otherwise under fakeroot
/// with its state kept in a file (useradd and chown need a root; the owners they set
/// are read back through the same state).
struct AsRoot {
    fake_state: Option<PathBuf>,
}

impl AsRoot {
    fn new(dir: &Path) -> AsRoot {
        let uid = std::fs::metadata("/proc/self").map_or(u32::MAX, |m| m.uid());
        let fake_state = (uid != 0).then(|| dir.join("fakeroot.state"));
        if let Some(f) = &fake_state {
            std::fs::write(f, "").unwrap();
        }
        AsRoot { fake_state }
    }

    fn command(&self, program: &str) -> Command {
        match &self.fake_state {
            None => Command::new(program),
            Some(f) => {
                let mut c = Command::new("fakeroot");
                c.arg("-i").arg(f).arg("-s").arg(f).arg("--").arg(program);
                c
            }
        }
    }

    /// `dpkg` on the throwaway root: its maintainer scripts run outside a chroot with
    /// DPKG_ROOT set.
    fn dpkg(&self, root: &Path, args: &[&str]) -> Output {
        self.command("dpkg")
            .arg(format!("--root={}", root.display()))
            .args([
                "--force-script-chrootless",
                "--force-depends",
                "--force-not-root",
            ])
            .arg("--log=/dev/null")
            .args(args)
            .output_within(CHILD_LIMIT)
    }

    /// Owner, group and permission bits of `p`.
    fn owner(&self, p: &Path) -> (u32, u32, u32) {
        let out = ok(
            "stat",
            self.command("stat")
                .args(["-c", "%u %g %a"])
                .arg(p)
                .output_within(CHILD_LIMIT),
        );
        let f: Vec<&str> = out.split_whitespace().collect();
        (
            f[0].parse().unwrap(),
            f[1].parse().unwrap(),
            u32::from_str_radix(f[2], 8).unwrap(),
        )
    }
}

/// An empty root with what dpkg and useradd need: a status database, and passwd and
/// group files with the groups Debian's base-passwd makes (video, dialout).
fn throwaway_root(root: &Path) {
    for d in [
        "var/lib/dpkg/info",
        "var/lib/dpkg/updates",
        "var/lib/dpkg/triggers",
        "etc",
    ] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    let files = [
        ("var/lib/dpkg/status", ""),
        ("etc/passwd", "root:x:0:0:root:/root:/bin/sh\n"),
        ("etc/group", "root:x:0:\ndialout:x:20:\nvideo:x:44:\n"),
        ("etc/shadow", "root:*:19000:0:99999:7:::\n"),
        ("etc/gshadow", "root:*::\ndialout:*::\nvideo:*::\n"),
    ];
    for (f, text) in files {
        std::fs::write(root.join(f), text).unwrap();
    }
}

/// passwd or group line `name` of the root, split at ':'.
fn entry(root: &Path, file: &str, name: &str) -> Option<Vec<String>> {
    std::fs::read_to_string(root.join("etc").join(file))
        .unwrap()
        .lines()
        .find(|l| l.split(':').next() == Some(name))
        .map(|l| l.split(':').map(str::to_string).collect())
}

#[test]
fn the_debian_package_installs_its_user_units_and_config_and_purges_without_the_data() {
    let dir = tempfile::tempdir().unwrap();
    let deb = build(&dir.path().join("out"));
    let deb_s = deb.to_str().unwrap();

    // control fields
    let field = |name: &str| {
        ok(
            "dpkg-deb -f",
            Command::new("dpkg-deb")
                .args(["-f", deb_s, name])
                .output_within(CHILD_LIMIT),
        )
        .trim()
        .to_string()
    };
    assert_eq!(field("Package"), "conformd");
    assert_eq!(field("Version"), format!("{}-1", env!("CARGO_PKG_VERSION")));
    let depends = field("Depends");
    for lib in [
        "libc6",
        "libopencv-core",
        "libopencv-calib3d",
        "passwd",
        "fonts-dejavu-core",
        "libjs-three",
    ] {
        assert!(depends.contains(lib), "Depends lacks {lib}: {depends}");
    }

    // contents, with their modes
    let listing = ok(
        "dpkg-deb -c",
        Command::new("dpkg-deb")
            .args(["-c", deb_s])
            .output_within(CHILD_LIMIT),
    );
    for (path, perms) in [
        ("./usr/bin/conformd", "-rwxr-xr-x"),
        ("./lib/systemd/system/conformd.service", "-rw-r--r--"),
        ("./lib/systemd/system/conformd-worker.service", "-rw-r--r--"),
        ("./etc/conformd/station.toml", "-rw-r--r--"),
        ("./etc/conformd/rig.example.toml", "-rw-r--r--"),
        ("./usr/share/conformd/measurements/pig.toml", "-rw-r--r--"),
        ("./usr/share/conformd/measurements/body.toml", "-rw-r--r--"),
        ("./usr/share/doc/conformd/copyright", "-rw-r--r--"),
        (
            "./usr/share/doc/conformd/examples/worker.example.toml",
            "-rw-r--r--",
        ),
        ("./usr/share/man/man1/conformd.1.gz", "-rw-r--r--"),
    ] {
        let line = listing
            .lines()
            .find(|l| l.ends_with(&format!(" {path}")))
            .unwrap_or_else(|| panic!("{path} not in the package:\n{listing}"));
        assert!(line.starts_with(perms), "{line}: expected {perms}");
        assert!(line.contains(" root/root "), "{line}: not owned by root");
    }
    assert!(!listing.contains("/usr/local/"), "{listing}");

    // lintian: no errors (warnings are printed for the reader)
    let lint = Command::new("lintian")
        .args(["--fail-on", "error", deb_s])
        .output_within(CHILD_LIMIT);
    let lint_out = String::from_utf8_lossy(&lint.stdout).into_owned();
    assert!(
        lint.status.success() && !lint_out.lines().any(|l| l.starts_with("E:")),
        "lintian:\n{lint_out}{}",
        String::from_utf8_lossy(&lint.stderr)
    );
    eprintln!("lintian: {} lines\n{lint_out}", lint_out.lines().count());

    // installed into a throwaway root
    let root = dir.path().join("root");
    throwaway_root(&root);
    let as_root = AsRoot::new(dir.path());
    ok("dpkg --install", as_root.dpkg(&root, &["--install", deb_s]));
    let user = entry(&root, "passwd", "conformd").expect("the conformd user is made");
    assert_eq!(user[5], "/var/lib/conformd", "{user:?}");
    assert_eq!(user[6], "/usr/sbin/nologin", "{user:?}");
    for group in ["video", "dialout"] {
        let g = entry(&root, "group", group).unwrap();
        assert!(g[3].split(',').any(|m| m == "conformd"), "{group}: {g:?}");
    }
    let (uid, gid): (u32, u32) = (user[2].parse().unwrap(), user[3].parse().unwrap());
    let state = root.join("var/lib/conformd");
    assert!(state.is_dir(), "the state directory is not made");
    assert_eq!(as_root.owner(&state), (uid, gid, 0o750));
    let station = root.join("etc/conformd/station.toml");
    assert_eq!(as_root.owner(&station), (0, gid, 0o640));
    assert_eq!(as_root.owner(&root.join("usr/bin/conformd")), (0, 0, 0o755));
    let status = std::fs::read_to_string(root.join("var/lib/dpkg/status")).unwrap();
    assert!(
        status.contains("Status: install ok installed")
            && status.contains(" /etc/conformd/station.toml ")
            && status.contains(" /etc/conformd/rig.example.toml "),
        "{status}"
    );

    // the installed binary reads the installed station file
    ok(
        "conformd check on the installed station file",
        Command::new(root.join("usr/bin/conformd"))
            .arg("check")
            .arg(&station)
            .output_within(CHILD_LIMIT),
    );

    // the installed units name the installed binary and pass systemd-analyze verify
    let units = dir.path().join("units");
    std::fs::create_dir_all(&units).unwrap();
    for unit in ["conformd.service", "conformd-worker.service"] {
        let text = std::fs::read_to_string(root.join("lib/systemd/system").join(unit)).unwrap();
        assert!(
            text.contains("ExecStart=/usr/bin/conformd "),
            "{unit}:\n{text}"
        );
        let here = text.replace(
            "ExecStart=/usr/bin/conformd ",
            &format!("ExecStart={} ", root.join("usr/bin/conformd").display()),
        );
        std::fs::write(units.join(unit), here).unwrap();
    }
    ok(
        "systemd-analyze verify",
        Command::new("systemd-analyze")
            .arg("verify")
            .arg(units.join("conformd.service"))
            .arg(units.join("conformd-worker.service"))
            .output_within(CHILD_LIMIT),
    );

    // an operator's edit survives a reinstall; the user is not made twice
    let edited = std::fs::read_to_string(&station)
        .unwrap()
        .replace("name = \"crate-1\"", "name = \"crate-7\"");
    std::fs::write(&station, &edited).unwrap();
    ok(
        "dpkg --install again",
        as_root.dpkg(&root, &["--install", deb_s]),
    );
    assert_eq!(std::fs::read_to_string(&station).unwrap(), edited);
    let passwd = std::fs::read_to_string(root.join("etc/passwd")).unwrap();
    assert_eq!(
        passwd
            .lines()
            .filter(|l| l.starts_with("conformd:"))
            .count(),
        1,
        "{passwd}"
    );

    // purged: binary and configuration gone; the captures and the user stay
    let capture = state.join("captures/c-0001/pod1-left.png");
    std::fs::create_dir_all(capture.parent().unwrap()).unwrap();
    std::fs::write(&capture, b"a station's capture").unwrap();
    let purged = ok(
        "dpkg --purge",
        as_root.dpkg(&root, &["--purge", "conformd"]),
    );
    assert!(!root.join("usr/bin/conformd").exists());
    assert!(!root.join("lib/systemd/system/conformd.service").exists());
    assert!(
        !root.join("etc/conformd").exists(),
        "configuration left after purge"
    );
    assert_eq!(
        std::fs::read(&capture).expect("a capture is kept on purge"),
        b"a station's capture"
    );
    assert!(entry(&root, "passwd", "conformd").is_some());
    assert!(purged.contains("/var/lib/conformd"), "{purged}");
}
