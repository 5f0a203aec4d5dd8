//! The daemon's HTTP side (axum): the JSON API, Prometheus metrics, and the status page a
//! station operator leaves open. Mutating calls need the configured bearer token; ids are
//! plain names; bodies are small.

use super::journal::{Job, State};
use super::{BUCKETS, CaptureRequest, Shared};
use crate::files::DataDir;
use crate::station::pipeline::PlacedLandmark;
use crate::station::review::{Review, Verdict};
use axum::Router;
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State as Ctx};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use std::fmt::Write as _;
use std::sync::Arc;

/// Largest request body (trigger requests carry a subject id at most).
pub const MAX_BODY: usize = 4096;

pub fn router(shared: Arc<Shared>) -> Router {
    let mutating = Router::new()
        .route("/api/trigger", post(trigger))
        .route("/api/captures/{id}/reprocess", post(reprocess))
        .route("/api/captures/{id}/review", post(review))
        .route("/api/captures/{id}/landmarks", post(place_landmarks))
        .route("/api/model/rebuild", post(rebuild))
        .route_layer(middleware::from_fn_with_state(
            shared.clone(),
            require_token,
        ));
    Router::new()
        .route("/", get(page))
        .route("/captures/{id}", get(capture_page))
        .route("/subjects/{tag}", get(subject_page))
        .route("/subjects/{tag}/history.png", get(subject_plot))
        .route("/api/subjects/{tag}", get(subject_api))
        .route("/api/export.csv", get(export))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/metrics", get(metrics))
        .route("/api/status", get(status))
        .route("/api/captures", get(list))
        .route("/api/captures/{id}", get(capture))
        .route("/api/captures/{id}/{file}", get(capture_file))
        .route("/static/viewer.js", get(viewer_js))
        .route("/static/three/{file}", get(three_js))
        .merge(mutating)
        .layer(DefaultBodyLimit::max(MAX_BODY))
        .with_state(shared)
}

/// Longest a client may take to send a request's headers, counted from the connection's
/// first byte or from the end of its last response: a half-sent request or an idle
/// keep-alive connection is closed after it (a browser sends its headers at once).
pub const HEADER_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);
/// Most connections open at once, well below the unit's `LimitNOFILE` (4096): past it,
/// new connections wait in the kernel's queue until one closes, instead of taking the
/// descriptors the journal, the camera and the jobs need.
pub const MAX_CONNECTIONS: usize = 512;

/// Serves `app` on `listener` until `stop` resolves: every connection with
/// [`HEADER_TIMEOUT`], at most [`MAX_CONNECTIONS`] at once; then lets the requests in
/// flight finish and returns once every connection is closed.
pub async fn serve(
    listener: tokio::net::TcpListener,
    app: Router,
    stop: impl std::future::Future<Output = ()>,
) {
    let permits = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    let (closing, closing_rx) = tokio::sync::watch::channel(false);
    let mut connections = tokio::task::JoinSet::new();
    tokio::pin!(stop);
    loop {
        let permit = tokio::select! {
            p = permits.clone().acquire_owned() => p.expect("the semaphore is never closed"),
            _ = &mut stop => break,
        };
        let stream = tokio::select! {
            r = listener.accept() => match r {
                Ok((stream, _)) => stream,
                Err(e) => {
                    // out of descriptors, or the peer gave up: not the server's end
                    tracing::warn!(error = %e, "accepting an HTTP connection failed");
                    tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                    continue;
                }
            },
            _ = &mut stop => break,
        };
        let service = hyper_util::service::TowerToHyperService::new(app.clone());
        let mut closing = closing_rx.clone();
        connections.spawn(async move {
            let _permit = permit;
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(hyper_util::rt::TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT);
            let conn = builder.serve_connection(hyper_util::rt::TokioIo::new(stream), service);
            tokio::pin!(conn);
            tokio::select! {
                _ = conn.as_mut() => {}
                _ = closing.changed() => {
                    conn.as_mut().graceful_shutdown();
                    let _ = conn.await;
                }
            }
        });
        while connections.try_join_next().is_some() {}
    }
    let _ = closing.send(true);
    while connections.join_next().await.is_some() {}
}

struct ApiError(StatusCode, String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, axum::Json(serde_json::json!({ "error": self.1 }))).into_response()
    }
}

type Api<T> = Result<T, ApiError>;

fn internal(e: impl std::fmt::Display) -> ApiError {
    ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string())
}

fn checked_id(id: &str) -> Api<()> {
    crate::paths::check_plain_name("capture id", id)
        .map_err(|e| ApiError(StatusCode::BAD_REQUEST, e.to_string()))
}

fn job_or_404(shared: &Shared, id: &str) -> Api<Job> {
    checked_id(id)?;
    shared
        .journal()
        .get(id)
        .map_err(internal)?
        .ok_or_else(|| ApiError(StatusCode::NOT_FOUND, format!("no capture '{id}'")))
}

async fn require_token(
    Ctx(shared): Ctx<Arc<Shared>>,
    headers: HeaderMap,
    req: Request,
    next: Next,
) -> Response {
    // only POSTs change anything; other methods go on to their 405
    let mutating = req.method() == axum::http::Method::POST;
    if mutating && let Some(refused) = cross_site(&headers) {
        return refused.into_response();
    }
    if let Some(token) = shared.cfg.daemon.token.as_ref().filter(|_| mutating) {
        let given = headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        let ok = given.is_some_and(|g| {
            g.len() == token.len()
                && g.bytes()
                    .zip(token.bytes())
                    .fold(0u8, |acc, (a, b)| acc | (a ^ b))
                    == 0
        });
        if !ok {
            let mut r = ApiError(
                StatusCode::UNAUTHORIZED,
                "this call needs 'Authorization: Bearer <token>' with the station's token".into(),
            )
            .into_response();
            r.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
            return r;
        }
    }
    next.run(req).await
}

/// Refuses a state-changing request that a page of another site, open in the operator's
/// browser, could have sent: its body must be declared JSON (a page can send a form or
/// plain text to any site, but JSON only after asking the station, which never agrees),
/// and an `Origin` or `Sec-Fetch-Site` header must say it came from the station's own
/// pages. Clients that are not browsers send neither header.
fn cross_site(headers: &HeaderMap) -> Option<ApiError> {
    let text = |name: header::HeaderName| headers.get(name).map(|v| v.to_str().unwrap_or("?"));
    let content_type = text(header::CONTENT_TYPE).unwrap_or("");
    let media = content_type.split(';').next().unwrap_or("").trim();
    if !media.eq_ignore_ascii_case("application/json") {
        return Some(ApiError(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            format!(
                "this call takes 'Content-Type: application/json' (the request had {}), even with no body",
                if content_type.is_empty() {
                    "none".to_string()
                } else {
                    format!("'{}'", content_type.escape_default())
                }
            ),
        ));
    }
    if let Some(origin) = text(header::ORIGIN) {
        let host = text(header::HOST).unwrap_or("");
        let own = !host.is_empty()
            && (origin == format!("http://{host}") || origin == format!("https://{host}"));
        if !own {
            return Some(ApiError(
                StatusCode::FORBIDDEN,
                format!(
                    "a request from a page of another site (Origin '{}') cannot change this station",
                    origin.escape_default()
                ),
            ));
        }
    }
    if text(header::HeaderName::from_static("sec-fetch-site")) == Some("cross-site") {
        return Some(ApiError(
            StatusCode::FORBIDDEN,
            "a request from a page of another site (Sec-Fetch-Site: cross-site) cannot change this station".into(),
        ));
    }
    None
}

#[derive(serde::Serialize)]
struct JournalStatus {
    store: String,
    online: bool,
    /// since when, and why, it cannot be reached
    offline_since: Option<f64>,
    error: Option<String>,
    /// capture sets in `captures/` to hand over when it is back
    waiting_handover: Vec<String>,
}

#[derive(serde::Serialize)]
struct Status {
    station: String,
    uptime_s: f64,
    journal: JournalStatus,
    queue: super::journal::Counts,
    running: Vec<String>,
    /// jobs this daemon runs at once (0: none, other machines' workers run them)
    workers: usize,
    /// every worker of the journal (this daemon's own and other machines'), from their
    /// heartbeats
    worker_list: Vec<super::journal::WorkerInfo>,
    stopping: bool,
    rig: super::RigStatus,
    free_disk_bytes: Option<u64>,
    model: Option<String>,
    model_exists: bool,
    model_rebuilding: bool,
    model_error: Option<String>,
    /// entries of `captures/` and `incoming/` the station will not take, with why
    not_taken: Vec<NotTaken>,
    /// scans of the capture folders since start-up
    scans: u64,
    /// newest results whose fit warned of distortion, not yet accepted or rejected
    awaiting_review: Vec<AwaitingReview>,
}

#[derive(serde::Serialize)]
struct NotTaken {
    /// `captures/<name>` or `incoming/<name>`
    entry: String,
    reason: String,
}

fn status_of(shared: &Shared) -> Api<Status> {
    // an unreachable journal is a state to show, not an error of this page
    let (queue, worker_list, store) = {
        let mut j = shared.journal();
        let q = j.counts();
        let w = j.workers();
        (q, w, j.describe())
    };
    let queue = shared.journal_result(queue).unwrap_or_default();
    let worker_list = shared.journal_result(worker_list).unwrap_or_default();
    let offline = shared.journal_offline.lock().ok().and_then(|o| o.clone());
    let journal = JournalStatus {
        store,
        online: offline.is_none(),
        offline_since: offline.as_ref().map(|o| o.0),
        error: offline.map(|o| o.1),
        waiting_handover: shared
            .waiting_handover
            .lock()
            .map(|w| w.iter().cloned().collect())
            .unwrap_or_default(),
    };
    let running = shared
        .running
        .lock()
        .map(|r| r.keys().cloned().collect())
        .unwrap_or_default();
    let model = shared.cfg.model.file.clone();
    Ok(Status {
        station: shared.cfg.station.name.clone(),
        uptime_s: shared.uptime(),
        journal,
        queue,
        running,
        workers: if shared.cfg.daemon.local_workers {
            shared.workers
        } else {
            0
        },
        worker_list,
        stopping: shared.stopping.load(std::sync::atomic::Ordering::SeqCst),
        rig: shared.rig.lock().map(|r| r.clone()).unwrap_or_default(),
        free_disk_bytes: fs4::available_space(&shared.cfg.station.data).ok(),
        model_exists: model.as_ref().is_some_and(|m| m.exists()),
        model: model.map(|m| m.display().to_string()),
        model_rebuilding: shared.model_busy.load(std::sync::atomic::Ordering::SeqCst),
        model_error: shared.model_error.lock().ok().and_then(|e| e.clone()),
        not_taken: shared
            .refused
            .lock()
            .map(|r| {
                r.iter()
                    .map(|(entry, reason)| NotTaken {
                        entry: entry.clone(),
                        reason: reason.clone(),
                    })
                    .collect()
            })
            .unwrap_or_default(),
        awaiting_review: awaiting_review(shared),
        scans: shared.scans.load(std::sync::atomic::Ordering::SeqCst),
    })
}

async fn status(Ctx(shared): Ctx<Arc<Shared>>) -> Api<axum::Json<Status>> {
    Ok(axum::Json(status_of(&shared)?))
}

#[derive(serde::Deserialize)]
struct ListQuery {
    state: Option<String>,
    limit: Option<usize>,
}

async fn list(
    Ctx(shared): Ctx<Arc<Shared>>,
    Query(q): Query<ListQuery>,
) -> Api<axum::Json<Vec<Job>>> {
    let state = match q.state.as_deref() {
        None | Some("") => None,
        Some(s) => Some(State::parse(s).ok_or_else(|| {
            ApiError(
                StatusCode::BAD_REQUEST,
                format!("state '{s}': expected queued, running, done or failed"),
            )
        })?),
    };
    let limit = q.limit.unwrap_or(100).min(10_000);
    Ok(axum::Json(
        shared.journal().list(state, limit).map_err(internal)?,
    ))
}

#[derive(serde::Serialize)]
struct CaptureDetail {
    #[serde(flatten)]
    job: Job,
    manifest: Option<serde_json::Value>,
    report: Option<serde_json::Value>,
    /// the operator's verdict on the result, when given
    review: Option<Review>,
    /// the scan landmarks an operator placed for this capture (its next fits use them)
    placed_landmarks: Option<Vec<PlacedLandmark>>,
}

/// A JSON file of a capture or result, None when it is missing or not JSON.
fn read_json(dir: &DataDir, name: &str) -> Option<serde_json::Value> {
    serde_json::from_slice(&dir.read(name, crate::files::MAX_REPORT_BYTES).ok()?).ok()
}

/// A capture's or result's folder inside the data folder, reached without following a
/// link: 404 when it is gone, 409 when a link or a file stands in its place.
fn data_dir(shared: &Shared, dir: &std::path::Path) -> Api<DataDir> {
    DataDir::open(&shared.cfg.station.data, dir).map_err(|e| match &e {
        crate::files::FileError::Io { source, .. }
            if source.kind() == std::io::ErrorKind::NotFound =>
        {
            ApiError(StatusCode::NOT_FOUND, format!("{e}: the folder is gone"))
        }
        crate::files::FileError::Content { .. } => ApiError(StatusCode::CONFLICT, e.to_string()),
        _ => internal(e),
    })
}

/// Results that await an operator's review: the newest [`REVIEW_SCAN`] finished ones
/// whose fit warned (of distortion, or of a placement in doubt) and that nobody has
/// accepted or rejected yet.
fn awaiting_review(shared: &Shared) -> Vec<AwaitingReview> {
    let done = shared.journal().list(Some(State::Done), REVIEW_SCAN);
    let done = shared.journal_result(done).unwrap_or_default();
    done.into_iter()
        .filter_map(|j| {
            let dir = data_dir(shared, &j.result?).ok()?;
            if dir.has(crate::station::review::REVIEW_FILE) {
                return None;
            }
            let report = read_json(&dir, "report.json")?;
            let warnings = fit_warnings(&report["conformation"]);
            (!warnings.is_empty()).then(|| AwaitingReview {
                capture: j.id,
                warning: warnings.join("; "),
            })
        })
        .collect()
}

/// The warnings of a report's `conformation`: distortion, then a placement in doubt.
fn fit_warnings(c: &serde_json::Value) -> Vec<&str> {
    ["distortion_warning", "placement_warning"]
        .iter()
        .filter_map(|k| c[*k].as_str())
        .collect()
}

/// How many of the newest results the awaiting-review list looks at (the status page
/// reloads every 5 s; older results are reviewed through their own page or the API).
const REVIEW_SCAN: usize = 200;

#[derive(serde::Serialize)]
struct AwaitingReview {
    capture: String,
    /// the fit's warnings (distortion, a placement in doubt)
    warning: String,
}

fn detail(shared: &Shared, id: &str) -> Api<CaptureDetail> {
    let job = job_or_404(shared, id)?;
    let manifest = data_dir(shared, &job.dir)
        .ok()
        .and_then(|d| read_json(&d, "manifest.json"));
    let result = job.result.as_ref().and_then(|r| data_dir(shared, r).ok());
    let report = result.as_ref().and_then(|d| read_json(d, "report.json"));
    let review = result
        .as_ref()
        .and_then(|d| crate::station::review::read_in(d).ok().flatten());
    let placed_landmarks = read_placed(shared, id);
    Ok(CaptureDetail {
        job,
        manifest,
        report,
        review,
        placed_landmarks,
    })
}

async fn capture(
    Ctx(shared): Ctx<Arc<Shared>>,
    Path(id): Path<String>,
) -> Api<axum::Json<CaptureDetail>> {
    Ok(axum::Json(detail(&shared, &id)?))
}

async fn capture_file(
    Ctx(shared): Ctx<Arc<Shared>>,
    Path((id, file)): Path<(String, String)>,
) -> Api<Response> {
    let job = job_or_404(&shared, &id)?;
    let kind = match file.as_str() {
        "preview.png" => "image/png",
        "report.json" | crate::station::view::VIEW_FILE => "application/json",
        "scan.ply" | "conformed.ply" => "application/octet-stream",
        _ => {
            return Err(ApiError(
                StatusCode::NOT_FOUND,
                format!(
                    "'{file}': a result has preview.png, report.json, scan.ply, conformed.ply and view.json"
                ),
            ));
        }
    };
    let dir = job.result.ok_or_else(|| {
        ApiError(
            StatusCode::NOT_FOUND,
            format!("capture '{id}' has no result yet"),
        )
    })?;
    let bytes = tokio::task::spawn_blocking(move || {
        data_dir(&shared, &dir)?
            .read(&file, crate::mesh::io::MAX_MESH_BYTES)
            .map_err(|e| ApiError(StatusCode::NOT_FOUND, e.to_string()))
    })
    .await
    .map_err(internal)??;
    Ok(([(header::CONTENT_TYPE, kind)], bytes).into_response())
}

/// The capture page's 3D viewer (`viewer.js`, built into the binary).
async fn viewer_js() -> Response {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        include_str!("viewer.js"),
    )
        .into_response()
}

/// Where Debian's libjs-three puts three.js: the viewer uses the system's copy, which
/// the distribution keeps patched, rather than one built into the binary.
pub const THREE_DIR: &str = "/usr/share/javascript/three";

/// The three files of three.js the viewer loads, from [`THREE_DIR`].
async fn three_js(Path(file): Path<String>) -> Api<Response> {
    let rel = match file.as_str() {
        "three.min.js" => "build/three.min.js",
        "OrbitControls.js" => "examples/js/controls/OrbitControls.js",
        "PLYLoader.js" => "examples/js/loaders/PLYLoader.js",
        _ => {
            return Err(ApiError(
                StatusCode::NOT_FOUND,
                format!(
                    "'{file}': the viewer serves three.min.js, OrbitControls.js and PLYLoader.js"
                ),
            ));
        }
    };
    let path = std::path::Path::new(THREE_DIR).join(rel);
    let bytes = tokio::task::spawn_blocking(move || {
        crate::files::read_limited(&path, crate::files::MAX_REPORT_BYTES)
    })
    .await
    .map_err(internal)?
    .map_err(|e| {
        ApiError(
            StatusCode::NOT_FOUND,
            format!("{e}: the 3D view needs Debian's libjs-three (apt-get install libjs-three)"),
        )
    })?;
    Ok((
        [
            (header::CONTENT_TYPE, "text/javascript; charset=utf-8"),
            (header::CACHE_CONTROL, "max-age=86400"),
        ],
        bytes,
    )
        .into_response())
}

#[derive(serde::Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct TriggerBody {
    subject: Option<String>,
}

async fn trigger(Ctx(shared): Ctx<Arc<Shared>>, body: axum::body::Bytes) -> Api<Response> {
    let req: TriggerBody = if body.is_empty() {
        TriggerBody::default()
    } else {
        json_body(&body, r#"{"subject": "ID"} or no body"#)?
    };
    if let Some(s) = &req.subject {
        crate::paths::check_plain_name("subject", s)
            .map_err(|e| ApiError(StatusCode::BAD_REQUEST, e.to_string()))?;
    }
    let tx = shared.capture.as_ref().ok_or_else(|| {
        ApiError(
            StatusCode::CONFLICT,
            "this station has no [capture] section: it only processes sets dropped into incoming/"
                .into(),
        )
    })?;
    let (reply, answer) = tokio::sync::oneshot::channel();
    tx.send(CaptureRequest {
        subject: req.subject,
        reply: Some(reply),
    })
    .map_err(|_| ApiError(StatusCode::SERVICE_UNAVAILABLE, "the rig is stopped".into()))?;
    match tokio::time::timeout(std::time::Duration::from_secs(60), answer).await {
        Ok(Ok(Ok(id))) => Ok((
            StatusCode::CREATED,
            axum::Json(serde_json::json!({ "capture": id })),
        )
            .into_response()),
        Ok(Ok(Err(e))) => Err(ApiError(StatusCode::SERVICE_UNAVAILABLE, e.to_string())),
        _ => Err(ApiError(
            StatusCode::SERVICE_UNAVAILABLE,
            "the rig did not answer".into(),
        )),
    }
}

/// A request body as `T`, or a 400 saying what was `expected` and what was wrong. The
/// body must be a JSON object: serde would take `["accepted"]` for a struct too.
fn json_body<T: serde::de::DeserializeOwned>(body: &[u8], expected: &str) -> Api<T> {
    let bad = |e: String| ApiError(StatusCode::BAD_REQUEST, format!("expected {expected}: {e}"));
    let value: serde_json::Value = serde_json::from_slice(body).map_err(|e| bad(e.to_string()))?;
    if !value.is_object() {
        return Err(bad(format!(
            "the body is {}, not an object",
            json_kind(&value)
        )));
    }
    serde_json::from_value(value).map_err(|e| bad(e.to_string()))
}

fn json_kind(v: &serde_json::Value) -> &'static str {
    match v {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

/// The result folder of a finished `job`, or a 409 saying `why` one is needed.
fn finished_result(job: Job, why: &str) -> Api<std::path::PathBuf> {
    match (job.state, job.result) {
        (State::Done, Some(dir)) => Ok(dir),
        (state, _) => Err(ApiError(
            StatusCode::CONFLICT,
            format!("capture '{}' is {}: {why}", job.id, state.as_str()),
        )),
    }
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ReviewBody {
    verdict: Verdict,
    #[serde(default)]
    reason: Option<String>,
}

/// An operator accepts or rejects a finished result (a rejection with its reason); a
/// rejected result is left out of the export, the weight fit and model rebuilds.
async fn review(
    Ctx(shared): Ctx<Arc<Shared>>,
    Path(id): Path<String>,
    body: axum::body::Bytes,
) -> Api<Response> {
    let job = job_or_404(&shared, &id)?;
    let req: ReviewBody = json_body(
        &body,
        r#"{"verdict": "accepted"} or {"verdict": "rejected", "reason": "..."}"#,
    )?;
    let review = Review::new(req.verdict, req.reason, super::journal::now())
        .map_err(|e| ApiError(StatusCode::BAD_REQUEST, e.to_string()))?;
    let dir = finished_result(job, "only a finished result can be reviewed")?;
    let written = review.clone();
    let ctx = shared.clone();
    tokio::task::spawn_blocking(move || {
        crate::station::review::write_in(&data_dir(&ctx, &dir)?, &written).map_err(internal)
    })
    .await
    .map_err(internal)??;
    tracing::info!(capture = %id, verdict = ?review.verdict, reason = review.reason.as_deref().unwrap_or(""), "result reviewed");
    Ok(axum::Json(serde_json::json!({ "capture": id, "review": review })).into_response())
}

/// The landmarks an operator placed for capture `id`, None when none were (or their file
/// cannot be read: the job that reads it names why).
fn read_placed(shared: &Shared, id: &str) -> Option<Vec<PlacedLandmark>> {
    // as every file served: inside the data folder, no link followed
    let dir = data_dir(shared, &shared.cfg.station.landmarks()).ok()?;
    let name = format!("{id}.txt");
    let bytes = dir
        .read(&name, crate::mesh::landmarks::MAX_LANDMARK_BYTES)
        .ok()?;
    let lms =
        crate::mesh::landmarks::parse_text(&dir.path().join(&name).display().to_string(), &bytes)
            .ok()?;
    Some(
        lms.into_iter()
            .filter_map(|l| match l.pos {
                crate::mesh::LandmarkPos::Point(p) => Some(PlacedLandmark {
                    name: l.name,
                    position: [p.x, p.y, p.z],
                }),
                crate::mesh::LandmarkPos::Vertex(_) => None,
            })
            .collect(),
    )
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct LandmarksBody {
    landmarks: Vec<PlacedLandmark>,
}

/// An operator's scan landmarks for a finished result: checked against the template's
/// landmark names (the result's view.json) and its scan, kept in `landmarks/<id>.txt`
/// (never in the capture set), and the capture queued again to be fitted by them.
async fn place_landmarks(
    Ctx(shared): Ctx<Arc<Shared>>,
    Path(id): Path<String>,
    body: axum::body::Bytes,
) -> Api<Response> {
    let job = job_or_404(&shared, &id)?;
    let req: LandmarksBody = json_body(
        &body,
        r#"{"landmarks": [{"name": "...", "position": [x, y, z]}, ...]}"#,
    )?;
    let dir = finished_result(job, "landmarks are placed on a finished result's scan")?;
    let (folder, cid, ctx) = (shared.cfg.station.landmarks(), id.clone(), shared.clone());
    let checked = tokio::task::spawn_blocking(move || -> Result<usize, ApiError> {
        let conflict = |e: String| ApiError(StatusCode::CONFLICT, e);
        let result = data_dir(&ctx, &dir)?;
        let view: crate::station::view::View = serde_json::from_slice(
            &result
                .read(crate::station::view::VIEW_FILE, crate::files::MAX_REPORT_BYTES)
            .map_err(|e| {
                conflict(format!(
                    "{e}: this result does not say which landmarks the template has; reprocess it once"
                ))
            })?,
        )
        .map_err(|e| conflict(format!("the result's view.json: {e}")))?;
        let names: Vec<String> = view.landmarks.into_iter().map(|l| l.name).collect();
        if names.is_empty() {
            return Err(conflict(
                "the station's template has no landmarks to place ([template] landmarks)".into(),
            ));
        }
        let scan = result
            .read("scan.ply", crate::mesh::io::MAX_MESH_BYTES)
            .and_then(|b| crate::mesh::io::mesh_from_bytes(&dir.join("scan.ply"), &b))
            .map_err(|e| conflict(e.to_string()))?;
        let lms = crate::station::placed::check(&req.landmarks, &names, &scan)
            .map_err(|e| ApiError(StatusCode::BAD_REQUEST, e.to_string()))?;
        std::fs::create_dir_all(&folder).map_err(|e| {
            conflict(format!(
                "{}: {e}: the station keeps placed landmarks in this folder",
                folder.display()
            ))
        })?;
        let kept = data_dir(&ctx, &folder)?;
        let _one_writer = kept.lock().map_err(internal)?;
        kept.write_atomic(
            &format!("{cid}.txt"),
            crate::station::placed::text(&lms, &cid).as_bytes(),
        )
        .map_err(internal)?;
        Ok(lms.len())
    })
    .await
    .map_err(internal)??;
    if !shared.journal().reprocess(&id).map_err(internal)? {
        return Err(ApiError(
            StatusCode::CONFLICT,
            format!("capture '{id}' is being processed now; its next run uses the landmarks"),
        ));
    }
    shared.wake.notify_one();
    tracing::info!(capture = %id, landmarks = checked, "manual landmarks placed; queued again");
    Ok((
        StatusCode::ACCEPTED,
        axum::Json(serde_json::json!({ "capture": id, "landmarks": checked, "state": "queued" })),
    )
        .into_response())
}

async fn reprocess(Ctx(shared): Ctx<Arc<Shared>>, Path(id): Path<String>) -> Api<Response> {
    job_or_404(&shared, &id)?;
    if !shared.journal().reprocess(&id).map_err(internal)? {
        return Err(ApiError(
            StatusCode::CONFLICT,
            format!("capture '{id}' is being processed now"),
        ));
    }
    shared.wake.notify_one();
    Ok((
        StatusCode::ACCEPTED,
        axum::Json(serde_json::json!({ "capture": id, "state": "queued" })),
    )
        .into_response())
}

async fn rebuild(Ctx(shared): Ctx<Arc<Shared>>) -> Api<Response> {
    if shared.cfg.model.file.is_none() {
        return Err(ApiError(
            StatusCode::CONFLICT,
            "the station file has no [model] file".into(),
        ));
    }
    let started = super::request_model_rebuild(&shared);
    Ok((
        StatusCode::ACCEPTED,
        axum::Json(serde_json::json!({ "rebuilding": true, "already_running": !started })),
    )
        .into_response())
}

async fn metrics(Ctx(shared): Ctx<Arc<Shared>>) -> Api<Response> {
    let c = shared.journal().counts().map_err(internal)?;
    let failures = shared.journal().failures_by_stage().map_err(internal)?;
    let mut s = String::new();
    s.push_str("# HELP conformd_captures Captures in the journal by job state.\n# TYPE conformd_captures gauge\n");
    for (state, n) in [
        ("queued", c.queued),
        ("running", c.running),
        ("done", c.done),
        ("failed", c.failed),
    ] {
        let _ = writeln!(s, "conformd_captures{{state=\"{state}\"}} {n}");
    }
    let _ = writeln!(
        s,
        "# HELP conformd_queue_depth Captures waiting to be processed.\n# TYPE conformd_queue_depth gauge\nconformd_queue_depth {}",
        c.queued
    );
    s.push_str("# HELP conformd_failures Failed captures by the stage that failed.\n# TYPE conformd_failures gauge\n");
    for (stage, n) in failures {
        let _ = writeln!(s, "conformd_failures{{stage=\"{stage}\"}} {n}");
    }
    let m = shared.metrics.lock().map(|m| m.clone()).unwrap_or_default();
    let _ = writeln!(
        s,
        "# HELP conformd_jobs_started_total Jobs started since the daemon started.\n# TYPE conformd_jobs_started_total counter\nconformd_jobs_started_total {}",
        m.jobs_started
    );
    let _ = writeln!(
        s,
        "# HELP conformd_worker_crashes_total Worker processes that died of a signal.\n# TYPE conformd_worker_crashes_total counter\nconformd_worker_crashes_total {}",
        m.worker_crashes
    );
    let _ = writeln!(
        s,
        "# HELP conformd_job_timeouts_total Jobs stopped at their time limit.\n# TYPE conformd_job_timeouts_total counter\nconformd_job_timeouts_total {}",
        m.timeouts
    );
    s.push_str("# HELP conformd_stage_seconds Seconds per pipeline stage of finished jobs.\n# TYPE conformd_stage_seconds histogram\n");
    for (stage, (buckets, sum, count)) in &m.stages {
        for (b, n) in BUCKETS.iter().zip(buckets) {
            let _ = writeln!(
                s,
                "conformd_stage_seconds_bucket{{stage=\"{stage}\",le=\"{b}\"}} {n}"
            );
        }
        let _ = writeln!(
            s,
            "conformd_stage_seconds_bucket{{stage=\"{stage}\",le=\"+Inf\"}} {count}"
        );
        let _ = writeln!(s, "conformd_stage_seconds_sum{{stage=\"{stage}\"}} {sum}");
        let _ = writeln!(
            s,
            "conformd_stage_seconds_count{{stage=\"{stage}\"}} {count}"
        );
    }
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], s).into_response())
}

/// Text for HTML.
fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn when(t: Option<f64>) -> String {
    t.map(|t| {
        crate::devices::capture::utc_stamp(
            std::time::UNIX_EPOCH + std::time::Duration::from_secs_f64(t.max(0.0)),
        )
    })
    .unwrap_or_default()
}

const STYLE: &str = "body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse}td,th{padding:4px 10px;border-bottom:1px solid #ddd;text-align:left;vertical-align:top}.done{color:#176b2c}.failed{color:#b00020}.running{color:#1f4fb4}.queued{color:#666}img{border:1px solid #ccc}";

/// The status page's head and its queue, disk, trigger and model line.
fn head_and_queue(h: &mut String, st: &Status) {
    let _ = write!(
        h,
        "<!doctype html><html><head><meta charset=\"utf-8\"><meta http-equiv=\"refresh\" content=\"5\"><title>conformd: {name}</title><style>{STYLE}</style></head><body><h1>conformd: {name}</h1>",
        name = esc(&st.station)
    );
    let q = &st.queue;
    let _ = write!(
        h,
        "<p id=\"queue\">{} queued, {} running (of {} workers), {} done, {} failed. Free disk: {}. Trigger: {}. Model: {}.</p>",
        q.queued,
        q.running,
        st.workers,
        q.done,
        q.failed,
        st.free_disk_bytes
            .map(|b| format!("{:.1} GB", b as f64 / 1e9))
            .unwrap_or_else(|| "unknown".into()),
        match (&st.rig.trigger, st.rig.trigger_connected) {
            (None, _) => "software (no box)".to_string(),
            (Some(d), true) => format!("{} connected", esc(d)),
            (Some(d), false) => format!("<b>{} not connected</b>", esc(d)),
        },
        if st.model_exists {
            "yes"
        } else {
            "not built yet"
        }
    );
}

/// The latest result's preview, and the journal's state.
fn latest_and_journal(h: &mut String, st: &Status, jobs: &[Job]) {
    if let Some(latest) = jobs.iter().find(|j| j.state == State::Done) {
        let _ = write!(
            h,
            "<h2>Latest result: <a href=\"/captures/{id}\">{id}</a></h2><img id=\"latest-preview\" src=\"/api/captures/{id}/preview.png\" alt=\"preview of {id}\" width=\"640\">",
            id = esc(&latest.id)
        );
    }
    let jr = &st.journal;
    if jr.online {
        let _ = write!(h, "<p id=\"journal\">Journal: {}.</p>", esc(&jr.store));
    } else {
        let _ = write!(
            h,
            "<p id=\"journal\"><b>Journal {} cannot be reached since {}</b> ({}); {} capture(s) wait in captures/ to be handed over when it is back.</p>",
            esc(&jr.store),
            when(jr.offline_since),
            esc(jr.error.as_deref().unwrap_or("")),
            jr.waiting_handover.len()
        );
    }
}

/// Entries the daemon will not process, and the workers sharing the journal.
fn not_taken_and_workers(h: &mut String, st: &Status) {
    if !st.not_taken.is_empty() {
        h.push_str("<h2>Not taken</h2><table id=\"not-taken\"><tr><th>entry</th><th>why it is not processed</th></tr>");
        for n in &st.not_taken {
            let _ = write!(
                h,
                "<tr><td>{}</td><td>{}</td></tr>",
                esc(&n.entry),
                esc(&n.reason)
            );
        }
        h.push_str("</table>");
    }
    if !st.worker_list.is_empty() {
        h.push_str("<h2>Workers</h2><table id=\"workers\"><tr><th>worker</th><th>host</th><th>current job</th><th>jobs done</th><th>last heartbeat</th></tr>");
        let now = super::journal::now();
        for w in &st.worker_list {
            let _ = write!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.0} s ago</td></tr>",
                esc(&w.name),
                esc(&w.host),
                esc(w.job.as_deref().unwrap_or("idle")),
                w.jobs_done,
                (now - w.heartbeat_at).max(0.0)
            );
        }
        h.push_str("</table>");
    }
}

/// The latest captures, one row each.
fn captures_table(h: &mut String, jobs: &[Job]) {
    h.push_str("<h2>Captures</h2><table id=\"captures\"><tr><th>capture</th><th>subject</th><th>state</th><th>attempts</th><th>seconds</th><th>preview</th><th>error</th></tr>");
    for j in jobs {
        let total = j
            .seconds
            .as_ref()
            .and_then(|s| s.get("total"))
            .and_then(|v| v.as_f64())
            .map(|t| format!("{t:.2}"))
            .unwrap_or_default();
        let thumb = if j.state == State::Done {
            format!(
                "<img src=\"/api/captures/{}/preview.png\" width=\"160\" alt=\"\">",
                esc(&j.id)
            )
        } else {
            String::new()
        };
        let _ = write!(
            h,
            "<tr><td><a href=\"/captures/{id}\">{id}</a></td><td>{subj}</td><td class=\"{st}\">{st}</td><td>{att}</td><td>{total}</td><td>{thumb}</td><td>{err}</td></tr>",
            id = esc(&j.id),
            subj = subject_link(j.subject.as_deref()),
            st = j.state.as_str(),
            att = j.attempts,
            err = esc(j.error.as_deref().unwrap_or(""))
        );
    }
    h.push_str("</table>");
}

/// Results awaiting an operator's review, and the latest failures.
fn reviews_and_failures(h: &mut String, st: &Status, failed: &[Job]) {
    if !st.awaiting_review.is_empty() {
        h.push_str("<h2>Awaiting review</h2><ul id=\"awaiting-review\">");
        for a in &st.awaiting_review {
            let _ = write!(
                h,
                "<li><a href=\"/captures/{id}\">{id}</a>: {w}</li>",
                id = esc(&a.capture),
                w = esc(&a.warning)
            );
        }
        h.push_str("</ul>");
    }
    if !failed.is_empty() {
        h.push_str("<h2>Failures</h2><ul id=\"failures\">");
        for j in failed {
            let _ = write!(
                h,
                "<li><a href=\"/captures/{id}\">{id}</a> ({stage}): {err}</li>",
                id = esc(&j.id),
                stage = esc(j.stage.as_deref().unwrap_or("")),
                err = esc(j.error.as_deref().unwrap_or(""))
            );
        }
        h.push_str("</ul>");
    }
}

async fn page(Ctx(shared): Ctx<Arc<Shared>>) -> Api<Html<String>> {
    let st = status_of(&shared)?;
    let (jobs, failed) = {
        let mut j = shared.journal();
        let jobs = j.list(None, 30);
        let failed = j.list(Some(State::Failed), 10);
        (jobs, failed)
    };
    let jobs = shared.journal_result(jobs).unwrap_or_default();
    let failed = shared.journal_result(failed).unwrap_or_default();
    let mut h = String::new();
    head_and_queue(&mut h, &st);
    latest_and_journal(&mut h, &st, &jobs);
    not_taken_and_workers(&mut h, &st);
    captures_table(&mut h, &jobs);
    reviews_and_failures(&mut h, &st, &failed);
    h.push_str("<p><a href=\"/api/status\">status (JSON)</a> · <a href=\"/api/export.csv\">all results (CSV)</a> · <a href=\"/metrics\">metrics</a></p></body></html>");
    Ok(Html(h))
}

async fn capture_page(Ctx(shared): Ctx<Arc<Shared>>, Path(id): Path<String>) -> Api<Html<String>> {
    let d = detail(&shared, &id)?;
    let j = &d.job;
    let mut h = String::new();
    let _ = write!(
        h,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>{id}</title><style>{STYLE}</style></head><body><p><a href=\"/\">station</a></p><h1>{id}</h1><table>",
        id = esc(&j.id)
    );
    let mut row = |k: &str, v: String| {
        let _ = write!(h, "<tr><th>{k}</th><td>{v}</td></tr>");
    };
    row(
        "state",
        format!("<span class=\"{0}\">{0}</span>", j.state.as_str()),
    );
    row("subject", subject_link(j.subject.as_deref()));
    row("attempts", j.attempts.to_string());
    if j.state == State::Done {
        row(
            "landmarks",
            match &j.landmarks {
                Some(names) => format!(
                    "<b id=\"manual-landmarks\">placed by an operator</b>: {}",
                    esc(names)
                ),
                None => "automatic (none placed)".into(),
            },
        );
    }
    row("queued", when(Some(j.queued_at)));
    row("finished", when(j.finished_at));
    if let Some(e) = &j.error {
        row(
            "error",
            format!("{} ({})", esc(e), esc(j.stage.as_deref().unwrap_or(""))),
        );
    }
    if let Some(r) = &d.report {
        let c = &r["conformation"];
        row(
            "mean distance to the scan",
            format!(
                "{:.3}% of the diagonal",
                c["mean_distance_relative"].as_f64().unwrap_or(f64::NAN) * 100.0
            ),
        );
        row(
            "matched / filled vertices",
            format!("{} / {}", c["matched"], c["filled"]),
        );
        row("folded triangles", c["folded_triangles"].to_string());
        let v = &c["final_variation"];
        row(
            "distortion (edge length / area std)",
            format!(
                "{:.3} / {:.3}",
                v["edge_length"]["std"].as_f64().unwrap_or(f64::NAN),
                v["area"]["std"].as_f64().unwrap_or(f64::NAN)
            ),
        );
        for w in fit_warnings(c) {
            row("warning", esc(w));
        }
        row("seconds", stage_table(&r["seconds"]));
        if let Some(s) = r.get("scores").filter(|s| !s.is_null()) {
            row("model scores", mode_scores(&s["scores_sd"]));
        }
        if let Some(w) = r.get("weight").filter(|w| !w.is_null()) {
            row(
                "weight",
                format!(
                    "{:.1} kg ({:.1} to {:.1})",
                    w["kg"].as_f64().unwrap_or(f64::NAN),
                    w["low"].as_f64().unwrap_or(f64::NAN),
                    w["high"].as_f64().unwrap_or(f64::NAN)
                ),
            );
        }
        if let Some(e) = r["measurement_error"].as_str() {
            row("measurements", esc(e));
        }
    }
    if j.state == State::Done {
        row("review", review_form(&j.id, d.review.as_ref()));
    }
    h.push_str("</table>");
    if j.state == State::Done {
        h.push_str(&viewer(&j.id));
    }
    if let Some(r) = &d.report {
        h.push_str(&measurement_table(r));
    }
    if j.state == State::Done {
        let _ = write!(
            h,
            "<p><img src=\"/api/captures/{id}/preview.png\" width=\"640\" alt=\"preview\"></p><p><a href=\"/api/captures/{id}/conformed.ply\">conformed.ply</a> · <a href=\"/api/captures/{id}/scan.ply\">scan.ply</a> · <a href=\"/api/captures/{id}/report.json\">report.json</a> · <a href=\"/api/captures/{id}/view.json\">view.json</a></p>",
            id = esc(&j.id)
        );
    }
    h.push_str("</body></html>");
    Ok(Html(h))
}

/// A result's review: the verdict given, and the buttons that give one (through
/// `POST /api/captures/{id}/review`, with the token when the station has one).
fn review_form(id: &str, review: Option<&Review>) -> String {
    let given = match review {
        None => "<b>awaiting review</b>".to_string(),
        Some(r) => format!(
            "<b id=\"verdict\">{}</b> {} ({})",
            match r.verdict {
                Verdict::Accepted => "accepted",
                Verdict::Rejected => "rejected",
            },
            esc(r.reason.as_deref().unwrap_or("")),
            when(Some(r.at))
        ),
    };
    format!(
        "{given}<form id=\"review\" onsubmit=\"return false\">\
<input name=\"reason\" size=\"40\" maxlength=\"500\" placeholder=\"reason (needed to reject)\"> \
<input name=\"token\" type=\"password\" size=\"12\" placeholder=\"token, if set\"> \
<button data-verdict=\"accepted\">accept</button> <button data-verdict=\"rejected\">reject</button> <span id=\"review-said\"></span></form>\
<script>document.querySelectorAll('#review button').forEach(b=>b.onclick=async()=>{{\
const f=document.getElementById('review'),h={{'Content-Type':'application/json'}};\
if(f.token.value)h.Authorization='Bearer '+f.token.value;\
const r=await fetch('/api/captures/{id}/review',{{method:'POST',headers:h,body:JSON.stringify({{verdict:b.dataset.verdict,reason:f.reason.value||null}})}});\
if(r.ok)location.reload();else document.getElementById('review-said').textContent=(await r.json()).error;}});</script>",
        id = esc(id)
    )
}

/// The 3D view of a result: the layers' toggles, the canvas' box, the distance colour
/// bar and the scripts (three.js from the system, then `viewer.js`).
fn viewer(id: &str) -> String {
    let toggles: String = [
        ("scan", "scan points"),
        ("mesh", "conformed mesh"),
        ("landmarks", "landmarks"),
        ("measurements", "measurements"),
        ("names", "landmark names"),
    ]
    .iter()
    .map(|(layer, text)| {
        // the names crowd a small subject: off until asked for
        let on = if *layer == "names" { "" } else { " checked" };
        format!("<label><input type=\"checkbox\" data-layer=\"{layer}\"{on}> {text}</label> ")
    })
    .collect();
    format!(
        "<h2>3D view</h2><div id=\"viewer-controls\">{toggles}<br><small>drag to turn, scroll to zoom, right-drag to pan</small></div>\
<div style=\"display:flex;gap:1.5em;align-items:flex-start;flex-wrap:wrap\"><div><div id=\"viewer\" data-capture=\"{id}\" data-state=\"loading\" style=\"width:900px;max-width:100%;height:560px;border:1px solid #ccc\"></div>\
<div id=\"viewer-bar\" style=\"display:none;width:900px;max-width:100%\"><div>distance to the scan</div><div style=\"height:12px;background:linear-gradient(to right,#440154,#3b528b,#21918c,#5ec962,#fde725)\"></div><span class=\"lo\"></span><span class=\"hi\" style=\"float:right\"></span></div></div>\
<div id=\"landmarks-panel\" data-state=\"loading\" style=\"max-width:340px\"><h3 style=\"margin-top:0\">Landmarks</h3><p>Pick a name, then click the scan where it belongs (at least 4, not all in one plane); \
the capture is then fitted again by them and its result replaced.</p><ol id=\"landmark-list\"></ol>\
<input id=\"landmarks-token\" type=\"password\" size=\"12\" placeholder=\"token, if set\"> <button type=\"button\" id=\"landmarks-submit\">reprocess with these landmarks</button> \
<button type=\"button\" id=\"landmarks-clear\">clear</button> <span id=\"landmarks-said\"></span></div></div>\
<script src=\"/static/three/three.min.js\"></script><script src=\"/static/three/OrbitControls.js\"></script><script src=\"/static/three/PLYLoader.js\"></script><script src=\"/static/viewer.js\"></script>",
        id = esc(id)
    )
}

/// A report's stage seconds (`{"read": 0.1, ...}`) as a small table, the total last.
fn stage_table(seconds: &serde_json::Value) -> String {
    let Some(stages) = seconds.as_object() else {
        return String::new();
    };
    let mut rows: Vec<(&String, f64)> = stages
        .iter()
        .filter_map(|(k, v)| v.as_f64().map(|v| (k, v)))
        .collect();
    rows.sort_by_key(|(k, _)| *k == "total");
    let mut h = String::from("<table class=\"stages\">");
    for (k, v) in rows {
        let _ = write!(h, "<tr><td>{}</td><td>{v:.2} s</td></tr>", esc(k));
    }
    h.push_str("</table>");
    h
}

/// Mode scores in standard deviations, one per mode: "mode 1: +0.52 sd, ...".
fn mode_scores(sd: &serde_json::Value) -> String {
    sd.as_array()
        .map(|a| {
            a.iter()
                .enumerate()
                .map(|(i, z)| format!("mode {}: {:+.2} sd", i + 1, z.as_f64().unwrap_or(f64::NAN)))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .unwrap_or_default()
}

/// A link to a subject's page (an RFID tag or the id a trigger named).
fn subject_link(subject: Option<&str>) -> String {
    match subject {
        Some(s) if crate::paths::check_plain_name("subject", s).is_ok() => {
            format!("<a href=\"/subjects/{0}\">{0}</a>", esc(s))
        }
        Some(s) => esc(s),
        None => String::new(),
    }
}

/// A result's measurements as an HTML table: raw and, when taken, posture-free.
fn measurement_table(r: &serde_json::Value) -> String {
    let Some(raw) = r["measurements"].as_array() else {
        return String::new();
    };
    let normalised = r["measurements_normalised"].as_array();
    let mut h = String::from(
        "<h2>Measurements</h2><table id=\"measurements\"><tr><th>measurement</th><th>value</th><th>posture removed</th><th>unit</th></tr>",
    );
    for m in raw {
        let name = m["name"].as_str().unwrap_or("");
        let n = normalised
            .and_then(|ns| ns.iter().find(|x| x["name"].as_str() == Some(name)))
            .and_then(|x| x["value"].as_f64())
            .map_or(String::new(), |v| format!("{v:.4}"));
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{:.4}</td><td>{}</td><td>{}</td></tr>",
            esc(name),
            m["value"].as_f64().unwrap_or(f64::NAN),
            n,
            esc(m["unit"].as_str().unwrap_or(""))
        );
    }
    h.push_str("</table>");
    h
}

/// The finished results of one subject, oldest first, with their reports.
fn subject_results(shared: &Shared, tag: &str) -> Api<Vec<(Job, serde_json::Value)>> {
    crate::paths::check_plain_name("subject", tag)
        .map_err(|e| ApiError(StatusCode::BAD_REQUEST, e.to_string()))?;
    let mut jobs: Vec<Job> = shared
        .journal()
        .list(Some(State::Done), 100_000)
        .map_err(internal)?
        .into_iter()
        .filter(|j| j.subject.as_deref() == Some(tag))
        .collect();
    jobs.sort_by(|a, b| a.queued_at.total_cmp(&b.queued_at));
    let results: Vec<_> = jobs
        .into_iter()
        .filter_map(|j| {
            let r = j.result.as_ref()?.join("report.json");
            let v = serde_json::from_slice(
                &crate::files::read_limited(&r, crate::files::MAX_REPORT_BYTES).ok()?,
            )
            .ok()?;
            Some((j, v))
        })
        .collect();
    // the page and its plot answer alike: no finished result, nothing to show
    if results.is_empty() {
        return Err(ApiError(
            StatusCode::NOT_FOUND,
            format!("subject '{tag}' has no finished result"),
        ));
    }
    Ok(results)
}

async fn subject_page(Ctx(shared): Ctx<Arc<Shared>>, Path(tag): Path<String>) -> Api<Html<String>> {
    let results = subject_results(&shared, &tag)?;
    let mut h = String::new();
    let _ = write!(
        h,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>{t}</title><style>{STYLE}</style></head><body><p><a href=\"/\">station</a></p><h1>Subject {t}</h1><p><img id=\"history\" src=\"/subjects/{t}/history.png\" width=\"800\" alt=\"history\"></p><table><tr><th>capture</th><th>finished</th><th>weight (kg)</th></tr>",
        t = esc(&tag)
    );
    for (j, r) in &results {
        let _ = write!(
            h,
            "<tr><td><a href=\"/captures/{id}\">{id}</a></td><td>{when}</td><td>{w}</td></tr>",
            id = esc(&j.id),
            when = when(j.finished_at),
            w = r["weight"]["kg"]
                .as_f64()
                .map_or(String::new(), |v| format!("{v:.1}"))
        );
    }
    h.push_str("</table>");
    match subject_repeatability(&shared, &results) {
        Some(r) => {
            let _ = write!(
                h,
                "<h2>Repeatability</h2><p>Over {} results (rejected ones left out): each measurement's mean, standard deviation and coefficient of variation, as measured and posture-free.</p><table id=\"repeatability\"><tr><th>measurement</th><th>mean</th><th>SD</th><th>CV</th><th>posture-free mean</th><th>SD</th><th>CV</th></tr>",
                r.results
            );
            for m in &r.raw {
                let free = r.posture_free.iter().find(|p| p.name == m.name);
                let cell = |v: Option<String>| v.unwrap_or_default();
                let _ = write!(
                    h,
                    "<tr><td>{n}</td><td>{:.4} {u}</td><td>{:.4}</td><td>{:.2}%</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                    m.mean,
                    m.sd,
                    100.0 * m.cv,
                    cell(free.map(|p| format!("{:.4} {}", p.mean, esc(&p.unit)))),
                    cell(free.map(|p| format!("{:.4}", p.sd))),
                    cell(free.map(|p| format!("{:.2}%", 100.0 * p.cv))),
                    n = esc(&m.name),
                    u = esc(&m.unit),
                );
            }
            h.push_str("</table>");
        }
        None => h.push_str(
            "<h2>Repeatability</h2><p id=\"repeatability\">Needs two results or more that an operator has not rejected.</p>",
        ),
    }
    h.push_str("<p><a href=\"/api/export.csv\">all results (CSV)</a></p></body></html>");
    Ok(Html(h))
}

/// How well the subject's measurements repeat over `results`, the rejected ones left
/// out; `None` with fewer than two left.
fn subject_repeatability(
    shared: &Shared,
    results: &[(Job, serde_json::Value)],
) -> Option<crate::station::export::SubjectSpread> {
    let kept: Vec<serde_json::Value> = results
        .iter()
        .filter(|(j, _)| {
            // as the export: a verdict that cannot be read leaves the result out
            let left_out = j
                .result
                .as_ref()
                .and_then(|r| data_dir(shared, r).ok())
                .map(|d| crate::station::review::left_out_in(&d).unwrap_or(true));
            left_out == Some(false)
        })
        .map(|(_, r)| r.clone())
        .collect();
    crate::station::export::subject_spreads(&kept)
        .into_iter()
        .next()
}

/// `GET /api/subjects/{tag}`: the subject's finished captures (oldest first) and how
/// well its measurements repeat over them.
async fn subject_api(
    Ctx(shared): Ctx<Arc<Shared>>,
    Path(tag): Path<String>,
) -> Api<axum::Json<serde_json::Value>> {
    let results = subject_results(&shared, &tag)?;
    let captures: Vec<&str> = results.iter().map(|(j, _)| j.id.as_str()).collect();
    Ok(axum::Json(serde_json::json!({
        "subject": tag,
        "captures": captures,
        "repeatability": subject_repeatability(&shared, &results),
    })))
}

async fn subject_plot(Ctx(shared): Ctx<Arc<Shared>>, Path(tag): Path<String>) -> Api<Response> {
    let results = subject_results(&shared, &tag)?;
    let t0 = results.first().map_or(0.0, |(j, _)| j.queued_at);
    let mut series: Vec<crate::render::plot::Series> = Vec::new();
    let mut add = |name: &str, unit: &str, t: f64, v: f64| {
        let x = (t - t0) / 86_400.0;
        match series.iter_mut().find(|s| s.name == name) {
            Some(s) => s.points.push((x, v)),
            None => series.push(crate::render::plot::Series {
                name: name.into(),
                unit: unit.into(),
                points: vec![(x, v)],
            }),
        }
    };
    for (j, r) in &results {
        if let Some(kg) = r["weight"]["kg"].as_f64() {
            add("weight", "kg", j.queued_at, kg);
        }
        // posture-free when taken: the measurement of the animal, not of its stance
        let ms = r["measurements_normalised"]
            .as_array()
            .or(r["measurements"].as_array());
        for m in ms.into_iter().flatten() {
            if let (Some(n), Some(u), Some(v)) =
                (m["name"].as_str(), m["unit"].as_str(), m["value"].as_f64())
            {
                add(n, u, j.queued_at, v);
            }
        }
    }
    let title = format!("subject {tag}");
    let since = when(Some(t0));
    let png = tokio::task::spawn_blocking(move || {
        crate::render::plot::history_png(&title, &since, &series, 900, 700)
    })
    .await
    .map_err(internal)?
    .map_err(internal)?;
    Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response())
}

async fn export(Ctx(shared): Ctx<Arc<Shared>>) -> Api<Response> {
    let dir = shared.results_dir();
    let export = tokio::task::spawn_blocking(move || crate::station::export::export_csv(&dir))
        .await
        .map_err(internal)?
        .map_err(internal)?;
    for (file, why) in &export.skipped {
        tracing::warn!("export.csv: {file} left out: {why}");
    }
    let csv = export.csv;
    Ok((
        [
            (header::CONTENT_TYPE, "text/csv; charset=utf-8"),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"results.csv\"",
            ),
        ],
        csv,
    )
        .into_response())
}
