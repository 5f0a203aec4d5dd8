//! A WebDriver session on Debian's chromedriver driving headless Chromium (software
//! WebGL), for the capture page's test and the viewer benchmark. The driver listens on
//! 127.0.0.1 only and is killed with its guard.

// each includer uses some of the calls
#![allow(dead_code)]

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

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
