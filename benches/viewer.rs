//! The capture page's 3D view on a large scan (issue 23: usable on a 100k-point scan):
//! one simulated capture processed by the daemon in this process, its page opened in
//! headless Chromium through chromedriver, once with the scan as reconstructed (about
//! 130,000 points from the example rig) and once grown threefold (each point copied with
//! a small jitter). Reported:
//! the time from asking for the page to the view ready (files fetched, parsed, the
//! scene built), milliseconds per frame while the view turns once round, the JavaScript
//! heap, and the scan file's size. WebGL runs on the CPU here (SwiftShader): a laptop's
//! GPU draws faster. Run: `cargo bench --bench viewer`.

#[path = "../tests/support/webdriver.rs"]
mod webdriver;

use conformd::daemon::Handle;
use conformd::station::StationConfig;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The frame timer the benchmark puts into the page: n frames drawn at once while the
/// view turns once round (through the viewer's three.js objects, `conformdViewer.three`),
/// each read back so that it is finished; milliseconds per frame.
const TIME_FRAMES: &str = "const timeFrames = (n, moving) => {
  const { renderer, scene, camera, controls, moving: lod, render } = window.conformdViewer.three;
  lod(!!moving);
  const gl = renderer.getContext(), px = new Uint8Array(4), t0 = performance.now();
  for (let i = 0; i < n; i++) {
    camera.position.sub(controls.target).applyAxisAngle(camera.up, (2 * Math.PI) / n).add(controls.target);
    camera.lookAt(controls.target);
    renderer.render(scene, camera);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
  }
  lod(false);
  render();
  return (performance.now() - t0) / n;
};";

fn main() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let set = conformd::commands::simulate(&rig, "pig", "swing=8,nod=-5", 1, 2.0, &d.join("sim"))
        .unwrap()
        .remove(0);
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let station = d.join("station.toml");
    std::fs::write(
        &station,
        format!(
            "[station]\nname = \"bench\"\ndata = \"data\"\n[template]\ngeneric = \"pig\"\nvertices = 10000\n\
             [rig]\nfile = \"{}\"\ncalibration = \"sim/calibration\"\n\
             [daemon]\nlisten = \"127.0.0.1:{port}\"\nrescan_s = 1.0\n",
            rig.display()
        ),
    )
    .unwrap();
    let cfg = StationConfig::load(&station).unwrap();
    let (incoming, results) = (cfg.station.incoming(), cfg.station.results());
    std::fs::create_dir_all(&incoming).unwrap();
    let id = set.file_name().unwrap().to_string_lossy().to_string();
    let staged = incoming.join(format!(".{id}.copying"));
    std::fs::create_dir_all(&staged).unwrap();
    for e in std::fs::read_dir(&set).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), staged.join(e.file_name())).unwrap();
    }
    let exe = PathBuf::from(env!("CARGO_BIN_EXE_conformd"));
    let h = Handle::spawn(cfg, Some(exe)).unwrap();
    std::fs::rename(&staged, incoming.join(&id)).unwrap();
    h.shared.wake.notify_one();
    let t = Instant::now();
    while h.shared.journal().counts().unwrap().done < 1 {
        assert!(
            t.elapsed() < Duration::from_secs(300),
            "the capture was not processed"
        );
        assert_eq!(
            h.shared.journal().counts().unwrap().failed,
            0,
            "the capture failed"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let scan_file = results.join(&id).join("scan.ply");
    let scan = conformd::mesh::read_mesh(&scan_file).unwrap();
    let mesh_vertices = conformd::mesh::read_mesh(&results.join(&id).join("conformed.ply"))
        .unwrap()
        .vertices
        .len();
    let browser = webdriver::Browser::start(&d.join("chrome"), 1400, 1000);
    let url = format!("http://127.0.0.1:{port}/captures/{id}");
    let mut grown = scan.clone();
    let (lo, hi) = scan.bounding_box().unwrap();
    let jitter = 0.002 * (hi - lo).norm();
    let mut k = 0u64;
    while grown.vertices.len() < (3 * scan.vertices.len()).max(100_000) {
        let p = scan.vertices[k as usize % scan.vertices.len()];
        // a cheap deterministic jitter: the points only need to be there to be drawn
        let h = |s: u64| ((k.wrapping_mul(2654435761).wrapping_add(s) % 1000) as f64 / 500.0) - 1.0;
        grown
            .vertices
            .push(p + conformd::mesh::V3::new(h(1), h(7), h(13)) * jitter);
        k += 1;
    }
    println!(
        "conformed mesh of {mesh_vertices} vertices; {} cores; WebGL on the CPU (SwiftShader)",
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    );
    for (what, points) in [("as reconstructed", &scan), ("grown threefold", &grown)] {
        let bytes = conformd::mesh::io::ply_bytes(
            points,
            conformd::mesh::io::PlyEncoding::BinaryLittleEndian,
        );
        conformd::files::write_atomic(&scan_file, &bytes).unwrap();
        let mut loads = Vec::new();
        let mut frames = Vec::new();
        let mut bare = Vec::new();
        let mut moving = Vec::new();
        let mut heap = 0.0;
        for _ in 0..3 {
            browser.go(&url);
            browser.wait_for(
                "const v = document.getElementById('viewer'); return !!v && v.dataset.state === 'ready';",
                "the view",
                Duration::from_secs(120),
            );
            let drawn = browser.run(
                "return Number(document.getElementById('viewer').dataset.scanPoints);",
                serde_json::json!([]),
            );
            assert_eq!(drawn, points.vertices.len(), "the view draws every point");
            loads.push(
                browser
                    .run(
                        "return Number(document.getElementById('viewer').dataset.loadMs);",
                        serde_json::json!([]),
                    )
                    .as_f64()
                    .unwrap(),
            );
            frames.push(
                browser
                    .run(
                        &format!("{TIME_FRAMES} return timeFrames(36);"),
                        serde_json::json!([]),
                    )
                    .as_f64()
                    .unwrap(),
            );
            moving.push(
                browser
                    .run(
                        &format!("{TIME_FRAMES} return timeFrames(36, true);"),
                        serde_json::json!([]),
                    )
                    .as_f64()
                    .unwrap(),
            );
            bare.push(
                browser
                    .run(
                        &format!("{TIME_FRAMES} const v = window.conformdViewer; v.scan.visible = false; const t = timeFrames(36); v.scan.visible = true; return t;"),
                        serde_json::json!([]),
                    )
                    .as_f64()
                    .unwrap(),
            );
            heap = browser
                .run(
                    "return performance.memory ? performance.memory.usedJSHeapSize : 0;",
                    serde_json::json!([]),
                )
                .as_f64()
                .unwrap_or(0.0);
        }
        loads.sort_by(f64::total_cmp);
        frames.sort_by(f64::total_cmp);
        bare.sort_by(f64::total_cmp);
        moving.sort_by(f64::total_cmp);
        println!(
            "scan {what}: {} points, {:.1} MB PLY; page to view ready median {:.0} ms (of 3: {:.0}-{:.0}); a frame of the whole scan {:.1} ms, while the view moves (30,000 of its points) {:.1} ms ({:.0} frames/s), without the scan {:.1} ms; JS heap {:.0} MB",
            points.vertices.len(),
            bytes.len() as f64 / 1e6,
            loads[1],
            loads[0],
            loads[2],
            frames[1],
            moving[1],
            1000.0 / moving[1],
            bare[1],
            heap / 1e6
        );
    }
    drop(browser);
    h.stop().unwrap();
}
