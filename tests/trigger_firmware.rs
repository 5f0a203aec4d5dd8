//! The reference trigger box's firmware (`firmware/trigger-box`, ATmega328P) run in the
//! simavr emulator (`firmware/sim/boxsim`) with its serial line on a pseudo-terminal:
//! the same link the station uses (TriggerLink by device name) does the handshake, arms
//! and fires; the emulator's pin log shows the fire pulse (when, how long, on both
//! outputs); the board's inputs give button, RFID and flash-not-charged; garbage and
//! over-long lines are refused without harm; the device unplugged and plugged back is
//! reopened; `conformd capture` fires a capture through it.

use crate::common::{CHILD_LIMIT, Deadline};
use conformd::devices::trigger::{BoxEvent, TriggerError, TriggerLink};
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// How far after a FIRE line's last byte reached the box its pulse may start, in the
/// emulator's time (measured 0.24-0.41 ms, most of it the emulated UART taking the byte).
const FIRE_LATENCY_US: u64 = 500;
/// How much longer than the exposure the pulse may last (measured +6 us).
const PULSE_SLACK_US: u64 = 10;

/// The firmware and the harness, built once per test run (`make -C firmware`).
fn built() -> &'static (PathBuf, PathBuf) {
    static BUILT: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    BUILT.get_or_init(|| {
        let top = Path::new(env!("CARGO_MANIFEST_DIR")).join("firmware");
        let out = Command::new("make")
            .arg("-C")
            .arg(&top)
            .output_within(CHILD_LIMIT);
        assert!(
            out.status.success(),
            "make -C firmware failed (it needs gcc-avr, avr-libc and libsimavr-dev: `make test-deps`):\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        (
            top.join("trigger-box/build/trigger-box.elf"),
            top.join("sim/build/boxsim"),
        )
    })
}

/// A running emulated box; stopped (its device gone) when dropped.
struct Emulator {
    child: Child,
    control: Option<ChildStdin>,
    lines: Arc<Mutex<Vec<String>>>,
}

impl Emulator {
    fn start(link: &Path) -> Emulator {
        let (elf, boxsim) = built();
        let mut child = Command::new(boxsim)
            .arg(elf)
            .arg(link)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("boxsim starts");
        let control = child.stdin.take();
        let lines = Arc::new(Mutex::new(Vec::new()));
        let out = child.stdout.take().unwrap();
        let sink = lines.clone();
        std::thread::spawn(move || {
            for l in BufReader::new(out).lines().map_while(Result::ok) {
                sink.lock().unwrap().push(l);
            }
        });
        let e = Emulator {
            child,
            control,
            lines,
        };
        e.wait_for("the emulator's READY line", |l| l.starts_with("READY "));
        e
    }

    /// The first log line `f` accepts, waiting up to 5 s for it.
    fn wait_for(&self, what: &str, f: impl Fn(&str) -> bool) -> String {
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(5) {
            if let Some(l) = self.lines.lock().unwrap().iter().find(|l| f(l)) {
                return l.clone();
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!(
            "no {what} from the emulator; its log:\n{}",
            self.lines.lock().unwrap().join("\n")
        );
    }

    fn log(&self) -> Vec<String> {
        self.lines.lock().unwrap().clone()
    }

    /// Acts on the board's inputs (`button`, `rfid TAG`, `charging`, `ready`).
    fn input(&mut self, line: &str) {
        let c = self.control.as_mut().unwrap();
        writeln!(c, "{line}").unwrap();
        c.flush().unwrap();
    }

    /// Unplugged: the emulator ends and its device name goes.
    fn unplug(mut self) {
        self.input("quit");
        self.stop();
    }

    fn stop(&mut self) {
        self.control = None;
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(5) {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        self.stop();
    }
}

/// `PIN name value us` and `RX_LF us` lines of the log as (name, value, us).
fn events(log: &[String]) -> Vec<(String, u8, u64)> {
    log.iter()
        .filter_map(|l| {
            let t: Vec<&str> = l.split_whitespace().collect();
            match t.as_slice() {
                ["PIN", name, v, us] => Some((name.to_string(), v.parse().ok()?, us.parse().ok()?)),
                ["RX_LF", us] => Some(("rx_lf".into(), 1, us.parse().ok()?)),
                _ => None,
            }
        })
        .collect()
}

/// The fire pulse after emulator time `after`: (start, end) of each output, and the
/// time the command's last byte reached the box.
fn pulse(log: &[String], after: u64) -> (u64, [(u64, u64); 2]) {
    let ev = events(log);
    let edge = |name: &str, value: u8, from: u64| {
        ev.iter()
            .find(|(n, v, t)| n == name && *v == value && *t >= from)
            .map(|e| e.2)
            .unwrap_or_else(|| {
                panic!(
                    "no {name} going {value} after {from} us:\n{}",
                    log.join("\n")
                )
            })
    };
    let rise = edge("cameras", 1, after);
    let lf = ev
        .iter()
        .filter(|(n, _, t)| n == "rx_lf" && *t <= rise)
        .map(|e| e.2)
        .next_back()
        .expect("the FIRE line's end");
    let mut out = [(0, 0); 2];
    for (k, name) in ["cameras", "flash"].iter().enumerate() {
        let up = edge(name, 1, after);
        out[k] = (up, edge(name, 0, up));
    }
    (lf, out)
}

fn last_time(log: &[String]) -> u64 {
    events(log).last().map_or(0, |e| e.2)
}

fn link(path: &Path) -> TriggerLink {
    TriggerLink::new(path, 115_200, Duration::from_millis(500))
}

#[test]
fn the_firmware_fires_its_pulse_on_time_and_refuses_what_it_should() {
    let dir = tempfile::tempdir().unwrap();
    let dev = dir.path().join("ttyACM-box");
    let mut emu = Emulator::start(&dev);
    let mut l = link(&dev);
    let firmware = l.with(|b| Ok(b.firmware.clone())).expect("handshake");
    assert_eq!(firmware, "fw-1.0.0");

    // armed, fired: the pulse on both outputs, on time and as long as the exposure
    let mut box_minus_emulator = Vec::new();
    for (seq, exposure) in [(1u32, 8000u64), (2, 20), (4_294_967_295, 250_000)] {
        let before = last_time(&emu.log());
        l.with(|b| b.arm(seq)).unwrap();
        let ack = l.with(|b| b.fire(seq, exposure as u32)).unwrap();
        emu.wait_for("the pulse's end", |line| {
            line.starts_with("PIN flash 0 ") && line[12..].parse::<u64>().unwrap_or(0) > before
        });
        let (lf, outputs) = pulse(&emu.log(), before + 1);
        for (k, (up, down)) in outputs.iter().enumerate() {
            let width = down - up;
            assert!(
                width >= exposure && width <= exposure + PULSE_SLACK_US,
                "output {k}: pulse {width} us for an exposure of {exposure} us"
            );
        }
        assert_eq!(
            outputs[0].0, outputs[1].0,
            "cameras and flash rise together"
        );
        let latency = outputs[0].0 - lf;
        assert!(
            latency <= FIRE_LATENCY_US,
            "pulse {latency} us after the FIRE line"
        );
        eprintln!(
            "FIRE {seq} {exposure}: pulse {} us, {latency} us after the line",
            outputs[0].1 - outputs[0].0
        );
        box_minus_emulator.push(ack as i64 - outputs[0].0 as i64);
    }
    // the ACK's time is the pulse's start on the box's clock
    let spread =
        box_minus_emulator.iter().max().unwrap() - box_minus_emulator.iter().min().unwrap();
    assert!(
        spread <= 2,
        "ACK times against the pulses: {box_minus_emulator:?}"
    );

    // refusals: not armed (a FIRE never fires twice), flash charging, out of range
    let refused =
        |l: &mut TriggerLink, seq: u32, exposure: u32| match l.with(|b| b.fire(seq, exposure)) {
            Err(TriggerError::Refused { code, .. }) => code,
            other => panic!("FIRE {seq} {exposure}: {other:?}"),
        };
    assert_eq!(refused(&mut l, 4_294_967_295, 8000), "E_NOT_ARMED");
    l.with(|b| b.arm(5)).unwrap();
    assert_eq!(refused(&mut l, 6, 8000), "E_NOT_ARMED");
    assert_eq!(refused(&mut l, 5, 5), "E_RANGE");
    emu.input("charging");
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(refused(&mut l, 5, 8000), "E_FLASH");
    emu.input("ready");
    std::thread::sleep(Duration::from_millis(20));
    let pulses_before = events(&emu.log())
        .iter()
        .filter(|e| e.0 == "cameras" && e.1 == 1)
        .count();
    assert!(
        l.with(|b| b.fire(5, 8000)).is_ok(),
        "fires once the flash is ready"
    );
    emu.wait_for("the fifth pulse", |line| line.starts_with("PIN cameras 1 "));
    std::thread::sleep(Duration::from_millis(50));
    let pulses = events(&emu.log())
        .iter()
        .filter(|e| e.0 == "cameras" && e.1 == 1)
        .count();
    assert_eq!(
        pulses,
        pulses_before + 1,
        "one pulse for the one FIRE accepted"
    );
    assert_eq!(pulses, 4, "no pulse for a refused FIRE");

    // PING: the box's clock runs on
    let p1 = l.with(|b| b.ping()).unwrap();
    std::thread::sleep(Duration::from_millis(30));
    let p2 = l.with(|b| b.ping()).unwrap();
    assert!(p2 > p1, "{p1} then {p2}");
}

#[test]
fn the_boards_button_and_rfid_reader_become_events() {
    let dir = tempfile::tempdir().unwrap();
    let dev = dir.path().join("ttyACM-box");
    let mut emu = Emulator::start(&dev);
    let mut l = link(&dev);
    l.with(|b| b.ping()).expect("handshake and ping");
    emu.input("button");
    std::thread::sleep(Duration::from_millis(100));
    emu.input("rfid 982000123456789");
    // a reader framing its tag with STX/ETX: the framing is left out
    std::thread::sleep(Duration::from_millis(100));
    emu.input("rfid \u{2}0E00A1B2C3\u{3}");
    let mut got = Vec::new();
    let start = Instant::now();
    while got.len() < 3 && start.elapsed() < Duration::from_secs(5) {
        got.extend(
            l.with(|b| b.poll_events(Duration::from_millis(50)))
                .unwrap(),
        );
    }
    assert_eq!(got.len(), 3, "{got:?}");
    let (t_button, t_tag) = match (&got[0], &got[1]) {
        (
            BoxEvent::Button { box_time_us: a },
            BoxEvent::Rfid {
                tag,
                box_time_us: b,
            },
        ) => {
            assert_eq!(tag, "982000123456789");
            (*a, *b)
        }
        other => panic!("{other:?}"),
    };
    assert!(t_tag > t_button + 50_000, "{t_button} then {t_tag}");
    assert!(
        matches!(&got[2], BoxEvent::Rfid { tag, .. } if tag == "0E00A1B2C3"),
        "{:?}",
        got[2]
    );
}

#[test]
fn garbage_and_over_long_lines_are_refused_and_the_box_carries_on() {
    let dir = tempfile::tempdir().unwrap();
    let dev = dir.path().join("ttyACM-box");
    let _emu = Emulator::start(&dev);
    let mut port = serialport::new(dev.to_string_lossy(), 115_200)
        .timeout(Duration::from_millis(50))
        .open_native()
        .expect("the emulated device opens");
    let mut sent = vec![0x00, 0xff, 0x13, b'\n'];
    sent.extend(std::iter::repeat_n(b'A', 500));
    sent.extend(b"\nBOGUS 12\nFIRE x y\nPING\n");
    port.write_all(&sent).unwrap();
    let mut text = String::new();
    let start = Instant::now();
    while !(text.contains("PONG") && text.ends_with('\n'))
        && start.elapsed() < Duration::from_secs(5)
    {
        let mut buf = [0u8; 256];
        if let Ok(n) = port.read(&mut buf) {
            text.push_str(&String::from_utf8_lossy(&buf[..n]));
        }
    }
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 5, "{text:?}");
    assert!(lines[0].starts_with("ERR - E_GARBAGE "), "{text}");
    assert!(lines[1].starts_with("ERR - E_LONG "), "{text}");
    assert!(lines[2].starts_with("ERR - E_UNKNOWN "), "{text}");
    assert!(lines[3].starts_with("ERR - E_ARGS "), "{text}");
    assert!(lines[4].starts_with("PONG "), "{text}");
    // and the station's link still shakes hands on the same line
    drop(port);
    let mut l = link(&dev);
    assert!(l.with(|b| b.ping()).is_ok());
}

#[test]
fn the_link_reopens_the_box_when_it_is_plugged_back() {
    let dir = tempfile::tempdir().unwrap();
    let dev = dir.path().join("ttyACM-box");
    let emu = Emulator::start(&dev);
    let mut l = link(&dev);
    l.with(|b| b.arm(1)).unwrap();
    l.with(|b| b.fire(1, 8000)).expect("fires");
    emu.unplug();
    assert!(!dev.exists(), "the device name goes with the box");
    let e = l.with(|b| b.ping()).unwrap_err();
    assert!(
        matches!(e, TriggerError::Io { .. } | TriggerError::NoAnswer { .. }),
        "{e}"
    );
    assert!(!l.is_connected());

    let _emu2 = Emulator::start(&dev);
    let start = Instant::now();
    let mut fired = false;
    while start.elapsed() < Duration::from_secs(10) {
        if l.with(|b| b.arm(2).and_then(|_| b.fire(2, 8000))).is_ok() {
            fired = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(fired, "reopened and fired within 10 s");
    assert_eq!(l.reconnects, 2);
}

#[test]
fn conformd_capture_fires_through_the_emulated_box() {
    let dir = tempfile::tempdir().unwrap();
    let dev = dir.path().join("ttyACM-box");
    let emu = Emulator::start(&dev);
    let cfg = crate::common::synthetic_station(dir.path(), Some(&dev));
    let out = Command::new(env!("CARGO_BIN_EXE_conformd"))
        .args([
            "capture",
            "--config",
            cfg.to_str().unwrap(),
            "--subject",
            "pig-7",
        ])
        .output_within(CHILD_LIMIT);
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let ev = events(&emu.log());
    let pulses = ev.iter().filter(|e| e.0 == "cameras" && e.1 == 1).count();
    assert_eq!(pulses, 1, "one pulse for one capture: {ev:?}");
    let sets: Vec<_> = std::fs::read_dir(dir.path().join("captures"))
        .unwrap()
        .filter_map(Result::ok)
        .collect();
    assert_eq!(sets.len(), 1);
    let manifest = std::fs::read_to_string(sets[0].path().join("manifest.json")).unwrap();
    assert!(
        manifest.contains("\"serial\"") && manifest.contains("box_time_us"),
        "{manifest}"
    );
}
