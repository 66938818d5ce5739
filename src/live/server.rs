//! The live page's HTTP routes (see the module docs of [`super`]).

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use tiny_http::{Header, Method, Request, Response, Server};

use super::{Request as Ask, Shared};

const PAGE: &str = include_str!("page.html");
const SCRIPT: &str = include_str!("page.js");
/// The page loads nothing from elsewhere and runs only its own script.
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'unsafe-inline'; \
                   img-src 'self' data:; connect-src 'self'; frame-src 'self'; \
                   base-uri 'none'; form-action 'none'; frame-ancestors 'self'";

/// Accept requests until the [`Shared::shutdown`] flag is set.
pub(super) fn serve(server: &Server, shared: &Arc<Shared>, bound: SocketAddr) {
    while !shared.shutdown.load(Ordering::SeqCst) {
        match server.recv_timeout(Duration::from_millis(100)) {
            Ok(Some(request)) => handle(request, shared, bound),
            Ok(None) => {}
            Err(e) => {
                tracing::warn!(error = %e, "live page: accepting a request failed");
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
}

fn header(name: &str, value: &str) -> Option<Header> {
    Header::from_bytes(name.as_bytes(), value.as_bytes()).ok()
}

fn respond<R: std::io::Read>(request: Request, mut response: Response<R>) {
    for (n, v) in [
        ("X-Content-Type-Options", "nosniff"),
        ("Cache-Control", "no-store"),
        ("Referrer-Policy", "no-referrer"),
    ] {
        if let Some(h) = header(n, v) {
            response.add_header(h);
        }
    }
    if let Err(e) = request.respond(response) {
        tracing::debug!(error = %e, "live page: the client went away");
    }
}

fn text(request: Request, status: u16, body: &str) {
    let mut r = Response::from_string(body).with_status_code(status);
    if let Some(h) = header("Content-Type", "text/plain; charset=utf-8") {
        r.add_header(h);
    }
    respond(request, r);
}

fn json(request: Request, status: u16, body: &serde_json::Value) {
    let mut r = Response::from_string(body.to_string()).with_status_code(status);
    if let Some(h) = header("Content-Type", "application/json") {
        r.add_header(h);
    }
    respond(request, r);
}

fn header_value<'r>(request: &'r Request, name: &str) -> Option<&'r str> {
    request
        .headers()
        .iter()
        .find(|h| h.field.as_str().as_str().eq_ignore_ascii_case(name))
        .map(|h| h.value.as_str())
}

/// On a loopback address, requests must name a loopback host (no DNS rebinding onto the page).
fn host_allowed(request: &Request, bound: SocketAddr) -> bool {
    if !bound.ip().is_loopback() {
        return true;
    }
    let Some(host) = header_value(request, "Host") else {
        return false;
    };
    let name = match host.rsplit_once(':') {
        Some((h, port)) if port.chars().all(|c| c.is_ascii_digit()) => h,
        _ => host,
    };
    let name = name.trim_start_matches('[').trim_end_matches(']');
    name.eq_ignore_ascii_case("localhost")
        || name
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

fn handle(request: Request, shared: &Arc<Shared>, bound: SocketAddr) {
    if !host_allowed(&request, bound) {
        return text(
            request,
            421,
            "this page answers only to localhost (it is bound to a loopback address)\n",
        );
    }
    let path = request.url().split('?').next().unwrap_or("").to_string();
    let method = request.method().clone();
    match (&method, path.as_str()) {
        (Method::Get, "/") => {
            let mut r = Response::from_string(PAGE);
            for (n, v) in [
                ("Content-Type", "text/html; charset=utf-8"),
                ("Content-Security-Policy", CSP),
            ] {
                if let Some(h) = header(n, v) {
                    r.add_header(h);
                }
            }
            respond(request, r);
        }
        (Method::Get, "/page.js") => {
            let mut r = Response::from_string(SCRIPT);
            if let Some(h) = header("Content-Type", "text/javascript; charset=utf-8") {
                r.add_header(h);
            }
            respond(request, r);
        }
        (Method::Get, "/events") => {
            if shared.lock().viewers.len() >= super::MAX_VIEWERS {
                return text(request, 503, "too many pages open\n");
            }
            let out = request.into_writer();
            let shared = Arc::clone(shared);
            let spawned = std::thread::Builder::new()
                .name("live-viewer".into())
                .spawn(move || super::stream_to(out, &shared));
            if let Err(e) = spawned {
                tracing::warn!(error = %e, "live page: cannot start a viewer thread");
            }
        }
        (Method::Get, "/report") => {
            let report = shared.lock().report.clone();
            match report.map(std::fs::read) {
                Some(Ok(bytes)) => {
                    let mut r = Response::from_data(bytes);
                    if let Some(h) = header("Content-Type", "text/html; charset=utf-8") {
                        r.add_header(h);
                    }
                    respond(request, r);
                }
                Some(Err(e)) => text(request, 500, &format!("cannot read the report: {e}\n")),
                None => text(request, 404, "no report yet: the run has not finished\n"),
            }
        }
        (Method::Get, "/api/state") => {
            let body = {
                let st = shared.lock();
                serde_json::json!({
                    "control": shared.token.is_some(),
                    "run": st.run,
                    "running": st.running,
                    "report": st.report.is_some(),
                    "viewers": st.viewers.len(),
                    "frames_dropped": shared.frames_dropped.load(Ordering::Relaxed),
                })
            };
            json(request, 200, &body);
        }
        (Method::Post, "/api/stop" | "/api/start") => {
            let Some(token) = &shared.token else {
                return text(
                    request,
                    403,
                    "read-only: no operator token is configured (http.token_file)\n",
                );
            };
            let presented = header_value(&request, "Authorization")
                .and_then(|v| v.strip_prefix("Bearer "))
                .unwrap_or("");
            if !token.matches(presented.trim()) {
                tracing::warn!(
                    path,
                    remote = ?request.remote_addr(),
                    "live page: write refused (missing or wrong operator token)"
                );
                return text(request, 401, "operator token missing or wrong\n");
            }
            let running = shared.lock().running;
            if path == "/api/stop" {
                if !running {
                    return text(request, 409, "no run in progress\n");
                }
                tracing::info!("live page: the operator stopped the run");
                shared.stop.store(true, Ordering::SeqCst);
                json(request, 202, &serde_json::json!({ "stopping": true }));
            } else {
                if running {
                    return text(request, 409, "a run is in progress\n");
                }
                let sent = shared
                    .requests
                    .lock()
                    .map(|tx| tx.send(Ask::Start).is_ok())
                    .unwrap_or(false);
                if sent {
                    tracing::info!("live page: the operator asked for a new run");
                    json(request, 202, &serde_json::json!({ "starting": true }));
                } else {
                    text(request, 503, "the station no longer takes runs\n");
                }
            }
        }
        (_, "/" | "/page.js" | "/events" | "/report" | "/api/state") => {
            text(request, 405, "method not allowed\n")
        }
        (_, "/api/stop" | "/api/start") => text(request, 405, "use POST\n"),
        _ => text(request, 404, "not found\n"),
    }
}
