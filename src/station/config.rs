//! The station file: one typed, checked reader for every section (`[station]`,
//! `[template]`, `[conform]`, `[rig]`, `[capture]`, `[[cameras]]`, `[trigger]`, `[model]`, `[measure]`,
//! `[daemon]`). Paths are taken relative to the file; unknown keys are refused with their
//! line; every problem is collected, not just the first. `config/station.example.toml`
//! shows every key.

use crate::conform::ConformOptions;
use crate::devices::setup::{CameraSection, CaptureSection, RigConfig, TriggerSection};
use crate::template::TemplateSource;
use serde::de::{DeserializeOwned, IgnoredAny, MapAccess, Visitor};
use std::path::{Path, PathBuf};

/// `[station]`: who the station is and where its data lives.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StationSection {
    /// the station's name, written into every capture set
    pub name: String,
    /// the folder holding `captures/`, `incoming/` and `results/`
    pub data: PathBuf,
}

impl Default for StationSection {
    fn default() -> Self {
        StationSection {
            name: "station".into(),
            data: PathBuf::from("."),
        }
    }
}

impl StationSection {
    pub fn captures(&self) -> PathBuf {
        self.data.join("captures")
    }
    pub fn incoming(&self) -> PathBuf {
        self.data.join("incoming")
    }
    pub fn results(&self) -> PathBuf {
        self.data.join("results")
    }
    /// scan landmarks operators placed on the capture page, `<capture id>.txt` (beside
    /// the results, never in the capture set)
    pub fn landmarks(&self) -> PathBuf {
        self.data.join("landmarks")
    }
    /// what the worker processes keep between jobs (a generic template once built);
    /// anything in it may be deleted
    pub fn cache(&self) -> PathBuf {
        self.data.join("cache")
    }
}

/// `[rig]`: the stereo rig that reconstructs every capture.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigSection {
    /// the rig file (pods, lenses, poses, working volume, reconstruction settings)
    pub file: PathBuf,
    /// a folder of measured pod calibrations (`<pod>.yml`) replacing the rig file's
    pub calibration: Option<PathBuf>,
    /// scans as meshes with holes (each pod's depth grid triangulated) instead of fused
    /// point clouds
    #[serde(default)]
    pub mesh: bool,
}

/// `[model]`: the station's shape model.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelSection {
    /// the current model file; every result is scored against it when it exists
    pub file: Option<PathBuf>,
    /// rebuild the model after this many new results (0: only on request)
    pub rebuild_every: usize,
}

/// `[measure]`: measurements of every result (`measure` definitions; README).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MeasureSection {
    /// measurement definitions (TOML); a generic template brings its own
    pub definitions: Option<PathBuf>,
    /// also measure every result with its posture removed: a generic template's pose
    /// fitted and undone, or `posture_model`'s posture modes taken out
    pub normalise_posture: bool,
    /// a model with posture modes (`conformd model posture` / `model build --posture`)
    pub posture_model: Option<PathBuf>,
    /// a weight regression (`conformd model weigh`): every result gets a predicted weight
    pub weight: Option<PathBuf>,
}

impl Default for MeasureSection {
    fn default() -> Self {
        MeasureSection {
            definitions: None,
            normalise_posture: true,
            posture_model: None,
            weight: None,
        }
    }
}

/// `[daemon]`: how the station service runs.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DaemonSection {
    /// jobs at once (0: as many as the machine's cores allow)
    pub workers: usize,
    /// run jobs on this machine; false: only `conformd worker`s elsewhere run them (a
    /// PostgreSQL journal)
    pub local_workers: bool,
    /// seconds between full rescans of the capture folders
    pub rescan_s: f64,
    /// the HTTP server's address
    pub listen: String,
    /// bearer token for mutating API calls; required when `listen` is not loopback
    pub token: Option<String>,
    /// a job running longer than this is stopped and failed
    pub job_timeout_s: f64,
    /// attempts of a job whose failure was the machine's, not the capture's
    pub max_attempts: u32,
    /// watch the capture folders with inotify (off: rescans alone, e.g. on NFS)
    pub watch: bool,
    /// seconds a stop (SIGTERM) waits for running jobs before queueing them again
    pub drain_s: f64,
}

impl Default for DaemonSection {
    fn default() -> Self {
        DaemonSection {
            workers: 0,
            local_workers: true,
            rescan_s: 30.0,
            listen: "127.0.0.1:8470".into(),
            token: None,
            job_timeout_s: 300.0,
            max_attempts: 3,
            watch: true,
            drain_s: 30.0,
        }
    }
}

/// `[journal]`: where the job queue lives.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JournalSection {
    /// `postgres://user@host/db`: one journal for several stations and workers on other
    /// machines; none: the SQLite file `<data>/journal.sqlite` (one station)
    pub url: Option<String>,
    /// seconds a claimed job stays a worker's without a heartbeat; a worker that dies
    /// loses it after this and the job is claimed again
    pub lease_s: f64,
    /// seconds an idle worker waits for news of work (NOTIFY) before looking anyway
    pub poll_s: f64,
}

impl JournalSection {
    /// The URL as it may be shown: any password replaced by `***`.
    pub fn shown_url(&self) -> Option<String> {
        let u = self.url.as_ref()?;
        let Some((scheme, rest)) = u.split_once("://") else {
            return Some(u.clone());
        };
        let (auth, host) = match rest.rsplit_once('@') {
            Some((a, h)) => (a, h),
            None => return Some(u.clone()),
        };
        Some(match auth.split_once(':') {
            Some((user, _)) => format!("{scheme}://{user}:***@{host}"),
            None => u.clone(),
        })
    }
}

impl Default for JournalSection {
    fn default() -> Self {
        JournalSection {
            url: None,
            lease_s: 30.0,
            poll_s: 10.0,
        }
    }
}

/// `[worker]`: a `conformd worker` on a machine of its own.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorkerSection {
    /// its name in the journal and on the status page (default: host and process id)
    pub name: Option<String>,
    /// jobs at once (0: half the machine's cores, at least one)
    pub jobs: usize,
    /// the program each job runs, the daemon's own and a worker's, as `PROGRAM process
    /// <capture> --config <this file> --out <results> --json --stage` (default: this
    /// conformd); a wrapper (nice, a container) may stand in
    pub program: Option<PathBuf>,
}

impl Default for WorkerSection {
    fn default() -> Self {
        WorkerSection {
            name: None,
            jobs: 1,
            program: None,
        }
    }
}

/// A whole station file, checked, with paths made absolute against its folder.
#[derive(Debug, Clone, serde::Serialize)]
pub struct StationConfig {
    pub file: PathBuf,
    pub station: StationSection,
    pub template: Option<TemplateSource>,
    pub conform: ConformOptions,
    pub rig: Option<RigSection>,
    pub capture: Option<CaptureSection>,
    pub cameras: Vec<CameraSection>,
    pub trigger: Option<TriggerSection>,
    pub model: ModelSection,
    pub measure: MeasureSection,
    pub daemon: DaemonSection,
    pub journal: JournalSection,
    pub worker: WorkerSection,
}

/// One problem in a station file; `line` is 1-based.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ConfigProblem {
    pub line: Option<usize>,
    pub msg: String,
}

/// Every problem found in a station file, each with its line when known.
#[derive(Debug, thiserror::Error)]
pub struct ConfigError {
    pub path: String,
    pub problems: Vec<ConfigProblem>,
}

impl std::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.problems.len() > 1 {
            write!(f, "{}: {} problems", self.path, self.problems.len())?;
        }
        for (i, p) in self.problems.iter().enumerate() {
            let sep = if self.problems.len() > 1 {
                "\n  "
            } else if i > 0 {
                "\n"
            } else {
                ""
            };
            match p.line {
                Some(l) if self.problems.len() > 1 => write!(f, "{sep}line {l}: {}", p.msg)?,
                Some(l) => write!(f, "{}:{l}: {}", self.path, p.msg)?,
                None if self.problems.len() > 1 => write!(f, "{sep}{}", p.msg)?,
                None => write!(f, "{}: {}", self.path, p.msg)?,
            }
        }
        Ok(())
    }
}

const SECTIONS: [&str; 12] = [
    "station", "template", "conform", "rig", "capture", "cameras", "trigger", "model", "measure",
    "daemon", "journal", "worker",
];

/// True when a TOML table is a station file (it has one of the station's sections)
/// rather than, say, a bare `conform.toml`.
pub fn is_station_file(table: &toml::Table) -> bool {
    SECTIONS.iter().any(|k| table.contains_key(*k))
}

/// Largest station file read.
const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// 1-based line of a byte offset.
fn line_of(text: &str, offset: usize) -> usize {
    text[..offset.min(text.len())].matches('\n').count() + 1
}

/// Deserializes the top-level table `key` of `text` alone (other tables are skipped), so
/// each section's errors come with their place in the whole file.
fn section<T: DeserializeOwned>(text: &str, key: &str) -> Result<Option<T>, toml::de::Error> {
    struct Pick<'k, T>(&'k str, std::marker::PhantomData<T>);
    impl<'de, T: DeserializeOwned> Visitor<'de> for Pick<'_, T> {
        type Value = Option<T>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a table")
        }
        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Option<T>, A::Error> {
            let mut out = None;
            while let Some(k) = map.next_key::<String>()? {
                if k == self.0 {
                    out = Some(map.next_value::<T>()?);
                } else {
                    map.next_value::<IgnoredAny>()?;
                }
            }
            Ok(out)
        }
    }
    use serde::Deserializer as _;
    toml::de::Deserializer::parse(text)?.deserialize_map(Pick(key, std::marker::PhantomData))
}

impl StationConfig {
    /// Reads and checks a station file.
    ///
    /// Example: `conformd check config/station.example.toml`; see `tests/pipeline.rs`.
    pub fn load(path: &Path) -> Result<StationConfig, ConfigError> {
        let name = path.display().to_string();
        let fail = |msg: String| ConfigError {
            path: name.clone(),
            problems: vec![ConfigProblem { line: None, msg }],
        };
        let text = crate::files::read_text_limited(path, MAX_CONFIG_BYTES).map_err(|e| {
            let msg = e.to_string();
            fail(
                msg.strip_prefix(&format!("{name}: "))
                    .unwrap_or(&msg)
                    .into(),
            )
        })?;
        Self::parse(&text, path)
    }

    /// Checks the text of a station file that lives at `path` (paths in it are taken from
    /// its folder).
    pub fn parse(text: &str, path: &Path) -> Result<StationConfig, ConfigError> {
        let mut problems = Vec::new();
        let mut add = |line: Option<usize>, msg: String| problems.push(ConfigProblem { line, msg });
        // syntax first: every error the parser can recover from
        let (doc, syntax) = toml::de::DeTable::parse_recoverable(text);
        for e in &syntax {
            add(
                e.span().map(|s| line_of(text, s.start)),
                e.message().to_string(),
            );
        }
        if !syntax.is_empty() {
            return Err(ConfigError {
                path: path.display().to_string(),
                problems,
            });
        }
        let mut header = std::collections::BTreeMap::new();
        for (k, _) in doc.get_ref().iter() {
            let key: &str = k.get_ref();
            let line = line_of(text, k.span().start);
            header.insert(key.to_string(), line);
            if !SECTIONS.contains(&key) {
                add(
                    Some(line),
                    format!(
                        "unknown section or key '{}' (sections: {})",
                        key.escape_default(),
                        SECTIONS.join(", ")
                    ),
                );
            }
        }
        let at = |k: &str| header.get(k).copied();
        macro_rules! read {
            ($key:literal, $t:ty) => {
                match section::<$t>(text, $key) {
                    Ok(v) => v,
                    Err(e) => {
                        let line = e.span().map(|s| line_of(text, s.start));
                        let quoted = line
                            .and_then(|l| text.lines().nth(l - 1))
                            .map(|l| {
                                format!(" (`{}`)", l.trim().chars().take(60).collect::<String>())
                            })
                            .unwrap_or_default();
                        add(
                            line.or(at($key)),
                            format!("[{}]: {}{quoted}", $key, e.message()),
                        );
                        None
                    }
                }
            };
        }
        let station: StationSection = read!("station", StationSection).unwrap_or_default();
        let template = read!("template", TemplateSource);
        let conform: ConformOptions = read!("conform", ConformOptions).unwrap_or_default();
        let rig = read!("rig", RigSection);
        let capture = read!("capture", CaptureSection);
        let cameras: Vec<CameraSection> = read!("cameras", Vec<CameraSection>).unwrap_or_default();
        let trigger = read!("trigger", TriggerSection);
        let model: ModelSection = read!("model", ModelSection).unwrap_or_default();
        let measure: MeasureSection = read!("measure", MeasureSection).unwrap_or_default();
        let daemon: DaemonSection = read!("daemon", DaemonSection).unwrap_or_default();
        let journal: JournalSection = read!("journal", JournalSection).unwrap_or_default();
        let worker: WorkerSection = read!("worker", WorkerSection).unwrap_or_default();
        if doc.get_ref().is_empty() {
            add(
                None,
                "the station file is empty: it needs at least [station], and [template] and [rig] to process captures (see config/station.example.toml)".into(),
            );
        }
        let mut cfg = StationConfig {
            // absolute, so paths resolved against its folder are absolute too
            file: std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf()),
            station,
            template,
            conform,
            rig,
            capture,
            cameras,
            trigger,
            model,
            measure,
            daemon,
            journal,
            worker,
        };
        for (key, msg) in cfg.problems() {
            add(at(key), msg);
        }
        if !problems.is_empty() {
            problems.sort_by_key(|p| p.line.unwrap_or(usize::MAX));
            return Err(ConfigError {
                path: path.display().to_string(),
                problems,
            });
        }
        cfg.resolve_paths();
        Ok(cfg)
    }

    /// What the types cannot check, each with the section whose header line it is
    /// reported at.
    fn problems(&self) -> Vec<(&'static str, String)> {
        let mut out: Vec<(&'static str, String)> = Vec::new();
        if self.station.data.as_os_str().is_empty() {
            let msg = "[station]: data = \"\" names no folder; give the folder for captures/, \
                       incoming/ and results/ (\".\" for the station file's own)";
            out.push(("station", msg.into()));
        }
        if let Some(c) = &self.capture
            && !(c.options.max_skew_ms >= 0.0 && c.options.max_skew_ms <= 10_000.0)
        {
            out.push((
                "capture",
                format!(
                    "[capture]: max_skew_ms = {} is not 0 to 10000",
                    c.options.max_skew_ms
                ),
            ));
        }
        if self.worker.jobs > 256 {
            out.push(("worker", "[worker]: jobs must be at most 256".into()));
        }
        if let Err(e) = self.conform.validate() {
            out.push(("conform", format!("[conform]: {e}")));
        }
        if let Some(t) = &self.template
            && let Err(e) = t.check()
        {
            out.push(("template", format!("[template]: {e}")));
        }
        if let Err(e) = crate::paths::check_plain_name("station name", &self.station.name) {
            out.push(("station", format!("[station]: {e}")));
        }
        let mut ids = std::collections::BTreeSet::new();
        for c in &self.cameras {
            if let Err(e) = c.check() {
                out.push(("cameras", format!("[[cameras]]: {e}")));
            }
            if !ids.insert(&c.id) {
                out.push((
                    "cameras",
                    format!("[[cameras]]: two cameras have the id '{}'", c.id),
                ));
            }
        }
        if self.capture.is_some() && self.cameras.is_empty() {
            out.push(("capture", "[[cameras]]: no camera is configured".into()));
        }
        out.extend(self.journal.problems().into_iter().map(|m| ("journal", m)));
        out.extend(self.daemon.problems().into_iter().map(|m| ("daemon", m)));
        out
    }

    /// The config as it may be printed: the journal URL's password and the API token
    /// replaced by `***`.
    pub fn shown(&self) -> StationConfig {
        let mut c = self.clone();
        c.journal.url = self.journal.shown_url();
        if c.daemon.token.is_some() {
            c.daemon.token = Some("***".into());
        }
        c
    }

    /// Makes every relative path absolute against the file's folder.
    fn resolve_paths(&mut self) {
        let base = self.file.parent().unwrap_or(Path::new(".")).to_path_buf();
        let abs = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        abs(&mut self.station.data);
        if let Some(t) = &mut self.template {
            t.resolve(&base);
        }
        if let Some(r) = &mut self.rig {
            abs(&mut r.file);
            r.calibration.iter_mut().for_each(abs);
        }
        if let Some(c) = &mut self.capture {
            c.root.iter_mut().for_each(abs);
        }
        for c in &mut self.cameras {
            c.replay.iter_mut().flatten().for_each(abs);
        }
        self.model.file.iter_mut().for_each(abs);
        self.worker.program.iter_mut().for_each(abs);
        for p in [
            &mut self.measure.definitions,
            &mut self.measure.posture_model,
            &mut self.measure.weight,
        ] {
            p.iter_mut().for_each(abs);
        }
    }

    /// The rig part, for capture sessions: `[capture]`, `[trigger]`, `[[cameras]]`.
    /// Captures go to `[capture] root`, else the station's `captures/`.
    pub fn rig_config(&self) -> Result<RigConfig, ConfigError> {
        let fail = |msg: &str| ConfigError {
            path: self.file.display().to_string(),
            problems: vec![ConfigProblem {
                line: None,
                msg: msg.into(),
            }],
        };
        let mut capture = self
            .capture
            .clone()
            .ok_or_else(|| fail("no [capture] section: this station does not capture"))?;
        if self.cameras.is_empty() {
            return Err(fail("[[cameras]]: no camera is configured"));
        }
        let root = capture
            .root
            .clone()
            .unwrap_or_else(|| self.station.captures());
        capture.root = Some(root.clone());
        if capture.options.station == crate::devices::capture::CaptureOptions::default().station {
            capture.options.station = self.station.name.clone();
        }
        Ok(RigConfig {
            root,
            capture,
            trigger: self.trigger.clone(),
            cameras: self.cameras.clone(),
        })
    }
}

impl JournalSection {
    fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        if let Some(u) = &self.url {
            if !(u.starts_with("postgres://") || u.starts_with("postgresql://")) {
                out.push("[journal]: url must start with postgres:// or postgresql://".into());
            } else if let Err(e) = u.parse::<postgres::Config>() {
                // the driver's own reading, so what passes here connects the same way;
                // the URL is not quoted: it may hold a password
                out.push(format!(
                    "[journal]: url is not a PostgreSQL connection URL: {e}"
                ));
            }
        }
        let within = |v: f64, lo: f64, hi: f64| (lo..=hi).contains(&v);
        if !within(self.lease_s, 2.0, 3600.0) || !within(self.poll_s, 0.1, 3600.0) {
            out.push(format!(
                "[journal]: lease_s = {} must be 2 to 3600 and poll_s = {} 0.1 to 3600",
                self.lease_s, self.poll_s
            ));
        }
        out
    }
}

impl DaemonSection {
    fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !(self.rescan_s >= 0.5 && self.rescan_s <= 86_400.0) {
            out.push(format!(
                "[daemon]: rescan_s = {} is not 0.5 to 86400",
                self.rescan_s
            ));
        }
        if !(self.job_timeout_s >= 1.0 && self.job_timeout_s <= 86_400.0) {
            out.push(format!(
                "[daemon]: job_timeout_s = {} is not 1 to 86400",
                self.job_timeout_s
            ));
        }
        if !(0.0..=3600.0).contains(&self.drain_s) {
            out.push(format!(
                "[daemon]: drain_s = {} is not 0 to 3600",
                self.drain_s
            ));
        }
        if !(1..=100).contains(&self.max_attempts) || self.workers > 256 {
            out.push("[daemon]: max_attempts must be 1 to 100, workers at most 256".into());
        }
        match self.listen.parse::<std::net::SocketAddr>() {
            Err(_) => out.push(format!(
                "[daemon]: listen = '{}' is not an address:port",
                self.listen
            )),
            Ok(a)
                if !a.ip().is_loopback()
                    && self
                        .token
                        .as_deref()
                        .unwrap_or("")
                        .chars()
                        .filter(|c| !c.is_whitespace())
                        .count()
                        < 16 =>
            {
                out.push(format!(
                    "[daemon]: listening on {a}, beyond this machine, needs a token of 16 or more characters other than spaces"
                ))
            }
            Ok(_) => {}
        }
        out
    }
}
