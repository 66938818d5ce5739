//! `--http` and `--http-token-file` of `calibrate` and `serve`: open the live page
//! ([`cubecal::live`]), tell it when runs start and end, and wait after a run for the operator's
//! Start (or the linger time, or a signal). The page itself renders the station's events.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use cubecal::live::{Live, Tee, Token, Waited};
use cubecal::station::setup::{self, Prepared, RunRequest};
use cubecal::station::{EventSink, StationConfig};

/// The live page's flags (each a config key of `[http]`).
#[derive(Debug, Clone, clap::Args)]
pub struct HttpArgs {
    /// Serve the live page (frame with detections, coverage, σ, prompts, verdict, report) at ADDR:
    /// PORT, HOST:PORT or IP:PORT (http.listen). A bare port, or --http alone (port 8035), binds
    /// 127.0.0.1: visible on this machine only.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "8035")]
    pub http: Option<String>,
    /// File whose first line is the operator token that enables the page's Start and Stop
    /// (http.token_file). Without it the page is read-only.
    #[arg(long, value_name = "FILE")]
    pub http_token_file: Option<PathBuf>,
}

/// The open page and how long it stays up after a run.
#[derive(Debug)]
pub(super) struct Page {
    pub live: Live,
    linger: Option<Duration>,
}

fn say(line: &str) {
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}

/// Open the page when the config asks for one (`http.listen`); `stop` is the flag the runs get.
pub(super) fn open(cfg: &StationConfig, stop: Arc<AtomicBool>) -> anyhow::Result<Option<Page>> {
    let Some(listen) = &cfg.http.listen else {
        return Ok(None);
    };
    let addr = cubecal::live::parse_addr(listen)?;
    let token = (cfg.http.token_file.as_deref())
        .map(Token::from_file)
        .transpose()?;
    let live = Live::start(&addr, token, stop)?;
    say(&format!(
        "live page: {} ({})",
        live.url(),
        if live.has_control() {
            "Start and Stop need the operator token"
        } else {
            "read-only: no operator token configured"
        }
    ));
    Ok(Some(Page {
        live,
        linger: cfg.http.linger_s.map(Duration::from_secs),
    }))
}

impl Page {
    /// A run ended with `outcome`: the page shows how, and the report when there is one.
    pub fn finished(&self, run_dir: &Path, outcome: &anyhow::Result<u8>) {
        let (code, error) = match outcome {
            Ok(code) => (*code, None),
            Err(e) => (
                super::exit_code_for(e),
                Some(
                    e.chain()
                        .map(|c| c.to_string())
                        .collect::<Vec<_>>()
                        .join(": "),
                ),
            ),
        };
        self.live
            .run_finished(Some(run_dir.join("report.html")), code, error);
    }

    /// After a run: wait for the operator's Start, the linger time or `quit` (a signal); `tick` is
    /// called every 100 ms meanwhile.
    pub fn wait(&self, quit: &AtomicBool, tick: &mut dyn FnMut()) -> Waited {
        let until = match self.linger {
            Some(s) if s.is_zero() => None,
            Some(s) => Some(format!("for {} s", s.as_secs())),
            None => Some("until Ctrl-C / SIGTERM".to_string()),
        };
        if let Some(until) = until {
            let again = if self.live.has_control() {
                " (Start runs again)"
            } else {
                ""
            };
            say(&format!(
                "the live page stays up at {} {until}{again}",
                self.live.url()
            ));
        }
        self.live.wait(self.linger, quit, tick)
    }

    /// The runs of `calibrate --http` and `serve --http`: `prepared` first, then, each time the
    /// operator presses Start after a run, another in a new run directory (`numbered`), until the
    /// wait after a run ends ([`Page::wait`]; `tick(state)` meanwhile). `run_once` runs one with the
    /// page open; `stop` is cleared between runs. Returns the last run's outcome.
    pub fn runs<S>(
        &self,
        prepared: Prepared,
        mut request: RunRequest,
        stop: &AtomicBool,
        quit: &AtomicBool,
        state: &mut S,
        mut run_once: impl FnMut(&mut S, Prepared, &Live) -> anyhow::Result<u8>,
        mut tick: impl FnMut(&mut S),
    ) -> anyhow::Result<u8> {
        let first = prepared.run_dir.clone();
        let mut next = Some(prepared);
        for n in 2.. {
            let prepared = match next.take() {
                Some(p) => p,
                None => setup::prepare(&request)?,
            };
            let run_dir = prepared.run_dir.clone();
            self.live.run_started(&run_dir);
            let outcome = run_once(state, prepared, &self.live);
            self.finished(&run_dir, &outcome);
            if self.wait(quit, &mut || tick(state)) == Waited::Exit {
                return outcome;
            }
            if let Err(e) = &outcome {
                tracing::warn!(error = %e, "run ended with an error; starting the next as asked");
            }
            stop.store(false, std::sync::atomic::Ordering::SeqCst);
            request.out = Some(numbered(&first, n));
        }
        Ok(cubecal::exit::INTERNAL)
    }
}

/// `f` with `sink`, or with `sink` and the live page's sink both when the page is open.
pub(super) fn with_page<R>(
    live: Option<&Live>,
    sink: &mut dyn EventSink,
    f: impl FnOnce(&mut dyn EventSink) -> R,
) -> R {
    match live {
        Some(live) => {
            let mut page = live.sink();
            f(&mut Tee {
                first: sink,
                second: &mut page,
            })
        }
        None => f(sink),
    }
}

/// The run directory of the page's `n`-th run (n ≥ 2) when the first was `first`: `first-n`.
fn numbered(first: &Path, n: usize) -> PathBuf {
    let mut name = first.as_os_str().to_os_string();
    name.push(format!("-{n}"));
    PathBuf::from(name)
}
