//! A WebDriver session on Debian's chromedriver driving headless Chromium (software
//! WebGL), for the capture page's test and the viewer benchmark. The driver listens on
//! 127.0.0.1 only and is killed with its guard.

// each includer uses some of the calls
#![allow(dead_code)]

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The key of an element reference in WebDriver's JSON (the W3C standard's constant).
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

pub struct Browser {
    driver: Child,
    url: String,
    session: String,
    agent: ureq::Agent,
}

impl Browser {
    /// A session whose window is `width` x `height`, its profile in `profile`.
    pub fn start(profile: &Path, width: u32, height: u32) -> Browser {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let driver = Command::new("chromedriver")
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect(
                "chromedriver is needed: `make test` installs Debian's chromium-driver package",
            );
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(120)))
            .build()
            .into();
        let mut b = Browser {
            driver,
            url: format!("http://127.0.0.1:{port}"),
            session: String::new(),
            agent,
        };
        let t = Instant::now();
        while !b
            .agent
            .get(&format!("{}/status", b.url))
            .call()
            .is_ok_and(|r| r.status() == 200)
        {
            assert!(
                t.elapsed() < Duration::from_secs(30),
                "chromedriver did not answer"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        let caps = serde_json::json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            // a script may draw many frames on the CPU (the viewer benchmark's 36 of a
            // 400k-point scan); under the HTTP client's 120 s
            "timeouts": {"script": 100_000},
            "goog:chromeOptions": {"args": [
                "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                "--disable-background-networking", "--disable-component-update",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                format!("--window-size={width},{height}"),
                format!("--user-data-dir={}", profile.display()),
            ]}
        }}});
        let v = b.call("session", caps);
        b.session = v["sessionId"].as_str().expect("a session").to_string();
        b
    }

    fn call(&self, path: &str, body: serde_json::Value) -> serde_json::Value {
        let r = self
            .agent
            .post(&format!("{}/{path}", self.url))
            .header("Content-Type", "application/json")
            .send(body.to_string().as_bytes());
        let (code, text) = match r {
            Ok(mut r) => (
                r.status().as_u16(),
                r.body_mut().read_to_string().unwrap_or_default(),
            ),
            Err(e) => (0, e.to_string()),
        };
        let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
        assert_eq!(code, 200, "WebDriver {path}: {text}");
        v["value"].clone()
    }

    pub fn go(&self, url: &str) {
        self.call(
            &format!("session/{}/url", self.session),
            serde_json::json!({ "url": url }),
        );
    }

    /// Runs `script` in the page (its arguments `args`); returns what it returns.
    pub fn run(&self, script: &str, args: serde_json::Value) -> serde_json::Value {
        self.call(
            &format!("session/{}/execute/sync", self.session),
            serde_json::json!({ "script": script, "args": args }),
        )
    }

    /// Runs `script`, which calls its last argument with the answer when done.
    pub fn run_async(&self, script: &str, args: serde_json::Value) -> serde_json::Value {
        self.call(
            &format!("session/{}/execute/async", self.session),
            serde_json::json!({ "script": script, "args": args }),
        )
    }

    /// The first element `css` selects (fails when there is none).
    fn element(&self, css: &str) -> String {
        let v = self.call(
            &format!("session/{}/element", self.session),
            serde_json::json!({ "using": "css selector", "value": css }),
        );
        v[ELEMENT]
            .as_str()
            .unwrap_or_else(|| panic!("no element '{css}': {v}"))
            .to_string()
    }

    /// Clicks the element `css` selects, as a person would (WebDriver's element click:
    /// scrolled into view, the pointer at its centre).
    pub fn click(&self, css: &str) {
        let e = self.element(css);
        self.call(
            &format!("session/{}/element/{e}/click", self.session),
            serde_json::json!({}),
        );
    }

    /// Types `text` into the element `css` selects, key by key.
    pub fn type_into(&self, css: &str, text: &str) {
        let e = self.element(css);
        self.call(
            &format!("session/{}/element/{e}/value", self.session),
            serde_json::json!({ "text": text }),
        );
    }

    /// The left mouse button pressed at `from` and let go at `to`, moving in between;
    /// points in pixels from the centre of the element `css` selects. The same point
    /// twice is a click.
    pub fn press_and_release(&self, css: &str, from: (i64, i64), to: (i64, i64)) {
        let e = self.element(css);
        let origin = serde_json::json!({ ELEMENT: e });
        // at once, so that the element does not move under the pointer (a smooth
        // scroll still running from an earlier click did)
        self.run(
            "arguments[0].scrollIntoView({ block: 'center', behavior: 'instant' });",
            serde_json::json!([origin]),
        );
        let actions = serde_json::json!({ "actions": [{
            "type": "pointer", "id": "mouse", "parameters": { "pointerType": "mouse" },
            "actions": [
                { "type": "pointerMove", "duration": 0, "origin": origin, "x": from.0, "y": from.1 },
                { "type": "pointerDown", "button": 0 },
                { "type": "pointerMove", "duration": 200, "origin": origin, "x": to.0, "y": to.1 },
                { "type": "pointerUp", "button": 0 },
            ],
        }]});
        self.call(&format!("session/{}/actions", self.session), actions);
    }

    /// Waits (up to `limit`) until `script` returns true.
    pub fn wait_for(&self, script: &str, what: &str, limit: Duration) {
        let t = Instant::now();
        while self.run(script, serde_json::json!([])) != serde_json::json!(true) {
            assert!(t.elapsed() < limit, "waited {limit:?} for {what}");
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            let _ = self
                .agent
                .delete(&format!("{}/session/{}", self.url, self.session))
                .call();
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}
