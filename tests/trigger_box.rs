//! The trigger box protocol over a real pseudo-terminal pair, with a simulated box in a
//! thread: handshake, fire and acknowledge, button and RFID events, garbage bytes, an
//! over-long line, a box that stops answering, the pty closing and a new one appearing.

use conformd::devices::trigger::{BoxEvent, TriggerBox, TriggerError, TriggerLink};
use serialport::{SerialPort, TTYPort};
use std::io::{BufRead, BufReader, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// How the simulated box behaves.
#[derive(Clone, Default)]
struct Script {
    /// sent before answering the first FIRE
    noise_before_ack: Vec<u8>,
    /// events sent after the handshake
    events_after_hello: Vec<String>,
    /// stop answering FIRE
    mute: Arc<AtomicBool>,
    /// refuse FIRE with this sequence number
    refuse_seq: Option<u32>,
    /// end the box (its end of the pty closes: the device is unplugged)
    stop: Arc<AtomicBool>,
}

/// Runs a simulated box on the master side until the pty closes.
fn run_box(master: TTYPort, script: Script) -> std::thread::JoinHandle<u32> {
    std::thread::spawn(move || {
        let mut writer = master.try_clone_native().expect("clone master");
        let mut master = master;
        master.set_timeout(Duration::from_millis(50)).unwrap();
        let mut reader = BufReader::new(master);
        let mut fired = 0u32;
        let mut t = 1_000_000u64;
        let mut line = String::new();
        loop {
            if script.stop.load(Ordering::SeqCst) {
                return fired;
            }
            line.clear();
            match reader.read_line(&mut line) {
                Ok(n) if n > 0 => {}
                // nobody has the device open (EOF or EIO on the master): a real box
                // waits for the host to come back
                _ => {
                    std::thread::sleep(Duration::from_millis(5));
                    continue;
                }
            }
            let tok: Vec<&str> = line.split_whitespace().collect();
            t += 1000;
            let reply = match tok.as_slice() {
                ["HELLO", "conformd", v] => {
                    let mut r = format!("HELLO simbox {v} fw-2.1\n");
                    for e in &script.events_after_hello {
                        r.push_str(e);
                        r.push('\n');
                    }
                    r.into_bytes()
                }
                ["ARM", seq] => format!("ARMED {seq}\n").into_bytes(),
                ["FIRE", seq, _exp] => {
                    if script.mute.load(Ordering::SeqCst) {
                        continue;
                    }
                    let seq: u32 = seq.parse().unwrap();
                    if Some(seq) == script.refuse_seq {
                        format!("ERR {seq} E_FLASH flash not charged\n").into_bytes()
                    } else {
                        fired += 1;
                        let mut r = if fired == 1 {
                            script.noise_before_ack.clone()
                        } else {
                            vec![]
                        };
                        r.extend(format!("ACK {seq} {t}\n").bytes());
                        r
                    }
                }
                ["PING"] => format!("PONG {t}\n").into_bytes(),
                _ => b"ERR - E_UNKNOWN what\n".to_vec(),
            };
            let _ = writer.write_all(&reply);
        }
    })
}

fn client(slave: TTYPort) -> Result<TriggerBox<TTYPort>, TriggerError> {
    let mut slave = slave;
    slave.set_timeout(Duration::from_millis(20)).unwrap();
    TriggerBox::connect(slave, "pty", Duration::from_millis(300))
}

#[test]
fn handshake_fire_events_and_garbage() {
    let (master, slave) = TTYPort::pair().expect("a pseudo-terminal pair");
    let mut noise = vec![0x00, 0xff, 0x13, b'\n'];
    noise.extend(std::iter::repeat_n(b'A', 500));
    noise.extend(b"\nBOGUS 12\nACK x y\n");
    let script = Script {
        noise_before_ack: noise,
        events_after_hello: vec![
            "EVT BUTTON 999".into(),
            "EVT RFID 982000123456789 1500".into(),
        ],
        refuse_seq: Some(3),
        ..Default::default()
    };
    let stop = script.stop.clone();
    let sim = run_box(master, script);
    let mut b = client(slave).expect("handshake");
    assert_eq!(b.firmware, "fw-2.1");
    b.arm(1).unwrap();
    let t1 = b
        .fire(1, 8000)
        .expect("fire 1 is acknowledged through the garbage");
    assert!(t1 > 1_000_000);
    let t2 = b.fire(2, 8000).unwrap();
    assert!(t2 > t1, "box timestamps advance");
    let e = b.fire(3, 8000).unwrap_err();
    assert!(
        matches!(e, TriggerError::Refused { ref code, .. } if code == "E_FLASH"),
        "{e}"
    );
    assert!(e.to_string().contains("flash not charged"));
    assert!(b.ping().is_ok());
    let events = b.poll_events(Duration::from_millis(50)).unwrap();
    assert_eq!(events[0], BoxEvent::Button { box_time_us: 999 });
    assert_eq!(
        events[1],
        BoxEvent::Rfid {
            tag: "982000123456789".into(),
            box_time_us: 1500
        }
    );
    // every bad line was reported, none was fatal
    let w = b.warnings.join(" | ");
    assert!(
        w.contains("non-printable")
            && w.contains("over-long")
            && w.contains("unknown message 'BOGUS'")
            && w.contains("'x' is not a number"),
        "{w}"
    );
    drop(b);
    stop.store(true, Ordering::SeqCst);
    assert_eq!(sim.join().unwrap(), 2);
}

#[test]
fn a_silent_box_is_reported_not_waited_for() {
    let (master, slave) = TTYPort::pair().unwrap();
    let script = Script::default();
    script.mute.store(true, Ordering::SeqCst);
    let sim = run_box(master, script.clone());
    let mut b = client(slave).unwrap();
    let t = std::time::Instant::now();
    let e = b.fire(1, 8000).unwrap_err();
    assert!(matches!(e, TriggerError::NoAnswer { .. }), "{e}");
    assert!(e.to_string().contains("no answer to FIRE 1"), "{e}");
    assert!(t.elapsed() < Duration::from_millis(1000));
    script.stop.store(true, Ordering::SeqCst);
    sim.join().unwrap();
}

#[test]
fn the_link_reconnects_when_the_device_comes_back() {
    let dir = tempfile::tempdir().unwrap();
    let link_path = dir.path().join("trigbox");
    // a udev-style stable name pointing at the current pty
    let (master, slave) = TTYPort::pair().unwrap();
    std::os::unix::fs::symlink(slave.name().unwrap(), &link_path).unwrap();
    drop(slave);
    let script = Script::default();
    let sim = run_box(master, script.clone());
    let mut link = TriggerLink::new(&link_path, 115_200, Duration::from_millis(300));
    assert_eq!(link.with(|b| b.fire(1, 8000)).map(|_| ()), Ok(()));
    assert!(link.is_connected());

    // unplugged: the box's end closes and the device name disappears
    script.stop.store(true, Ordering::SeqCst);
    sim.join().unwrap();
    std::fs::remove_file(&link_path).unwrap();
    let e = link.with(|b| b.fire(2, 8000)).unwrap_err();
    assert!(
        matches!(e, TriggerError::Io { .. } | TriggerError::NoAnswer { .. }),
        "{e}"
    );
    assert!(!link.is_connected(), "the dead connection is dropped");
    let e = link.with(|b| b.fire(2, 8000)).unwrap_err();
    assert!(
        matches!(
            e,
            TriggerError::Disconnected { .. } | TriggerError::Io { .. }
        ),
        "{e}"
    );

    // plugged back in: a new pty behind the same name
    let (master2, slave2) = TTYPort::pair().unwrap();
    std::os::unix::fs::symlink(slave2.name().unwrap(), &link_path).unwrap();
    drop(slave2);
    let script2 = Script::default();
    let sim2 = run_box(master2, script2.clone());
    let start = std::time::Instant::now();
    let mut fired = false;
    while start.elapsed() < Duration::from_secs(10) {
        if link.with(|b| b.fire(3, 8000)).is_ok() {
            fired = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(fired, "reconnected within 10 s");
    assert_eq!(link.reconnects, 2);
    script2.stop.store(true, Ordering::SeqCst);
    sim2.join().unwrap();
}

#[test]
fn a_capture_session_fires_through_the_box() {
    use conformd::devices::camera::{Camera, CameraInfo, CameraSettings, PixelFormat};
    use conformd::devices::capture::{CaptureOptions, Session};
    use conformd::devices::replay::ReplayCamera;
    let (master, slave) = TTYPort::pair().unwrap();
    let script = Script::default();
    let sim = run_box(master, script.clone());
    let b = client(slave).unwrap();
    let cams: Vec<Box<dyn Camera>> = ["left", "right"]
        .iter()
        .map(|s| {
            Box::new(ReplayCamera::synthetic(
                CameraInfo {
                    id: format!("pod1-{s}"),
                    pod: "pod1".into(),
                    side: s.to_string(),
                },
                16,
                12,
            )) as Box<dyn Camera>
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let settings = CameraSettings {
        format: PixelFormat::Grey,
        width: 16,
        height: 12,
        external_trigger: true,
        ..Default::default()
    };
    let mut s = Session::new(
        cams,
        Box::new(b),
        dir.path(),
        CaptureOptions {
            max_skew_ms: 50.0,
            ..Default::default()
        },
        settings,
    );
    s.configure().unwrap();
    let a = s.capture(Some("sow-1")).unwrap();
    let c = s.capture(Some("sow-1")).unwrap();
    assert_eq!(a.manifest.trigger.kind, "serial");
    assert_eq!(
        (a.manifest.trigger.sequence, c.manifest.trigger.sequence),
        (1, 2)
    );
    assert!(
        c.manifest.trigger.box_time_us.unwrap() > a.manifest.trigger.box_time_us.unwrap(),
        "the box's timestamps are recorded"
    );
    drop(s);
    script.stop.store(true, Ordering::SeqCst);
    assert_eq!(sim.join().unwrap(), 2);
}
