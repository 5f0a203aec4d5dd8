//! A simulated trigger box on a pseudo-terminal, for the demo and the daemon's tests: it
//! speaks the box's line protocol on the master side (HELLO, ARM, FIRE, PING) and sends
//! button and RFID events when asked. The daemon opens the slave side by its path, as it
//! would open `/dev/serial/by-id/...`.

use serialport::{SerialPort, TTYPort};
use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::mpsc::{Receiver, Sender};
use std::time::Duration;

pub struct SimulatedBox {
    /// the device path a host opens (`/dev/pts/N`)
    pub device: PathBuf,
    events: Sender<String>,
    stop: Arc<AtomicBool>,
    fired: Arc<AtomicU32>,
    // the slave end stays open so the pty lives while no host has it open
    _slave: TTYPort,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl SimulatedBox {
    /// Opens a pseudo-terminal pair and runs the box on its master side.
    pub fn start() -> Result<SimulatedBox, serialport::Error> {
        let (master, slave) = TTYPort::pair()?;
        let device = PathBuf::from(slave.name().unwrap_or_default());
        let (events, rx) = std::sync::mpsc::channel();
        let stop = Arc::new(AtomicBool::new(false));
        let fired = Arc::new(AtomicU32::new(0));
        let (s, f) = (stop.clone(), fired.clone());
        let thread = std::thread::spawn(move || run(master, rx, s, f));
        Ok(SimulatedBox {
            device,
            events,
            stop,
            fired,
            _slave: slave,
            thread: Some(thread),
        })
    }

    /// The operator presses the capture button.
    pub fn button(&self) {
        let _ = self.events.send("EVT BUTTON 0".into());
    }

    /// The RFID reader reads `tag`.
    pub fn rfid(&self, tag: &str) {
        let _ = self.events.send(format!("EVT RFID {tag} 0"));
    }

    /// FIRE commands acknowledged so far.
    pub fn fired(&self) -> u32 {
        self.fired.load(Ordering::SeqCst)
    }
}

impl Drop for SimulatedBox {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn run(master: TTYPort, events: Receiver<String>, stop: Arc<AtomicBool>, fired: Arc<AtomicU32>) {
    let Ok(mut writer) = master.try_clone_native() else {
        return;
    };
    let mut master = master;
    let _ = master.set_timeout(Duration::from_millis(20));
    let mut reader = BufReader::new(master);
    let mut t = 1_000_000u64;
    let mut line = String::new();
    let mut connected = false;
    while !stop.load(Ordering::SeqCst) {
        // events go out once a host has said HELLO
        if connected {
            while let Ok(e) = events.try_recv() {
                let e = e.replacen(" 0", &format!(" {t}"), 1);
                let _ = writer.write_all(format!("{e}\n").as_bytes());
            }
        }
        line.clear();
        match reader.read_line(&mut line) {
            Ok(n) if n > 0 => {}
            _ => {
                std::thread::sleep(Duration::from_millis(5));
                continue;
            }
        }
        t += 1000;
        let tok: Vec<&str> = line.split_whitespace().collect();
        let reply = match tok.as_slice() {
            ["HELLO", "conformd", v] => {
                connected = true;
                format!("HELLO simbox {v} sim-1\n")
            }
            ["ARM", seq] => format!("ARMED {seq}\n"),
            ["FIRE", seq, _] => {
                fired.fetch_add(1, Ordering::SeqCst);
                format!("ACK {seq} {t}\n")
            }
            ["PING"] => format!("PONG {t}\n"),
            _ => "ERR - E_UNKNOWN what\n".into(),
        };
        let _ = writer.write_all(reply.as_bytes());
    }
}
