//! Headless Chromium (Debian's `chromium`) driven over the DevTools protocol on a pipe
//! (`--remote-debugging-pipe`: JSON messages separated by NUL on fds 3 and 4, here two FIFOs), so a
//! test can open a live page, read its DOM while it changes and collect every console message and
//! uncaught exception. Used by tests/live_page.rs and benches/live.rs.
#![allow(
    dead_code,
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::print_stderr
)]

use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

/// Debian's chromium, when installed.
pub fn find() -> Option<PathBuf> {
    ["/usr/bin/chromium", "/usr/bin/chromium-browser"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
}

/// The browser unless it is missing: then `None` (skip), or a failure under CUBECAL_REQUIRE_TOOLS=1.
pub fn required(test: &str) -> Option<PathBuf> {
    match find() {
        Some(p) => Some(p),
        None if std::env::var("CUBECAL_REQUIRE_TOOLS").is_ok_and(|v| v == "1") => {
            panic!("{test}: chromium is missing (deploy/install-test-tools.sh installs it)")
        }
        None => {
            eprintln!("{test}: SKIPPED: no chromium (apt-get install chromium)");
            None
        }
    }
}

/// One browser with one page.
pub struct Browser {
    child: Child,
    to: std::fs::File,
    from: Receiver<Value>,
    next_id: u64,
    session: String,
    /// Console messages, log entries and uncaught exceptions of the page, as text.
    pub console: Arc<Mutex<Vec<String>>>,
    _dir: tempfile::TempDir,
}

impl Browser {
    /// Start the browser with an empty page (navigate with [`Browser::goto`]).
    pub fn start(chromium: &std::path::Path) -> Browser {
        let dir = tempfile::tempdir().unwrap();
        let (fin, fout) = (dir.path().join("in"), dir.path().join("out"));
        for f in [&fin, &fout] {
            assert!(Command::new("mkfifo").arg(f).status().unwrap().success());
        }
        let child = Command::new("sh")
            .arg("-c")
            .arg(r#"exec "$0" --headless --no-sandbox --disable-gpu --disable-dev-shm-usage --no-first-run --no-default-browser-check --disable-extensions --disable-renderer-backgrounding --disable-background-timer-throttling --disable-backgrounding-occluded-windows --user-data-dir="$3" --remote-debugging-pipe about:blank 3<"$1" 4>"$2""#)
            .arg(chromium)
            .arg(&fin)
            .arg(&fout)
            .arg(dir.path().join("profile"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let to = std::fs::OpenOptions::new().write(true).open(&fin).unwrap();
        let from_file = std::fs::File::open(&fout).unwrap();
        let (tx, rx) = channel();
        std::thread::spawn(move || {
            let mut r = BufReader::new(from_file);
            loop {
                let mut buf = Vec::new();
                match r.read_until(0, &mut buf) {
                    Ok(0) | Err(_) => return,
                    Ok(_) => {
                        if buf.last() == Some(&0) {
                            buf.pop();
                        }
                        if let Ok(v) = serde_json::from_slice::<Value>(&buf)
                            && tx.send(v).is_err()
                        {
                            return;
                        }
                    }
                }
            }
        });
        let mut b = Browser {
            child,
            to,
            from: rx,
            next_id: 0,
            session: String::new(),
            console: Arc::default(),
            _dir: dir,
        };
        let targets = b.call(None, "Target.getTargets", json!({}));
        let target = targets["targetInfos"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["type"] == "page")
            .expect("a page target")["targetId"]
            .clone();
        let attached = b.call(
            None,
            "Target.attachToTarget",
            json!({ "targetId": target, "flatten": true }),
        );
        b.session = attached["sessionId"].as_str().unwrap().to_string();
        for m in ["Runtime.enable", "Log.enable", "Page.enable"] {
            b.session_call(m, json!({}));
        }
        b
    }

    fn send(&mut self, session: Option<&str>, method: &str, params: Value) -> u64 {
        self.next_id += 1;
        let mut msg = json!({ "id": self.next_id, "method": method, "params": params });
        if let Some(s) = session {
            msg["sessionId"] = json!(s);
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.to.write_all(&bytes).unwrap();
        self.to.flush().unwrap();
        self.next_id
    }

    /// Record console messages, log entries and exceptions; return a response's result.
    fn pump(&mut self, want: u64, deadline: Instant) -> Value {
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let v = match self.from.recv_timeout(left) {
                Ok(v) => v,
                Err(RecvTimeoutError::Timeout) => panic!("chromium did not answer in time"),
                Err(RecvTimeoutError::Disconnected) => panic!("chromium went away"),
            };
            match v["method"].as_str() {
                Some("Runtime.consoleAPICalled") => self.console.lock().unwrap().push(format!(
                    "console.{}: {}",
                    v["params"]["type"], v["params"]["args"]
                )),
                Some("Runtime.exceptionThrown") => self
                    .console
                    .lock()
                    .unwrap()
                    .push(format!("exception: {}", v["params"]["exceptionDetails"])),
                Some("Log.entryAdded") => self.console.lock().unwrap().push(format!(
                    "log {}: {}",
                    v["params"]["entry"]["level"], v["params"]["entry"]["text"]
                )),
                _ => {}
            }
            if v["id"].as_u64() == Some(want) {
                if let Some(e) = v.get("error") {
                    panic!("DevTools error: {e}");
                }
                return v["result"].clone();
            }
        }
    }

    fn call(&mut self, session: Option<&str>, method: &str, params: Value) -> Value {
        let id = self.send(session, method, params);
        self.pump(id, Instant::now() + Duration::from_secs(30))
    }

    fn session_call(&mut self, method: &str, params: Value) -> Value {
        let s = self.session.clone();
        self.call(Some(&s), method, params)
    }

    /// Open `url` in the page.
    pub fn goto(&mut self, url: &str) {
        self.session_call("Page.navigate", json!({ "url": url }));
    }

    /// Evaluate `expr` in the page and return its value (JSON).
    pub fn eval(&mut self, expr: &str) -> Value {
        let r = self.session_call(
            "Runtime.evaluate",
            json!({ "expression": expr, "returnByValue": true }),
        );
        r["result"]["value"].clone()
    }

    /// The page's `<body>` data attributes (`data-frames` → `frames`).
    pub fn dataset(&mut self) -> Value {
        let v = self.eval("JSON.stringify(document.body ? document.body.dataset : {})");
        serde_json::from_str(v.as_str().unwrap_or("{}")).unwrap_or(Value::Null)
    }

    /// The text of the element with `id`.
    pub fn text_of(&mut self, id: &str) -> String {
        let v = self.eval(&format!(
            "(document.getElementById({id:?}) || {{textContent: ''}}).textContent"
        ));
        v.as_str().unwrap_or("").to_string()
    }

    /// Poll `cond` on the dataset every 50 ms until it holds or `limit` passes.
    pub fn wait_for(
        &mut self,
        what: &str,
        limit: Duration,
        cond: impl Fn(&Value) -> bool,
    ) -> Value {
        let start = Instant::now();
        loop {
            let d = self.dataset();
            if cond(&d) {
                return d;
            }
            if start.elapsed() > limit {
                panic!("page never showed {what} within {limit:?}; last dataset {d}");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Save a PNG screenshot of the page.
    pub fn screenshot(&mut self, path: &std::path::Path) {
        use base64::Engine as _;
        let r = self.session_call("Page.captureScreenshot", json!({ "format": "png" }));
        let png = base64::engine::general_purpose::STANDARD
            .decode(r["data"].as_str().unwrap())
            .unwrap();
        std::fs::write(path, png).unwrap();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
