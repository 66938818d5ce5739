//! The operator's live page (issue 35, src/live): its write endpoints need the operator token, it
//! answers only to loopback names when bound to loopback, and in headless Chromium it shows a
//! synthetic run as it happens — frames updating, the coverage filling up to the verdict, the report,
//! and, on a manual stage, each prompt before the operator confirms it — with no console message.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stderr)]

#[path = "support/chromium.rs"]
mod chromium;

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use cubecal::live::{Live, Token, Waited};

/// One HTTP/1.1 request; returns the status and the body.
fn http(addr: SocketAddr, method: &str, path: &str, headers: &[(&str, &str)]) -> (u16, String) {
    http_host(addr, &addr.to_string(), method, path, headers)
}

fn http_host(
    addr: SocketAddr,
    host: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n");
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("Content-Length: 0\r\n\r\n");
    s.write_all(req.as_bytes()).unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text.split_once("\r\n\r\n").map_or("", |b| b.1).to_string();
    (status, body)
}

const TOKEN: &str = "correct-horse-battery-staple-35";

#[test]
fn writes_need_the_operator_token_and_the_page_binds_to_loopback() {
    let bearer = format!("Bearer {TOKEN}");
    let auth = [("Authorization", bearer.as_str())];
    let wrong = [("Authorization", "Bearer correct-horse-battery-staple-3")];

    // Without a token: read-only. Every write is refused, whatever is presented.
    let addr = cubecal::live::parse_addr("0").unwrap();
    assert_eq!(addr, "127.0.0.1:0", "a bare port binds to loopback");
    let stop = Arc::new(AtomicBool::new(false));
    let ro = Live::start(&addr, None, Arc::clone(&stop)).unwrap();
    assert!(ro.addr().ip().is_loopback());
    ro.run_started(Path::new("run"));
    for path in ["/api/stop", "/api/start"] {
        assert_eq!(http(ro.addr(), "POST", path, &[]).0, 403, "{path}");
        assert_eq!(http(ro.addr(), "POST", path, &auth).0, 403, "{path}");
    }
    assert!(!stop.load(Ordering::SeqCst), "a refused stop set the flag");
    let (code, state) = http(ro.addr(), "GET", "/api/state", &[]);
    assert_eq!(code, 200);
    assert!(state.contains(r#""control":false"#), "{state}");
    // The page and its script are served; nothing else.
    let (code, page) = http(ro.addr(), "GET", "/", &[]);
    assert_eq!(code, 200);
    assert!(page.contains("<script src=\"/page.js\">"), "{page}");
    assert_eq!(http(ro.addr(), "GET", "/page.js", &[]).0, 200);
    assert_eq!(http(ro.addr(), "GET", "/nothing", &[]).0, 404);
    assert_eq!(
        http(ro.addr(), "GET", "/report", &[]).0,
        404,
        "no report yet"
    );
    // DNS rebinding: a loopback-bound page answers only to loopback names.
    assert_eq!(
        http_host(ro.addr(), "evil.example:80", "GET", "/api/state", &[]).0,
        421
    );
    let port = ro.addr().port();
    assert_eq!(
        http_host(ro.addr(), &format!("localhost:{port}"), "GET", "/", &[]).0,
        200
    );
    drop(ro);

    // With a token: the writes need exactly it.
    let dir = tempfile::tempdir().unwrap();
    let token_file = dir.path().join("token");
    std::fs::write(&token_file, format!("{TOKEN}\n")).unwrap();
    let token = Token::from_file(&token_file).unwrap();
    let rw = Live::start("127.0.0.1:0", Some(token), Arc::clone(&stop)).unwrap();
    let a = rw.addr();
    rw.run_started(Path::new("run"));
    for path in ["/api/stop", "/api/start"] {
        assert_eq!(http(a, "POST", path, &[]).0, 401, "{path} without a token");
        assert_eq!(http(a, "POST", path, &wrong).0, 401, "{path} wrong token");
        assert_eq!(
            http(a, "POST", path, &[("Authorization", TOKEN)]).0,
            401,
            "{path}: not a bearer header"
        );
        assert_eq!(http(a, "GET", path, &auth).0, 405, "{path} by GET");
    }
    assert!(!stop.load(Ordering::SeqCst), "a refused stop set the flag");
    assert_eq!(http(a, "POST", "/api/start", &auth).0, 409, "start mid-run");
    assert_eq!(http(a, "POST", "/api/stop", &auth).0, 202);
    assert!(
        stop.load(Ordering::SeqCst),
        "the stop did not reach the flag"
    );
    rw.run_finished(None, 130, Some("interrupted".into()));
    assert_eq!(
        http(a, "POST", "/api/stop", &auth).0,
        409,
        "stop with no run"
    );
    assert_eq!(
        rw.wait(Some(Duration::ZERO), &AtomicBool::new(false), &mut || {}),
        Waited::Exit
    );
    assert_eq!(http(a, "POST", "/api/start", &auth).0, 202);
    assert_eq!(
        rw.wait(
            Some(Duration::from_secs(5)),
            &AtomicBool::new(false),
            &mut || {}
        ),
        Waited::Start
    );
    let (_, state) = http(a, "GET", "/api/state", &[]);
    assert!(state.contains(r#""control":true"#), "{state}");
    assert!(!state.contains(TOKEN), "the token leaked: {state}");

    // An empty token file is refused rather than taken as "no token".
    std::fs::write(&token_file, "\n").unwrap();
    assert!(matches!(
        Token::from_file(&token_file),
        Err(cubecal::live::LiveError::TokenEmpty { .. })
    ));
}

/// `cubecal calibrate … --http 127.0.0.1:0`, its stdin piped, its stderr kept.
struct Station {
    child: Child,
    stderr: Arc<Mutex<String>>,
    url: String,
}

impl Station {
    fn start(args: &[&str], out: &Path) -> Station {
        let mut child = Command::new(env!("CARGO_BIN_EXE_cubecal"))
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .args(["calibrate", "--synthetic"])
            .args(args)
            .args(["--http", ":0", "--set", "http.linger_s=120", "--out"])
            .arg(out)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stderr = Arc::new(Mutex::new(String::new()));
        let mut pipe = child.stderr.take().unwrap();
        let keep = Arc::clone(&stderr);
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = pipe.read(&mut buf) {
                if n == 0 {
                    break;
                }
                keep.lock()
                    .unwrap()
                    .push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        });
        let start = Instant::now();
        let url = loop {
            let text = stderr.lock().unwrap().clone();
            if let Some(rest) = text.split("live page: ").nth(1) {
                break rest.split_whitespace().next().unwrap().to_string();
            }
            assert!(
                start.elapsed() < Duration::from_secs(30),
                "no live page announced: {text}"
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        assert!(
            url.starts_with("http://127.0.0.1:"),
            "not on loopback: {url}"
        );
        Station { child, stderr, url }
    }

    /// SIGTERM while the page lingers: the process ends with the run's exit code.
    fn finish(mut self) -> i32 {
        let pid = self.child.id().to_string();
        assert!(
            Command::new("kill")
                .args(["-TERM", &pid])
                .status()
                .unwrap()
                .success()
        );
        let status = self.child.wait().unwrap();
        status.code().unwrap_or(-1)
    }
}

const SMALL: &[&str] = &[
    "--set",
    "synthetic.width=640",
    "--set",
    "synthetic.height=480",
    "--set",
    "synthetic.fx=560.0",
    "--set",
    "synthetic.fy=560.0",
];

fn num(v: &serde_json::Value, key: &str) -> f64 {
    v[key]
        .as_str()
        .and_then(|s| s.parse().ok())
        .unwrap_or(f64::NAN)
}

fn assert_quiet(b: &chromium::Browser) {
    let console = b.console.lock().unwrap();
    assert!(console.is_empty(), "console messages: {console:#?}");
}

#[test]
fn the_live_page_shows_a_run_in_chromium() {
    let Some(chromium) = chromium::required("the_live_page_shows_a_run_in_chromium") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // The browser first, so the page opens while the station is still homing.
    let mut b = chromium::Browser::start(&chromium);

    // 1. A quick run on the GRBL simulator: frames update, the coverage fills up to the verdict,
    //    the report appears.
    let mut args = vec!["--turntable", "sim-grbl"];
    args.extend_from_slice(SMALL);
    let run = dir.path().join("quick");
    let st = Station::start(&args, &run);
    b.goto(&st.url);
    let mut sequences = BTreeSet::new();
    let mut coverages = Vec::new();
    let start = Instant::now();
    let done = loop {
        let d = b.dataset();
        if let Some(s) = d["lastSequence"].as_str() {
            sequences.insert(s.to_string());
        }
        let c = num(&d, "coverage");
        if c.is_finite() && coverages.last() != Some(&c) {
            coverages.push(c);
        }
        if d["report"] == "shown" {
            break d;
        }
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "the run did not finish on the page: {d}\n{}",
            st.stderr.lock().unwrap()
        );
        std::thread::sleep(Duration::from_millis(30));
    };
    assert!(
        sequences.len() >= 3,
        "frames did not update on the page: sequences seen {sequences:?}"
    );
    assert!(
        num(&done, "frames") >= 3.0 && num(&done, "latencyCount") >= 3.0,
        "{done}"
    );
    // The coverage grew pose by pose and reached the value the verdict judged.
    assert!(
        coverages.len() >= 2,
        "coverage never changed: {coverages:?}"
    );
    assert!(
        coverages.windows(2).all(|w| w[1] >= w[0]),
        "coverage went down: {coverages:?}"
    );
    let result: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("result.json")).unwrap()).unwrap();
    let verdict = if result["verdict"]["pass"] == true {
        "pass"
    } else {
        "fail"
    };
    assert_eq!(done["verdict"], verdict, "{done}");
    let judged = result["verdict"]["checks"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "coverage")
        .unwrap()["value"]
        .as_f64()
        .unwrap();
    let last = *coverages.last().unwrap();
    assert!(
        last >= judged - 1e-9,
        "page coverage {last} < judged {judged}"
    );
    let cells =
        b.eval("document.querySelectorAll('#coverage rect:not([data-count=\"0\"])').length");
    let text = b.text_of("coveragetext");
    assert!(
        text.contains(&format!("/{} cells", 48))
            && text.starts_with(&format!("{}", (100.0 * last).round())),
        "{text}"
    );
    assert!(
        cells.as_u64().unwrap() as f64 >= judged * 48.0 - 1e-9,
        "{cells}"
    );
    // Every pose's outcome, the checks (with σ against its target) and the report.
    let views = result["views"].as_array().unwrap().len();
    let rows = b.eval("document.querySelectorAll('#poses tbody tr').length");
    assert_eq!(rows.as_u64(), Some(views as u64));
    let checks = b.text_of("checks");
    assert!(
        checks.contains("sigma_cx_px") && checks.contains("coverage"),
        "{checks}"
    );
    let sigma = b.text_of("sigma");
    assert!(sigma.contains("cx_px"), "{sigma}");
    let report_status = b.eval(
        "(function(){var x=new XMLHttpRequest();x.open('GET','/report',false);x.send();return x.status+' '+x.responseText.length;})()",
    );
    assert!(
        report_status.as_str().unwrap().starts_with("200 "),
        "{report_status}"
    );
    eprintln!(
        "quick run: {} frames on the page, grab-to-page latency mean {} ms, p95 {} ms, max {} ms",
        done["frames"], done["latencyMeanMs"], done["latencyP95Ms"], done["latencyMaxMs"]
    );
    if let Ok(shots) = std::env::var("LIVE_SHOTS") {
        b.screenshot(&Path::new(&shots).join("live_quick.png"));
    }
    assert_quiet(&b);
    assert_eq!(st.finish(), result_exit(&result), "exit code");

    // 2. A manual stage: each pose's prompt is on the page before the operator confirms it.
    let mut args = vec!["--turntable", "manual", "--set", "plan.poses=4"];
    args.extend_from_slice(SMALL);
    let mut st = Station::start(&args, &dir.path().join("manual"));
    b.goto(&st.url);
    let mut stdin = st.child.stdin.take().unwrap();
    // Homing, then the four poses.
    for k in 0..=4u32 {
        let d = b.wait_for(&format!("prompt {k}"), Duration::from_secs(60), |d| {
            num(d, "prompts") >= f64::from(k + 1)
        });
        let prompt = b.text_of("prompt");
        let (head, instruction) = prompt.split_once(": ").unwrap();
        let want = if k == 0 {
            "homing".to_string()
        } else {
            format!("pose {k}/4")
        };
        assert_eq!(head, want, "{prompt}");
        assert!(instruction.contains("turntable"), "{prompt}");
        // The same words the terminal asks for, and the station waits for the operator.
        let start = Instant::now();
        while !st.stderr.lock().unwrap().contains(instruction) {
            assert!(start.elapsed() < Duration::from_secs(30), "{prompt}");
            std::thread::sleep(Duration::from_millis(20));
        }
        let now = b.dataset();
        assert_eq!(
            num(&now, "prompts"),
            f64::from(k + 1),
            "ran ahead of the operator: {d} then {now}"
        );
        stdin.write_all(b"\n").unwrap();
        stdin.flush().unwrap();
    }
    let d = b.wait_for("the verdict", Duration::from_secs(60), |d| {
        d["verdict"] == "pass" || d["verdict"] == "fail"
    });
    assert!(num(&d, "frames") >= 2.0, "{d}");
    assert_quiet(&b);
    drop(stdin);
    let code = st.finish();
    assert!([0, 5, 6].contains(&code), "exit {code}");
}

fn result_exit(result: &serde_json::Value) -> i32 {
    if result["verdict"]["pass"] == true {
        0
    } else if result["calibration"].is_null() {
        5
    } else {
        6
    }
}
