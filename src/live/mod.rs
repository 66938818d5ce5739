//! The operator's screen: a small web page, served by the station's process, that shows a run as it
//! happens — the current frame with the detected corners drawn over it, the coverage map filling up,
//! the σ of each parameter against its target, the operator's prompt, each pose's accept/reject
//! reason, the verdict, and the run's report when it is done (`cubecal calibrate|serve --http ADDR`).
//!
//! ## A renderer, like the CLI and `STATUS=`
//! The page renders the station's [`Event`] stream and nothing else: [`LiveSink`] is an
//! [`EventSink`] that turns each event into one server-sent event (`event: station`, the event's
//! JSON exactly as `--json` prints it) for every open page; the page's script draws them. No
//! decision of the station is taken here or in the page. The station does not know this module (it
//! sits at the report layer: it imports the station's event types, never the reverse).
//!
//! Frames reach the page through [`Event::Frame`], which the station makes only for a sink that
//! [wants frames](EventSink::wants_frames). [`LiveSink`] hands each frame to one encoder thread
//! through a channel of one slot and never waits: when the encoder is still busy with the previous
//! frame, the new one is dropped for the page (the station's own copy is untouched). The encoder
//! reduces the frame with [`crate::run::preview::downscale`] to at most [`FRAME_WIDTH`] px wide,
//! encodes it as JPEG and sends it as `event: frame` with the grab time, so the page can show the
//! grab-to-screen latency. Each page has its own bounded queue: a page too slow for the frames skips
//! frames; one too slow for the events is disconnected, and its `EventSource` reconnects and is sent
//! the run's events from the start again (the server keeps the current run's events).
//!
//! ## Why tiny_http
//! The station is synchronous (threads, no async runtime), and the page needs four small routes, a
//! long-lived event stream and two POSTs. `tiny_http` is a small, maintained, synchronous HTTP/1.1
//! server (four small dependencies, no TLS by default); axum would bring tokio, hyper and tower for
//! the same four routes. The event stream is written by hand on the connection
//! ([`tiny_http::Request::into_writer`]) so that every message is flushed when it is sent.
//!
//! ## Read-only unless an operator token is configured
//! Without a token (`http.token_file`, `--http-token-file`) every write endpoint answers 403. With
//! one, `POST /api/stop` sets the station's stop flag (the same flag SIGINT/SIGTERM set: the run
//! stops the turntable and closes its session marked incomplete) and `POST /api/start` asks the
//! front end for a new run; both need `Authorization: Bearer TOKEN` (401 otherwise). The token is
//! read from a file (never given on the command line, never logged), compared in constant time, and
//! typed into the page by the operator. A header a cross-site form cannot send guards the POSTs
//! against cross-site requests; the server answers no CORS preflight. When bound to a loopback
//! address (the default, `127.0.0.1`) requests must name a loopback host, so a web site that rebinds
//! its DNS name to 127.0.0.1 cannot read the page either.
//!
//! Routes: `GET /` the page, `GET /page.js` its script, `GET /events` the event stream, `GET
//! /report` the finished run's `report.html`, `GET /api/state` a JSON summary, `POST /api/start`,
//! `POST /api/stop`.

use std::io::Write;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime};

use crate::station::event::FrameImage;
use crate::station::{Event, EventSink};

mod server;

/// Widest frame sent to the page (px): frames are reduced by an integer factor to at most this.
pub const FRAME_WIDTH: u32 = 640;
/// JPEG quality of the page's frames.
pub const JPEG_QUALITY: u8 = 80;
/// Pages open at once; more are refused (503).
pub const MAX_VIEWERS: usize = 16;
/// Messages queued per page before it skips frames (and, for other events, is disconnected).
const VIEWER_QUEUE: usize = 256;
/// Events of one run kept for pages that open later.
const MAX_HISTORY: usize = 20_000;
/// The port when `--http` names none.
pub const DEFAULT_PORT: u16 = 8035;

/// Errors of the live page.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error("--http {value}: expected PORT, HOST:PORT or IP:PORT (e.g. 8035, 127.0.0.1:8035)")]
    Address { value: String },
    #[error("cannot listen on {addr} for the live page")]
    Bind {
        addr: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    #[error("cannot read the operator token file {path}")]
    TokenRead {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "the operator token file {path} is empty (or its first line is): put a long random token on its first line"
    )]
    TokenEmpty { path: PathBuf },
    #[error("cannot start the live page's threads")]
    Thread(#[source] std::io::Error),
}

impl LiveError {
    pub fn exit_code(&self) -> u8 {
        match self {
            LiveError::Address { .. } | LiveError::TokenEmpty { .. } => crate::exit::BAD_INPUT,
            LiveError::TokenRead { .. } => crate::exit::BAD_INPUT,
            LiveError::Bind { .. } => crate::exit::DEVICE,
            LiveError::Thread(_) => crate::exit::INTERNAL,
        }
    }
}

/// Parse `--http`'s value: `PORT`, `:PORT`, `HOST:PORT` or `IP:PORT` (`[::1]:PORT`); a missing host
/// is `127.0.0.1`, the loopback address: the page is visible only on this machine unless a
/// host is named.
pub fn parse_addr(value: &str) -> Result<String, LiveError> {
    let bad = || LiveError::Address {
        value: value.to_string(),
    };
    let v = value.trim();
    if v.is_empty() {
        return Ok(format!("127.0.0.1:{DEFAULT_PORT}"));
    }
    let port_only = v.strip_prefix(':').unwrap_or(v);
    if let Ok(port) = port_only.parse::<u16>() {
        return Ok(format!("127.0.0.1:{port}"));
    }
    if v.parse::<SocketAddr>().is_ok() {
        return Ok(v.to_string());
    }
    match v.rsplit_once(':') {
        Some((host, port))
            if !host.is_empty() && !host.contains(':') && port.parse::<u16>().is_ok() =>
        {
            Ok(v.to_string())
        }
        _ => Err(bad()),
    }
}

/// An operator token (compared in constant time; `Debug` never shows it).
#[derive(Clone)]
pub struct Token(String);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(…)")
    }
}

impl Token {
    /// The first line of `path`, trimmed. Warns (without the token) when the file can be read by
    /// others than its owner.
    pub fn from_file(path: &Path) -> Result<Token, LiveError> {
        let text = std::fs::read_to_string(path).map_err(|source| LiveError::TokenRead {
            path: path.to_path_buf(),
            source,
        })?;
        let token = text.lines().next().unwrap_or("").trim().to_string();
        if token.is_empty() {
            return Err(LiveError::TokenEmpty {
                path: path.to_path_buf(),
            });
        }
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            if let Ok(meta) = std::fs::metadata(path)
                && meta.permissions().mode() & 0o077 != 0
            {
                tracing::warn!(
                    path = %path.display(),
                    "the operator token file can be read by other users; chmod 600 it"
                );
            }
        }
        Ok(Token(token))
    }

    /// A token from a string (tests, and front ends that hold it already).
    pub fn new(token: impl Into<String>) -> Token {
        Token(token.into())
    }

    /// Constant-time comparison with what a request presented.
    pub fn matches(&self, presented: &str) -> bool {
        let (a, b) = (self.0.as_bytes(), presented.as_bytes());
        let mut diff = a.len() ^ b.len();
        for (i, x) in a.iter().enumerate() {
            diff |= usize::from(x ^ b.get(i).copied().unwrap_or(0));
        }
        diff == 0
    }
}

/// What the page's operator asked for ([`Live::wait`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request {
    /// `POST /api/start`: run the station again.
    Start,
}

/// How a wait after a run ended ([`Live::wait`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Waited {
    /// The operator asked for a new run.
    Start,
    /// The linger time passed, or the process was asked to stop.
    Exit,
}

/// Shared between the sink, the encoder, the server and the viewer threads.
#[derive(Debug)]
struct Shared {
    state: Mutex<State>,
    token: Option<Token>,
    /// The station's stop flag of the current run (set by `POST /api/stop`).
    stop: Arc<AtomicBool>,
    requests: Mutex<mpsc::Sender<Request>>,
    shutdown: AtomicBool,
    frames_dropped: AtomicU64,
}

#[derive(Debug, Default)]
struct State {
    /// The current run's events as server-sent-event messages, for pages that open later.
    history: Vec<Arc<str>>,
    /// The latest frame message.
    last_frame: Option<Arc<str>>,
    viewers: Vec<SyncSender<Arc<str>>>,
    /// Runs started so far (the current one's number).
    run: u64,
    running: bool,
    /// The finished run's report, served at `/report`.
    report: Option<PathBuf>,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock leaves plain data: keep serving it.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Send `msg` to every page; `keep` puts it in the run's history. A page whose queue is full
    /// skips a frame, and is disconnected for any other message (it reconnects and replays).
    fn broadcast(&self, msg: Arc<str>, is_frame: bool) {
        let mut st = self.lock();
        if is_frame {
            st.last_frame = Some(Arc::clone(&msg));
        } else if st.history.len() < MAX_HISTORY {
            st.history.push(Arc::clone(&msg));
        }
        st.viewers.retain(|v| match v.try_send(Arc::clone(&msg)) {
            Ok(()) => true,
            Err(TrySendError::Full(_)) => is_frame,
            Err(TrySendError::Disconnected(_)) => false,
        });
    }
}

/// One server-sent event: `event: NAME` and the JSON on one `data:` line.
fn sse(name: &str, json: &str) -> Arc<str> {
    Arc::from(format!("event: {name}\ndata: {json}\n\n"))
}

fn unix_ms() -> f64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1e3)
}

/// A frame for the encoder.
struct FrameJob {
    index: usize,
    sequence: u64,
    grabbed_unix_ms: f64,
    image: FrameImage,
}

/// The live page: its server and encoder threads. Dropping it stops them.
#[derive(Debug)]
pub struct Live {
    shared: Arc<Shared>,
    addr: SocketAddr,
    requests: Receiver<Request>,
    frames: Option<SyncSender<FrameJob>>,
    threads: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for FrameJob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "FrameJob({} {:?})", self.sequence, self.image)
    }
}

impl Live {
    /// Listen on `addr` ([`parse_addr`]'s form) and start serving. `stop` is the flag the station's
    /// runs are given; `POST /api/stop` sets it (only with a `token`).
    pub fn start(
        addr: &str,
        token: Option<Token>,
        stop: Arc<AtomicBool>,
    ) -> Result<Live, LiveError> {
        let server = tiny_http::Server::http(addr).map_err(|source| LiveError::Bind {
            addr: addr.to_string(),
            source,
        })?;
        let bound = server
            .server_addr()
            .to_ip()
            .ok_or_else(|| LiveError::Bind {
                addr: addr.to_string(),
                source: "not an IP socket".into(),
            })?;
        let (req_tx, req_rx) = mpsc::channel();
        let shared = Arc::new(Shared {
            state: Mutex::new(State::default()),
            token,
            stop,
            requests: Mutex::new(req_tx),
            shutdown: AtomicBool::new(false),
            frames_dropped: AtomicU64::new(0),
        });
        let (frame_tx, frame_rx) = mpsc::sync_channel::<FrameJob>(1);
        let enc_shared = Arc::clone(&shared);
        let encoder = std::thread::Builder::new()
            .name("live-encoder".into())
            .spawn(move || encode_frames(&enc_shared, &frame_rx))
            .map_err(LiveError::Thread)?;
        let srv_shared = Arc::clone(&shared);
        let serving = std::thread::Builder::new()
            .name("live-http".into())
            .spawn(move || server::serve(&server, &srv_shared, bound))
            .map_err(LiveError::Thread)?;
        tracing::info!(addr = %bound, control = shared.token.is_some(), "live page listening");
        Ok(Live {
            shared,
            addr: bound,
            requests: req_rx,
            frames: Some(frame_tx),
            threads: vec![encoder, serving],
        })
    }

    /// The address the page is served on (the port chosen when `:0` was asked for).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The page's URL.
    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// Whether the write endpoints are enabled (an operator token is configured).
    pub fn has_control(&self) -> bool {
        self.shared.token.is_some()
    }

    /// A new run starts: pages clear their view and the run's events start over.
    pub fn run_started(&self, run_dir: &Path) {
        let msg = {
            let mut st = self.shared.lock();
            st.run += 1;
            st.running = true;
            st.report = None;
            st.history.clear();
            st.last_frame = None;
            serde_json::json!({ "run": st.run, "state": "running", "run_dir": run_dir })
        };
        self.shared.broadcast(sse("run", &msg.to_string()), false);
    }

    /// The run ended: `report` is its `report.html` (when written), `error` what ended it early.
    pub fn run_finished(&self, report: Option<PathBuf>, exit_code: u8, error: Option<String>) {
        let msg = {
            let mut st = self.shared.lock();
            st.running = false;
            st.report = report.filter(|p| p.is_file());
            serde_json::json!({
                "run": st.run,
                "state": "done",
                "report": st.report.is_some(),
                "exit_code": exit_code,
                "error": error,
            })
        };
        self.shared.broadcast(sse("run", &msg.to_string()), false);
    }

    /// The sink that renders events for the page (give it to the station, teed with the front
    /// end's own sink: [`Tee`]).
    pub fn sink(&self) -> LiveSink<'_> {
        LiveSink { live: self }
    }

    /// After a run: wait for the operator's `start` (`POST /api/start`) for at most `linger`
    /// (`None`: until `quit` is set, checked every 100 ms). `tick` is called at each check (the
    /// service pings its watchdog there).
    pub fn wait(
        &self,
        linger: Option<Duration>,
        quit: &AtomicBool,
        tick: &mut dyn FnMut(),
    ) -> Waited {
        let start = std::time::Instant::now();
        loop {
            tick();
            if quit.load(Ordering::SeqCst) {
                return Waited::Exit;
            }
            if let Some(l) = linger
                && start.elapsed() >= l
            {
                return Waited::Exit;
            }
            match self.requests.recv_timeout(Duration::from_millis(100)) {
                Ok(Request::Start) => return Waited::Start,
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => return Waited::Exit,
            }
        }
    }

    /// Frames the page skipped because the encoder was busy.
    pub fn frames_dropped(&self) -> u64 {
        self.shared.frames_dropped.load(Ordering::Relaxed)
    }
}

impl Drop for Live {
    fn drop(&mut self) {
        self.shared.shutdown.store(true, Ordering::SeqCst);
        self.frames = None;
        // Viewer threads end when their queue's sender goes.
        self.shared.lock().viewers.clear();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// The page's [`EventSink`]: wants frames, never blocks the station for long (a lock held while
/// queueing a message for each page; frames go to the encoder's one-slot channel or are dropped).
#[derive(Debug)]
pub struct LiveSink<'a> {
    live: &'a Live,
}

impl EventSink for LiveSink<'_> {
    fn event(&mut self, event: &Event) {
        match event {
            Event::Alive => {}
            Event::Frame {
                index,
                sequence,
                grabbed_unix_ms,
                image,
            } => {
                let Some(tx) = &self.live.frames else { return };
                let job = FrameJob {
                    index: *index,
                    sequence: *sequence,
                    grabbed_unix_ms: *grabbed_unix_ms,
                    image: image.clone(),
                };
                if let Err(TrySendError::Full(_)) = tx.try_send(job) {
                    self.live
                        .shared
                        .frames_dropped
                        .fetch_add(1, Ordering::Relaxed);
                }
            }
            other => match serde_json::to_string(other) {
                Ok(json) => self.live.shared.broadcast(sse("station", &json), false),
                Err(e) => tracing::warn!(error = %e, "live page: cannot serialise an event"),
            },
        }
    }

    fn wants_frames(&self) -> bool {
        true
    }
}

/// Two sinks as one: the front end's own and the page's (wants frames when either does).
#[derive(Debug)]
pub struct Tee<'a, A: EventSink + ?Sized, B: EventSink + ?Sized> {
    pub first: &'a mut A,
    pub second: &'a mut B,
}

impl<A: EventSink + ?Sized, B: EventSink + ?Sized> EventSink for Tee<'_, A, B> {
    fn event(&mut self, event: &Event) {
        self.first.event(event);
        self.second.event(event);
    }

    fn wants_frames(&self) -> bool {
        self.first.wants_frames() || self.second.wants_frames()
    }
}

/// The encoder thread: reduce, JPEG-encode and send each frame until the sink's sender goes.
fn encode_frames(shared: &Shared, frames: &Receiver<FrameJob>) {
    while let Ok(job) = frames.recv() {
        match frame_message(&job) {
            Ok(msg) => shared.broadcast(msg, true),
            Err(e) => tracing::warn!(error = %e, "live page: cannot encode a frame"),
        }
    }
}

/// The `event: frame` message of a frame: the reduced frame as base64 JPEG, its full size, the
/// reduction factor and the grab and send times.
fn frame_message(job: &FrameJob) -> Result<Arc<str>, image::ImageError> {
    use base64::Engine as _;
    let img = &job.image.0;
    let k = img.width().div_ceil(FRAME_WIDTH).max(1);
    let small = crate::run::preview::downscale(img, k);
    let mut jpeg = Vec::with_capacity(64 * 1024);
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, JPEG_QUALITY).encode(
        small.as_raw(),
        small.width(),
        small.height(),
        image::ExtendedColorType::L8,
    )?;
    let msg = serde_json::json!({
        "index": job.index,
        "sequence": job.sequence,
        "width": img.width(),
        "height": img.height(),
        "factor": k,
        "grabbed_unix_ms": job.grabbed_unix_ms,
        "sent_unix_ms": unix_ms(),
        "jpeg": base64::engine::general_purpose::STANDARD.encode(&jpeg),
    });
    Ok(sse("frame", &msg.to_string()))
}

/// Write one page's event stream until it goes away: the run so far, then every new message.
fn stream_to(mut out: Box<dyn Write + Send>, shared: &Shared) {
    let (tx, rx) = mpsc::sync_channel::<Arc<str>>(VIEWER_QUEUE);
    let (backlog, hello) = {
        let mut st = shared.lock();
        let mut backlog = st.history.clone();
        backlog.extend(st.last_frame.clone());
        let hello = serde_json::json!({
            "control": shared.token.is_some(),
            "run": st.run,
            "running": st.running,
            "report": st.report.is_some(),
            "now_unix_ms": unix_ms(),
        });
        st.viewers.push(tx);
        (backlog, hello)
    };
    let head = "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream; charset=utf-8\r\n\
                Cache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\n\
                Connection: close\r\n\r\nretry: 1000\n\n";
    let mut write = |s: &str| -> std::io::Result<()> {
        out.write_all(s.as_bytes())?;
        out.flush()
    };
    if write(head).is_err() || write(&sse("hello", &hello.to_string())).is_err() {
        return;
    }
    for msg in backlog {
        if write(&msg).is_err() {
            return;
        }
    }
    loop {
        match rx.recv_timeout(Duration::from_secs(15)) {
            Ok(msg) => {
                if write(&msg).is_err() {
                    return;
                }
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {
                if shared.shutdown.load(Ordering::SeqCst) || write(": keep-alive\n\n").is_err() {
                    return;
                }
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => return,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_default_to_loopback() {
        assert_eq!(parse_addr("8035").ok().as_deref(), Some("127.0.0.1:8035"));
        assert_eq!(parse_addr(":0").ok().as_deref(), Some("127.0.0.1:0"));
        assert_eq!(parse_addr("").ok().as_deref(), Some("127.0.0.1:8035"));
        assert_eq!(parse_addr("0.0.0.0:80").ok().as_deref(), Some("0.0.0.0:80"));
        assert_eq!(parse_addr("[::1]:9").ok().as_deref(), Some("[::1]:9"));
        assert_eq!(
            parse_addr("station.local:8035").ok().as_deref(),
            Some("station.local:8035")
        );
        assert!(parse_addr("localhost").is_err());
        assert!(parse_addr("1.2.3.4:99999").is_err());
    }

    #[test]
    fn tokens_compare_whole() {
        let t = Token::new("s3cret-token");
        assert!(t.matches("s3cret-token"));
        assert!(!t.matches("s3cret-toke"));
        assert!(!t.matches("s3cret-token!"));
        assert!(!t.matches(""));
        assert!(!format!("{t:?}").contains("s3cret"));
    }
}
