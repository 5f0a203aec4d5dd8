//! The trigger box: a serial line protocol (documented in the README), a client that
//! checks every line, and a link that reconnects with backoff when the device disappears
//! (a USB adapter unplugged) and comes back.
//!
//! Lines are ASCII, at most 120 bytes, ending in `\n`. Host to box:
//! `HELLO conformd 1`, `ARM <seq>`, `FIRE <seq> <exposure_us>`, `PING`.
//! Box to host: `HELLO <name> <protocol> <firmware>`, `ARMED <seq>`,
//! `ACK <seq> <box_time_us>`, `PONG <box_time_us>`, and at any time the events
//! `EVT BUTTON <box_time_us>`, `EVT RFID <tag> <box_time_us>`, `EVT FAULT <code> <text>`,
//! or `ERR <seq|-> <code> <text>` for a refused command. Garbage, over-long and unknown
//! lines are reported and skipped, never fatal.

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

pub const PROTOCOL: u32 = 1;
pub const MAX_LINE: usize = 120;

/// A line from the box.
#[derive(Debug, Clone, PartialEq)]
pub enum BoxMessage {
    Hello {
        name: String,
        protocol: u32,
        firmware: String,
    },
    Armed {
        seq: u32,
    },
    Ack {
        seq: u32,
        box_time_us: u64,
    },
    Pong {
        box_time_us: u64,
    },
    Event(BoxEvent),
    Error {
        seq: Option<u32>,
        code: String,
        text: String,
    },
}

/// Something the box reports on its own.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "event", rename_all = "lowercase")]
pub enum BoxEvent {
    /// the operator pressed the capture button
    Button {
        box_time_us: u64,
    },
    /// an RFID reader read an animal's tag
    Rfid {
        tag: String,
        box_time_us: u64,
    },
    Fault {
        code: String,
        text: String,
    },
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TriggerError {
    #[error("trigger box {port}: {msg}")]
    Io { port: String, msg: String },
    #[error("trigger box {port}: no answer to {command} within {waited_ms} ms")]
    NoAnswer {
        port: String,
        command: String,
        waited_ms: u64,
    },
    #[error("trigger box {port}: speaks protocol {got}, conformd speaks {PROTOCOL}")]
    Protocol { port: String, got: u32 },
    #[error("trigger box {port}: refused {command}: {code} {text}")]
    Refused {
        port: String,
        command: String,
        code: String,
        text: String,
    },
    #[error("trigger box {port}: not connected (next attempt in {retry_ms} ms)")]
    Disconnected { port: String, retry_ms: u64 },
}

/// A line from the box that is not a message of the protocol: reported, then skipped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LineError {
    #[error("line of {0} bytes (at most {MAX_LINE})")]
    TooLong(usize),
    #[error("over-long line (more than {MAX_LINE} bytes) skipped")]
    Skipped,
    #[error("line with non-printable bytes")]
    NonPrintable,
    #[error("'{0}': a field is missing")]
    MissingField(String),
    #[error("'{line}': '{token}' is not a number")]
    NotANumber { line: String, token: String },
    #[error("'{0}': sequence too large")]
    SequenceTooLarge(String),
    #[error("'{line}': expected {expected} fields, found {found}")]
    FieldCount {
        line: String,
        expected: usize,
        found: usize,
    },
    #[error("'{0}': unknown event")]
    UnknownEvent(String),
    #[error("unknown message '{0}'")]
    UnknownMessage(String),
    #[error("empty line")]
    Empty,
}

/// Parses one line from the box (without its newline).
pub fn parse_line(line: &str) -> Result<BoxMessage, LineError> {
    if line.len() > MAX_LINE {
        return Err(LineError::TooLong(line.len()));
    }
    if !line.bytes().all(|b| (0x20..0x7f).contains(&b)) {
        return Err(LineError::NonPrintable);
    }
    let whole = || line.to_string();
    let tok: Vec<&str> = line.split_whitespace().collect();
    let num = |i: usize| -> Result<u64, LineError> {
        tok.get(i)
            .ok_or_else(|| LineError::MissingField(whole()))?
            .parse::<u64>()
            .map_err(|_| LineError::NotANumber {
                line: whole(),
                token: tok[i].to_string(),
            })
    };
    let seq = |i: usize| -> Result<u32, LineError> {
        num(i).and_then(|v| u32::try_from(v).map_err(|_| LineError::SequenceTooLarge(whole())))
    };
    let rest = |i: usize| tok.get(i..).map(|t| t.join(" ")).unwrap_or_default();
    let exact = |n: usize| {
        if tok.len() == n {
            Ok(())
        } else {
            Err(LineError::FieldCount {
                line: whole(),
                expected: n,
                found: tok.len(),
            })
        }
    };
    Ok(match tok.first().copied() {
        Some("HELLO") => {
            exact(4)?;
            BoxMessage::Hello {
                name: tok[1].into(),
                protocol: seq(2)?,
                firmware: tok[3].into(),
            }
        }
        Some("ARMED") => {
            exact(2)?;
            BoxMessage::Armed { seq: seq(1)? }
        }
        Some("ACK") => {
            exact(3)?;
            BoxMessage::Ack {
                seq: seq(1)?,
                box_time_us: num(2)?,
            }
        }
        Some("PONG") => {
            exact(2)?;
            BoxMessage::Pong {
                box_time_us: num(1)?,
            }
        }
        Some("EVT") => match tok.get(1).copied() {
            Some("BUTTON") => {
                exact(3)?;
                BoxMessage::Event(BoxEvent::Button {
                    box_time_us: num(2)?,
                })
            }
            Some("RFID") => {
                exact(4)?;
                BoxMessage::Event(BoxEvent::Rfid {
                    tag: tok[2].into(),
                    box_time_us: num(3)?,
                })
            }
            Some("FAULT") if tok.len() >= 3 => BoxMessage::Event(BoxEvent::Fault {
                code: tok[2].into(),
                text: rest(3),
            }),
            _ => return Err(LineError::UnknownEvent(whole())),
        },
        Some("ERR") if tok.len() >= 3 => BoxMessage::Error {
            seq: if tok[1] == "-" { None } else { Some(seq(1)?) },
            code: tok[2].into(),
            text: rest(3),
        },
        Some(other) => return Err(LineError::UnknownMessage(other.to_string())),
        None => return Err(LineError::Empty),
    })
}

/// Reads lines from a byte stream, skipping over-long ones whole.
struct LineReader {
    buf: Vec<u8>,
    overflow: bool,
}

impl LineReader {
    /// Takes bytes; returns complete lines and the problems met (over-long lines).
    fn feed(&mut self, bytes: &[u8], lines: &mut Vec<Result<String, LineError>>) {
        for &b in bytes {
            if b == b'\n' {
                if self.overflow {
                    lines.push(Err(LineError::Skipped));
                } else {
                    let s = String::from_utf8_lossy(&self.buf)
                        .trim_end_matches('\r')
                        .to_string();
                    lines.push(Ok(s));
                }
                self.buf.clear();
                self.overflow = false;
            } else if self.buf.len() >= MAX_LINE {
                self.overflow = true;
            } else {
                self.buf.push(b);
            }
        }
    }
}

/// A connected trigger box.
pub struct TriggerBox<P: Read + Write> {
    port: P,
    name: String,
    reader: LineReader,
    pending: VecDeque<Result<String, LineError>>,
    /// events received while waiting for answers, oldest first
    pub events: VecDeque<BoxEvent>,
    /// lines that were garbage, over-long or unknown: reported, then skipped
    pub warnings: Vec<String>,
    pub reply_timeout: Duration,
    pub firmware: String,
}

impl<P: Read + Write> TriggerBox<P> {
    /// Wraps an open port and shakes hands (protocol version checked). The port's own
    /// read timeout should be short (tens of milliseconds): deadlines are kept here.
    pub fn connect(port: P, name: &str, reply_timeout: Duration) -> Result<Self, TriggerError> {
        let mut b = TriggerBox {
            port,
            name: name.into(),
            reader: LineReader {
                buf: Vec::new(),
                overflow: false,
            },
            pending: VecDeque::new(),
            events: VecDeque::new(),
            warnings: Vec::new(),
            reply_timeout,
            firmware: String::new(),
        };
        b.send(&format!("HELLO conformd {PROTOCOL}"))?;
        match b.wait("HELLO", |m| matches!(m, BoxMessage::Hello { .. }))? {
            BoxMessage::Hello {
                protocol, firmware, ..
            } => {
                if protocol != PROTOCOL {
                    return Err(TriggerError::Protocol {
                        port: b.name.clone(),
                        got: protocol,
                    });
                }
                b.firmware = firmware;
            }
            _ => unreachable!(),
        }
        Ok(b)
    }

    fn io(&self, e: impl std::fmt::Display) -> TriggerError {
        TriggerError::Io {
            port: self.name.clone(),
            msg: e.to_string(),
        }
    }

    fn send(&mut self, line: &str) -> Result<(), TriggerError> {
        let mut bytes = line.as_bytes().to_vec();
        bytes.push(b'\n');
        self.port
            .write_all(&bytes)
            .and_then(|_| self.port.flush())
            .map_err(|e| self.io(e))
    }

    /// Next line within the deadline (None when it passes).
    fn next_line(
        &mut self,
        deadline: Instant,
    ) -> Result<Option<Result<String, LineError>>, TriggerError> {
        loop {
            if let Some(l) = self.pending.pop_front() {
                return Ok(Some(l));
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            let mut buf = [0u8; 256];
            match self.port.read(&mut buf) {
                Ok(0) => return Err(self.io("the port closed")),
                Ok(n) => {
                    let mut lines = Vec::new();
                    self.reader.feed(&buf[..n], &mut lines);
                    self.pending.extend(lines);
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.io(e)),
            }
        }
    }

    /// Waits for a message `want` accepts; events are queued, garbage reported and
    /// skipped, an ERR for this command returned as an error.
    fn wait(
        &mut self,
        command: &str,
        want: impl Fn(&BoxMessage) -> bool,
    ) -> Result<BoxMessage, TriggerError> {
        let start = Instant::now();
        let deadline = start + self.reply_timeout;
        while let Some(line) = self.next_line(deadline)? {
            let msg = match line.and_then(|l| parse_line(&l)) {
                Ok(m) => m,
                Err(w) => {
                    self.warnings.push(w.to_string());
                    continue;
                }
            };
            match msg {
                BoxMessage::Event(e) => self.events.push_back(e),
                BoxMessage::Error { code, text, .. } => {
                    return Err(TriggerError::Refused {
                        port: self.name.clone(),
                        command: command.into(),
                        code,
                        text,
                    });
                }
                m if want(&m) => return Ok(m),
                m => self.warnings.push(format!(
                    "unexpected {m:?} while waiting for the answer to {command}"
                )),
            }
        }
        Err(TriggerError::NoAnswer {
            port: self.name.clone(),
            command: command.into(),
            waited_ms: start.elapsed().as_millis() as u64,
        })
    }

    pub fn arm(&mut self, seq: u32) -> Result<(), TriggerError> {
        self.send(&format!("ARM {seq}"))?;
        self.wait(
            &format!("ARM {seq}"),
            |m| matches!(m, BoxMessage::Armed { seq: s } if *s == seq),
        )
        .map(|_| ())
    }

    /// Fires the cameras; returns the box's timestamp of the pulse.
    pub fn fire(&mut self, seq: u32, exposure_us: u32) -> Result<u64, TriggerError> {
        self.send(&format!("FIRE {seq} {exposure_us}"))?;
        match self.wait(
            &format!("FIRE {seq}"),
            |m| matches!(m, BoxMessage::Ack { seq: s, .. } if *s == seq),
        )? {
            BoxMessage::Ack { box_time_us, .. } => Ok(box_time_us),
            _ => unreachable!(),
        }
    }

    pub fn ping(&mut self) -> Result<u64, TriggerError> {
        self.send("PING")?;
        match self.wait("PING", |m| matches!(m, BoxMessage::Pong { .. }))? {
            BoxMessage::Pong { box_time_us } => Ok(box_time_us),
            _ => unreachable!(),
        }
    }

    /// Reads whatever the box has sent (events) for up to `wait`.
    pub fn poll_events(&mut self, wait: Duration) -> Result<Vec<BoxEvent>, TriggerError> {
        let deadline = Instant::now() + wait;
        while let Some(line) = self.next_line(deadline)? {
            match line.and_then(|l| parse_line(&l)) {
                Ok(BoxMessage::Event(e)) => self.events.push_back(e),
                Ok(m) => self.warnings.push(format!("unexpected {m:?}")),
                Err(w) => self.warnings.push(w.to_string()),
            }
        }
        Ok(self.events.drain(..).collect())
    }
}

/// A trigger box on a serial device path that reconnects by itself: after the device
/// disappears, each operation tries to reopen it, waiting 100 ms, then twice as long
/// after each failure, up to `max_backoff`.
pub struct TriggerLink {
    pub path: PathBuf,
    pub baud: u32,
    pub reply_timeout: Duration,
    pub max_backoff: Duration,
    conn: Option<TriggerBox<serialport::TTYPort>>,
    backoff: Duration,
    next_attempt: Instant,
    pub reconnects: u32,
}

impl TriggerLink {
    pub fn new(path: &Path, baud: u32, reply_timeout: Duration) -> Self {
        TriggerLink {
            path: path.to_path_buf(),
            baud,
            reply_timeout,
            max_backoff: Duration::from_secs(5),
            conn: None,
            backoff: Duration::from_millis(100),
            next_attempt: Instant::now(),
            reconnects: 0,
        }
    }

    pub fn is_connected(&self) -> bool {
        self.conn.is_some()
    }

    fn name(&self) -> String {
        self.path.display().to_string()
    }

    /// The connection, opening it if it is due.
    pub fn connection(&mut self) -> Result<&mut TriggerBox<serialport::TTYPort>, TriggerError> {
        if self.conn.is_none() {
            let now = Instant::now();
            if now < self.next_attempt {
                return Err(TriggerError::Disconnected {
                    port: self.name(),
                    retry_ms: (self.next_attempt - now).as_millis() as u64,
                });
            }
            let opened = serialport::new(self.path.to_string_lossy(), self.baud)
                .timeout(Duration::from_millis(20))
                .open_native()
                .map_err(|e| TriggerError::Io {
                    port: self.name(),
                    msg: e.to_string(),
                })
                .and_then(|p| TriggerBox::connect(p, &self.name(), self.reply_timeout));
            match opened {
                Ok(c) => {
                    self.conn = Some(c);
                    self.backoff = Duration::from_millis(100);
                    self.reconnects += 1;
                }
                Err(e) => {
                    self.next_attempt = Instant::now() + self.backoff;
                    self.backoff = (self.backoff * 2).min(self.max_backoff);
                    return Err(e);
                }
            }
        }
        Ok(self.conn.as_mut().expect("just connected"))
    }

    /// Runs one operation; an I/O failure drops the connection so the next call reopens.
    pub fn with<T>(
        &mut self,
        op: impl FnOnce(&mut TriggerBox<serialport::TTYPort>) -> Result<T, TriggerError>,
    ) -> Result<T, TriggerError> {
        let r = op(self.connection()?);
        if matches!(
            r,
            Err(TriggerError::Io { .. }) | Err(TriggerError::NoAnswer { .. })
        ) {
            self.conn = None;
            self.next_attempt = Instant::now() + self.backoff;
        }
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_are_checked() {
        assert_eq!(
            parse_line("ACK 7 123456"),
            Ok(BoxMessage::Ack {
                seq: 7,
                box_time_us: 123456
            })
        );
        assert_eq!(
            parse_line("EVT RFID 982000123456789 55"),
            Ok(BoxMessage::Event(BoxEvent::Rfid {
                tag: "982000123456789".into(),
                box_time_us: 55
            }))
        );
        assert_eq!(
            parse_line("ERR 3 E_BUSY still charging"),
            Ok(BoxMessage::Error {
                seq: Some(3),
                code: "E_BUSY".into(),
                text: "still charging".into()
            })
        );
        assert!(
            parse_line("ACK seven 1")
                .unwrap_err()
                .to_string()
                .contains("'seven' is not a number")
        );
        assert!(
            parse_line("ACK 1")
                .unwrap_err()
                .to_string()
                .contains("expected 3 fields")
        );
        assert!(
            parse_line("WHAT 1")
                .unwrap_err()
                .to_string()
                .contains("unknown message 'WHAT'")
        );
        assert!(
            parse_line("ACK 1 2\u{7}")
                .unwrap_err()
                .to_string()
                .contains("non-printable")
        );
        let mut r = LineReader {
            buf: vec![],
            overflow: false,
        };
        let mut out = Vec::new();
        r.feed(&[b'x'; 300], &mut out);
        r.feed(b"\nPONG 5\n", &mut out);
        assert_eq!(out[0], Err(LineError::Skipped));
        assert_eq!(out[1], Ok("PONG 5".to_string()));
    }
}
