//! The read-only QC HTTP server: the operator's page, the JSON API, server-sent events and the
//! Prometheus metrics, all read from a [`QcHub`].
//!
//! It runs on its own thread with a current-thread tokio runtime, away from the per-pulse
//! threads. Every route is `GET` (and `HEAD`); other methods get 405, unknown paths 404. Nothing
//! served changes state, runs anything or reads a file: the page's three files are compiled in.
//!
//! | route | content |
//! |---|---|
//! | `/` | the operator's page (`text/html`) |
//! | `/app.js`, `/style.css` | its script and style sheet |
//! | `/metrics` | [`prometheus::render`], `text/plain; version=0.0.4` |
//! | `/api/status` | the latest [`QcSnapshot`](super::QcSnapshot) as JSON |
//! | `/api/history` | the chart history (JSON array of [`HistoryPoint`](super::HistoryPoint), oldest first) |
//! | `/api/waveform` | the last [`WaveformView`](super::WaveformView) as JSON, 204 before any |
//! | `/api/events` | server-sent events: `status` with the snapshot JSON on connect and on every publish |

use std::convert::Infallible;
use std::future::IntoFuture as _;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::thread::JoinHandle;
use std::time::Duration;

use axum::Router;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use tokio::sync::{mpsc, watch};

use super::{QcHub, prometheus};

/// How long [`QcServer::shutdown`] lets open requests finish before closing them, seconds.
pub const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

/// Interval of the keep-alive comment on `/api/events` when nothing is published.
pub const SSE_KEEP_ALIVE: Duration = Duration::from_secs(10);

const INDEX_HTML: &str = include_str!("assets/index.html");
const APP_JS: &str = include_str!("assets/app.js");
const STYLE_CSS: &str = include_str!("assets/style.css");

/// The page may load only what this server serves: no external resources.
const PAGE_CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
                        connect-src 'self'; img-src 'self' data:; base-uri 'none'; \
                        form-action 'none'; frame-ancestors 'none'";

/// Why the server did not start.
#[derive(Debug, thiserror::Error)]
pub enum QcServerError {
    /// The address could not be bound (in use, not local, no permission).
    #[error("QC server: cannot bind {addr}: {source}")]
    Bind {
        /// The address asked for.
        addr: SocketAddr,
        /// The system's reason.
        source: io::Error,
    },
    /// The runtime or its thread could not be made.
    #[error("QC server on {addr}: cannot start: {source}")]
    Start {
        /// The address bound.
        addr: SocketAddr,
        /// The system's reason.
        source: io::Error,
    },
}

/// A running QC server. Stops (gracefully) on [`shutdown`](QcServer::shutdown) or drop.
pub struct QcServer {
    local_addr: SocketAddr,
    stop: watch::Sender<bool>,
    thread: Option<JoinHandle<()>>,
}

impl QcServer {
    /// The address it listens on (with the port chosen when asked for port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// Stops accepting, ends the event streams, lets open requests finish (at most
    /// [`SHUTDOWN_GRACE`]) and waits for the server's thread.
    pub fn shutdown(mut self) {
        self.stop_and_join();
    }

    fn stop_and_join(&mut self) {
        self.stop.send_replace(true);
        if let Some(t) = self.thread.take()
            && t.join().is_err()
        {
            tracing::error!("QC server thread panicked");
        }
    }
}

impl Drop for QcServer {
    fn drop(&mut self) {
        self.stop_and_join();
    }
}

impl std::fmt::Debug for QcServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("QcServer")
            .field("local_addr", &self.local_addr)
            .finish_non_exhaustive()
    }
}

/// Binds `addr` now (so a bind error comes back here, naming the address) and serves `hub` on
/// a thread of its own (`qc-server`) until the returned [`QcServer`] is shut down or dropped.
///
/// The caller chooses the address; the daemon binds `127.0.0.1` unless its configuration
/// names another address explicitly.
pub fn spawn(addr: SocketAddr, hub: Arc<QcHub>) -> Result<QcServer, QcServerError> {
    let std_listener =
        std::net::TcpListener::bind(addr).map_err(|source| QcServerError::Bind { addr, source })?;
    let local_addr = std_listener
        .local_addr()
        .map_err(|source| QcServerError::Bind { addr, source })?;
    let start = |source| QcServerError::Start {
        addr: local_addr,
        source,
    };
    std_listener.set_nonblocking(true).map_err(start)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_io()
        .enable_time()
        .thread_name("qc-server")
        .build()
        .map_err(start)?;
    let listener = {
        let _guard = runtime.enter();
        tokio::net::TcpListener::from_std(std_listener).map_err(start)?
    };
    let (stop, stop_rx) = watch::channel(false);
    let app = router(AppState {
        hub,
        stop: stop_rx.clone(),
    });
    let thread = std::thread::Builder::new()
        .name("qc-server".into())
        .spawn(move || {
            runtime.block_on(serve(listener, app, stop_rx));
        })
        .map_err(start)?;
    tracing::info!(addr = %local_addr, "QC server listening");
    Ok(QcServer {
        local_addr,
        stop,
        thread: Some(thread),
    })
}

/// Serves until `stop` turns true (or its sender goes), then shuts down gracefully, cutting
/// what is still open after [`SHUTDOWN_GRACE`].
async fn serve(listener: tokio::net::TcpListener, app: Router, stop: watch::Receiver<bool>) {
    let mut signal = stop.clone();
    let mut deadline = stop;
    let server = axum::serve(listener, app)
        .with_graceful_shutdown(async move {
            let _ = signal.wait_for(|s| *s).await;
        })
        .into_future();
    let cut = async move {
        let _ = deadline.wait_for(|s| *s).await;
        tokio::time::sleep(SHUTDOWN_GRACE).await;
    };
    tokio::select! {
        r = server => {
            if let Err(e) = r {
                tracing::error!(error = %e, "QC server stopped on an error");
            }
        }
        () = cut => tracing::warn!("QC server: connections still open after the grace period, closed"),
    }
}

#[derive(Clone)]
struct AppState {
    hub: Arc<QcHub>,
    stop: watch::Receiver<bool>,
}

fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/app.js", get(app_js))
        .route("/style.css", get(style_css))
        .route("/metrics", get(prometheus))
        .route("/api/status", get(status))
        .route("/api/history", get(history))
        .route("/api/waveform", get(waveform))
        .route("/api/events", get(events))
        .fallback(not_found)
        .with_state(state)
}

/// A response with its content type, no caching and no content sniffing.
fn reply(content_type: &'static str, body: impl Into<axum::body::Body>) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "no-store"),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        ],
        body.into(),
    )
        .into_response()
}

fn json<T: serde::Serialize + ?Sized>(value: &T) -> Response {
    match serde_json::to_vec(value) {
        Ok(bytes) => reply("application/json", bytes),
        Err(e) => (
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("cannot serialise: {e}"),
        )
            .into_response(),
    }
}

async fn index() -> Response {
    let mut r = reply("text/html; charset=utf-8", INDEX_HTML);
    r.headers_mut().insert(
        header::CONTENT_SECURITY_POLICY,
        header::HeaderValue::from_static(PAGE_CSP),
    );
    r.headers_mut().insert(
        header::REFERRER_POLICY,
        header::HeaderValue::from_static("no-referrer"),
    );
    r
}

async fn app_js() -> Response {
    reply("text/javascript; charset=utf-8", APP_JS)
}

async fn style_css() -> Response {
    reply("text/css; charset=utf-8", STYLE_CSS)
}

async fn prometheus(State(st): State<AppState>) -> Response {
    reply(
        prometheus::CONTENT_TYPE,
        prometheus::render(&st.hub.snapshot()),
    )
}

async fn status(State(st): State<AppState>) -> Response {
    json(&*st.hub.snapshot())
}

async fn history(State(st): State<AppState>) -> Response {
    json(&st.hub.history())
}

async fn waveform(State(st): State<AppState>) -> Response {
    match st.hub.waveform() {
        Some(w) => json(&*w),
        None => (
            StatusCode::NO_CONTENT,
            [(header::CACHE_CONTROL, "no-store")],
        )
            .into_response(),
    }
}

async fn not_found() -> Response {
    let mut r = reply("text/plain; charset=utf-8", "not found\n");
    *r.status_mut() = StatusCode::NOT_FOUND;
    r
}

/// The snapshot as a `status` event, its sequence number as the event id.
fn status_event(hub: &QcHub) -> Event {
    let snap = hub.snapshot();
    // Compact JSON has no line feed, so it is one `data:` line.
    let data = serde_json::to_string(&*snap).unwrap_or_else(|_| "null".into());
    Event::default()
        .event("status")
        .id(snap.sequence.to_string())
        .data(data)
}

/// `/api/events`: a task per client forwards the hub's updates; it ends when the client goes
/// or the server stops, which ends the stream.
async fn events(State(st): State<AppState>) -> impl IntoResponse {
    let (tx, rx) = mpsc::channel(4);
    let mut updates = st.hub.subscribe();
    let mut stop = st.stop.clone();
    let hub = st.hub.clone();
    tokio::spawn(async move {
        // The current snapshot first, so a client has something at once.
        updates.borrow_and_update();
        if tx.send(status_event(&hub)).await.is_err() {
            return;
        }
        loop {
            tokio::select! {
                r = updates.changed() => if r.is_err() { break },
                _ = stop.wait_for(|s| *s) => break,
                () = tx.closed() => break,
            }
            if tx.send(status_event(&hub)).await.is_err() {
                break;
            }
        }
    });
    let mut r = Sse::new(EventStream(rx))
        .keep_alive(KeepAlive::new().interval(SSE_KEEP_ALIVE).text("keep-alive"))
        .into_response();
    r.headers_mut().insert(
        header::X_CONTENT_TYPE_OPTIONS,
        header::HeaderValue::from_static("nosniff"),
    );
    r
}

/// The events of one client, as a stream for [`Sse`].
struct EventStream(mpsc::Receiver<Event>);

impl futures_core::Stream for EventStream {
    type Item = Result<Event, Infallible>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.0.poll_recv(cx).map(|e| e.map(Ok))
    }
}

#[cfg(test)]
mod tests {
    use std::io::{BufRead, BufReader, Read, Write};
    use std::net::TcpStream;

    use super::*;
    use crate::qc::prometheus::tests::filled_snapshot;
    use crate::qc::snapshot::*;

    /// A response as the test client read it.
    struct Reply {
        status: u16,
        headers: Vec<(String, String)>,
        body: Vec<u8>,
    }

    impl Reply {
        fn header(&self, name: &str) -> Option<&str> {
            self.headers
                .iter()
                .find(|(n, _)| n.eq_ignore_ascii_case(name))
                .map(|(_, v)| v.as_str())
        }

        fn text(&self) -> &str {
            std::str::from_utf8(&self.body).expect("body not UTF-8")
        }

        fn json(&self) -> serde_json::Value {
            serde_json::from_slice(&self.body).expect("body not JSON")
        }
    }

    fn connect(addr: SocketAddr) -> TcpStream {
        let s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        s
    }

    /// Reads the status line and headers.
    fn read_head(r: &mut impl BufRead) -> (u16, Vec<(String, String)>) {
        let mut line = String::new();
        r.read_line(&mut line).unwrap();
        let mut parts = line.trim_end().splitn(3, ' ');
        assert_eq!(parts.next(), Some("HTTP/1.1"), "status line {line:?}");
        let status = parts.next().unwrap().parse().unwrap();
        let mut headers = Vec::new();
        loop {
            line.clear();
            r.read_line(&mut line).unwrap();
            let l = line.trim_end_matches(['\r', '\n']);
            if l.is_empty() {
                break;
            }
            let (n, v) = l.split_once(':').expect("header without :");
            headers.push((n.trim().to_string(), v.trim().to_string()));
        }
        (status, headers)
    }

    /// Reads one chunk of a chunked body; `None` at the last (empty) chunk.
    fn read_chunk(r: &mut impl BufRead) -> Option<Vec<u8>> {
        let mut line = String::new();
        r.read_line(&mut line).unwrap();
        let size = usize::from_str_radix(line.trim_end().split(';').next().unwrap(), 16)
            .unwrap_or_else(|_| panic!("bad chunk size {line:?}"));
        let mut data = vec![0; size];
        r.read_exact(&mut data).unwrap();
        let mut crlf = [0; 2];
        r.read_exact(&mut crlf).unwrap();
        assert_eq!(&crlf, b"\r\n");
        (size > 0).then_some(data)
    }

    /// One HTTP/1.1 request on a fresh connection (closed after it).
    fn request(addr: SocketAddr, method: &str, path: &str) -> Reply {
        let mut s = connect(addr);
        write!(
            s,
            "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut r = BufReader::new(s);
        let (status, headers) = read_head(&mut r);
        let find = |n: &str| {
            headers
                .iter()
                .find(|(h, _)| h.eq_ignore_ascii_case(n))
                .map(|(_, v)| v.clone())
        };
        let mut body = Vec::new();
        if method == "HEAD" || status == 204 || status == 304 {
        } else if let Some(len) = find("content-length") {
            body.resize(len.parse().unwrap(), 0);
            r.read_exact(&mut body).unwrap();
        } else if find("transfer-encoding").is_some_and(|t| t.contains("chunked")) {
            while let Some(c) = read_chunk(&mut r) {
                body.extend(c);
            }
        } else {
            r.read_to_end(&mut body).unwrap();
        }
        Reply {
            status,
            headers,
            body,
        }
    }

    fn get(addr: SocketAddr, path: &str) -> Reply {
        request(addr, "GET", path)
    }

    fn point(t: f64) -> HistoryPoint {
        HistoryPoint {
            t,
            rate_in_hz: 100_000.0,
            rate_processed_hz: 99_000.0,
            rate_dropped_hz: 1000.0,
            queue_fill: 0.25,
            e2e_p50_us: 300.0,
            e2e_p99_us: 900.0,
            stage_p99_us: vec![10.0, 200.0],
        }
    }

    fn start() -> (QcServer, Arc<QcHub>) {
        let hub = Arc::new(QcHub::default());
        let server = spawn("127.0.0.1:0".parse().unwrap(), hub.clone()).unwrap();
        assert!(server.local_addr().ip().is_loopback());
        assert_ne!(server.local_addr().port(), 0);
        (server, hub)
    }

    #[test]
    fn every_route_serves_its_content() {
        let (server, hub) = start();
        let addr = server.local_addr();

        // Before anything is published.
        let w = get(addr, "/api/waveform");
        assert_eq!(w.status, 204);
        assert!(w.body.is_empty());
        let h = get(addr, "/api/history");
        assert_eq!(h.status, 200);
        assert_eq!(h.json(), serde_json::json!([]));

        hub.publish(filled_snapshot(1), point(1.0));
        hub.publish(filled_snapshot(2), point(2.0));
        hub.set_waveform(WaveformView {
            pulse_id: 77,
            gps_time: 345_600.25,
            sample_ns: 1.0,
            start_ns: 1200.0,
            steps: vec![
                WaveformStep {
                    name: "raw".into(),
                    values: vec![0.0, 0.5, 1.0, 0.5, 0.0],
                },
                WaveformStep {
                    name: "denoise".into(),
                    values: vec![0.0, 0.4, 0.9, 0.4, 0.0],
                },
            ],
            returns: vec![FittedView {
                time_ns: 1202.0,
                amplitude: 0.9,
                sigma_ns: 1.1,
            }],
        });

        let page = get(addr, "/");
        assert_eq!(page.status, 200);
        assert!(
            page.header("content-type")
                .unwrap()
                .starts_with("text/html")
        );
        assert!(page.header("content-security-policy").is_some());
        let html = page.text();
        for id in [
            "rate-in",
            "rate-processed",
            "pulses-processed",
            "dropped-total",
            "uptime",
            "snapshot-seq",
            "alerts",
            "coverage",
            "waveform",
        ] {
            assert!(html.contains(&format!("id=\"{id}\"")), "page lacks #{id}");
        }
        assert!(html.contains("src=\"app.js\"") || html.contains("src=\"/app.js\""));
        // Nothing external.
        assert!(!html.contains("http://") && !html.contains("https://"));

        let js = get(addr, "/app.js");
        assert_eq!(js.status, 200);
        assert!(
            js.header("content-type")
                .unwrap()
                .starts_with("text/javascript")
        );
        assert!(js.text().contains("/api/status"));
        assert!(js.text().contains("dataset.ready"));
        assert!(!js.text().contains("http://") && !js.text().contains("https://"));
        let css = get(addr, "/style.css");
        assert_eq!(css.status, 200);
        assert!(css.header("content-type").unwrap().starts_with("text/css"));
        assert!(!css.text().contains("url(http"));

        let m = get(addr, "/metrics");
        assert_eq!(m.status, 200);
        let ct = m.header("content-type").unwrap();
        assert!(
            ct.starts_with("text/plain") && ct.contains("version=0.0.4"),
            "{ct}"
        );
        assert!(m.text().contains("fwlidar_snapshot_sequence 2\n"));
        crate::qc::prometheus::tests::check_exposition(m.text());
        assert!(m.text().contains("fwlidar_pulses_processed_total 12345\n"));

        let s = get(addr, "/api/status");
        assert_eq!(s.status, 200);
        assert_eq!(s.header("content-type"), Some("application/json"));
        let s = s.json();
        assert_eq!(s["sequence"], 2);
        assert_eq!(s["pulses"]["pulses_processed"], 12_345);
        assert_eq!(s["nav"][0]["port"], 2);
        assert_eq!(s["alerts"][0]["kind"], "input_down");
        // The +Inf bound is serialised as null.
        assert!(s["end_to_end"]["buckets"][3][0].is_null());

        let h = get(addr, "/api/history");
        assert_eq!(h.status, 200);
        assert_eq!(h.header("content-type"), Some("application/json"));
        let h = h.json();
        assert_eq!(h.as_array().unwrap().len(), 2);
        assert_eq!(h[1]["t"], 2.0);
        assert_eq!(h[1]["stage_p99_us"][1], 200.0);

        let w = get(addr, "/api/waveform");
        assert_eq!(w.status, 200);
        assert_eq!(w.header("content-type"), Some("application/json"));
        let w = w.json();
        assert_eq!(w["pulse_id"], 77);
        assert_eq!(w["steps"][1]["name"], "denoise");
        assert_eq!(w["returns"][0]["time_ns"], 1202.0);

        // HEAD is a GET without the body.
        let head = request(addr, "HEAD", "/api/status");
        assert_eq!(head.status, 200);

        server.shutdown();
    }

    #[test]
    fn read_only_other_methods_and_paths_are_refused() {
        let (server, hub) = start();
        let addr = server.local_addr();
        hub.publish(filled_snapshot(5), point(5.0));
        for path in ["/", "/api/status", "/metrics", "/api/events"] {
            for method in ["POST", "PUT", "DELETE", "PATCH"] {
                let r = request(addr, method, path);
                assert_eq!(r.status, 405, "{method} {path}");
            }
        }
        for path in [
            "/../Cargo.toml",
            "/etc/passwd",
            "/%2e%2e/Cargo.toml",
            "/src/qc/assets/app.js",
            "/api/",
            "/api/status/x",
            "/index.html",
        ] {
            let r = get(addr, path);
            assert_eq!(r.status, 404, "{path}");
            assert!(!r.text().contains("[package]"));
        }
        assert_eq!(request(addr, "POST", "/nowhere").status, 404);
        // Nothing changed.
        assert_eq!(hub.snapshot().sequence, 5);
        assert_eq!(get(addr, "/api/status").json()["sequence"], 5);
        drop(server);
    }

    /// Reads events from a chunked `text/event-stream` body until one of type `status`.
    fn next_status(r: &mut impl BufRead, pending: &mut String) -> serde_json::Value {
        loop {
            while let Some(end) = pending.find("\n\n") {
                let block: String = pending.drain(..end + 2).collect();
                let mut kind = None;
                let mut data = String::new();
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event:") {
                        kind = Some(v.trim().to_string());
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push_str(v.trim_start());
                    }
                }
                if kind.as_deref() == Some("status") {
                    return serde_json::from_str(&data).expect("status data not JSON");
                }
            }
            let chunk = read_chunk(r).expect("event stream ended");
            pending.push_str(std::str::from_utf8(&chunk).unwrap());
        }
    }

    #[test]
    fn events_deliver_each_publish() {
        let (server, hub) = start();
        let addr = server.local_addr();
        hub.publish(filled_snapshot(0), point(0.0));

        let mut s = connect(addr);
        write!(s, "GET /api/events HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
        let mut r = BufReader::new(s);
        let (status, headers) = read_head(&mut r);
        assert_eq!(status, 200);
        let ct = headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case("content-type"))
            .map(|(_, v)| v.as_str());
        assert_eq!(ct, Some("text/event-stream"));
        let mut pending = String::new();

        // The current snapshot on connect.
        let first = next_status(&mut r, &mut pending);
        assert_eq!(first["sequence"], 0);

        hub.publish(filled_snapshot(1), point(1.0));
        let a = next_status(&mut r, &mut pending);
        hub.publish(filled_snapshot(2), point(2.0));
        let b = next_status(&mut r, &mut pending);
        let (a, b) = (
            a["sequence"].as_u64().unwrap(),
            b["sequence"].as_u64().unwrap(),
        );
        assert_eq!((a, b), (1, 2));
        assert!(!pending.contains("\n\n"), "an event without a publish");

        // Shutdown ends the stream (the server does not wait for the grace period).
        let t = std::time::Instant::now();
        server.shutdown();
        assert!(
            t.elapsed() < SHUTDOWN_GRACE,
            "shutdown waited {:?}",
            t.elapsed()
        );
    }

    #[test]
    fn bind_error_names_the_address() {
        let (server, hub) = start();
        let addr = server.local_addr();
        let err = spawn(addr, hub).unwrap_err();
        assert!(matches!(err, QcServerError::Bind { addr: a, .. } if a == addr));
        assert!(err.to_string().contains(&addr.to_string()), "{err}");
        drop(server);
        // Once dropped, the port is free again.
        let again = spawn(addr, Arc::new(QcHub::default())).expect("rebind after drop");
        again.shutdown();
    }
}

/// A demonstration server for looking at the page by hand or from a browser test:
/// `FWLIDAR_QC_DEMO_ADDR=127.0.0.1:8787 FWLIDAR_QC_DEMO_SECS=600 cargo test --release --lib
/// qc::server::demo -- --ignored --nocapture`, then open the address. It publishes a made-up
/// snapshot a second (rates, drops, tiles growing, a navigation port going stale, alerts, a
/// waveform).
#[cfg(test)]
mod demo {
    use std::collections::BTreeMap;

    use super::*;
    use crate::qc::snapshot::*;

    fn latency(name: &str, scale_us: f64, count: u64) -> StageLatency {
        let bounds = [1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1];
        let mut buckets: Vec<(f64, u64)> = bounds
            .iter()
            .map(|&b| {
                let frac = 1.0 - (-(b * 1e6) / scale_us).exp();
                (b, (count as f64 * frac) as u64)
            })
            .collect();
        buckets.push((f64::INFINITY, count));
        StageLatency {
            name: name.into(),
            count,
            p50_us: scale_us * 0.69,
            p99_us: scale_us * 4.6,
            p999_us: scale_us * 6.9,
            max_us: scale_us * 12.0,
            sum_s: count as f64 * scale_us * 1e-6,
            buckets,
        }
    }

    // A test fixture: one snapshot written out field by field, every part of the page fed.
    #[allow(clippy::too_many_lines)]
    fn demo_snapshot(k: u64, start: f64) -> (QcSnapshot, HistoryPoint) {
        let t = start + k as f64;
        let kf = k as f64;
        let rate_in = 100_000.0 + 5_000.0 * (kf / 20.0).sin();
        let dropped_rate = if (k / 30) % 2 == 1 { 800.0 } else { 0.0 };
        let processed = rate_in - dropped_rate;
        let pulses_in = (kf * 100_000.0) as u64;
        let dropped = (kf * 200.0) as u64;
        let mut drops = BTreeMap::new();
        drops.insert("input_queue_full".to_string(), dropped * 3 / 4);
        drops.insert("decompose.no_return".to_string(), dropped - dropped * 3 / 4);
        let stage_names = ["denoise", "deconvolve", "decompose"];
        let stage_scale = [3.0, 60.0, 25.0];
        let stages: Vec<_> = stage_names
            .iter()
            .zip(stage_scale)
            .map(|(n, s)| latency(n, s * (1.0 + 0.2 * (kf / 7.0).sin()), pulses_in))
            .collect();
        let mut cells = Vec::new();
        let n = 4 + k / 5;
        for i in 0..n {
            let (tx, ty) = (100 + (i % 12) as i64, -20 + (i / 12) as i64);
            let closed = i + 3 < n;
            let pulses = 20_000 + (i * 7919 % 30_000);
            cells.push(TileCell {
                tx,
                ty,
                state: if closed { "closed" } else { "open" }.into(),
                pulses,
                density_per_m2: pulses as f64 / 62_500.0,
                canopy_height_m: Some(8.0 + (i * 37 % 23) as f64),
            });
        }
        let nav_age = |period: u64| (k % period) as f64 * 0.9 + 0.05;
        let mut alerts = vec![];
        if dropped_rate > 0.0 {
            alerts.push(Alert {
                kind: "overrun".into(),
                severity: "critical".into(),
                message: format!("dropping {dropped_rate} pulses/s: processing cannot keep up"),
            });
        }
        if nav_age(12) > 5.0 {
            alerts.push(Alert {
                kind: "navigation_gap".into(),
                severity: "warning".into(),
                message: "no navigation on port 2 for more than 5 s".into(),
            });
        }
        let queue_len = if dropped_rate > 0.0 {
            1020
        } else {
            40 + k % 50
        };
        let snap = QcSnapshot {
            time_unix_s: t,
            uptime_s: kf + 3600.0,
            version: env!("CARGO_PKG_VERSION").into(),
            survey: "Demo block <A> & \"north\"".into(),
            sequence: k,
            inputs: vec![
                InputStatus {
                    name: "frames".into(),
                    detail: "udp 127.0.0.1:5000".into(),
                    up: true,
                    last_data_age_s: Some(0.001),
                    bytes: pulses_in * 1200,
                    connects: 1,
                    failed_attempts: 0,
                    last_error: None,
                },
                InputStatus {
                    name: "serial:1".into(),
                    detail: "/dev/ttyUSB0 @ 115200".into(),
                    up: true,
                    last_data_age_s: Some(0.02),
                    bytes: k * 20_000,
                    connects: 1,
                    failed_attempts: 0,
                    last_error: None,
                },
                InputStatus {
                    name: "serial:2".into(),
                    detail: "/dev/gnss0 @ 230400".into(),
                    up: nav_age(12) < 5.0,
                    last_data_age_s: Some(nav_age(12)),
                    bytes: k * 9_000,
                    connects: 2 + k / 12,
                    failed_attempts: k / 12,
                    last_error: Some("<script>alert(1)</script> device /dev/gnss0 absent".into()),
                },
            ],
            pulses: PulseCounts {
                frames_received: pulses_in + k,
                frames_recorded: pulses_in + k,
                frames_lost: k / 10,
                frames_bad: k / 100,
                pulses_in,
                pulses_processed: pulses_in - dropped,
                dropped_total: dropped,
                rate_in_hz: rate_in,
                rate_processed_hz: processed,
                rate_dropped_hz: dropped_rate,
            },
            drops,
            queues: vec![
                QueueFill {
                    name: "recorder".into(),
                    len: 3,
                    capacity: 4096,
                },
                QueueFill {
                    name: "worker-0".into(),
                    len: queue_len,
                    capacity: 1024,
                },
                QueueFill {
                    name: "worker-1".into(),
                    len: queue_len / 2,
                    capacity: 1024,
                },
            ],
            stages,
            end_to_end: latency("end_to_end", 400.0, pulses_in),
            nav: vec![
                NavStatus {
                    port: 1,
                    fix: Some(4),
                    fix_name: "RTK fixed".into(),
                    satellites: Some(17),
                    ins_status: Some(3),
                    ins_name: "solution good".into(),
                    last_packet_age_s: Some(0.004),
                    last_gps_sow: Some(345_600.0 + kf),
                    position: Some([47.3769, 8.5417, 1650.0 + kf * 0.1]),
                    samples: k * 200,
                    rejected: 0,
                },
                NavStatus {
                    port: 2,
                    fix: Some(1),
                    fix_name: "single".into(),
                    satellites: Some(5),
                    ins_status: None,
                    ins_name: String::new(),
                    last_packet_age_s: Some(nav_age(12)),
                    last_gps_sow: Some(345_600.0 + kf - nav_age(12)),
                    position: None,
                    samples: k * 10,
                    rejected: k / 20,
                },
            ],
            georeference: GeorefStatus {
                enabled: true,
                placed: pulses_in - dropped - k * 10,
                missed: [("navigation_gap".to_string(), k * 10)]
                    .into_iter()
                    .collect(),
                crs: Some("EPSG:2056".into()),
            },
            tiles: TilesStatus {
                open: 3.min(n),
                closed: n.saturating_sub(3),
                tile_m: [250.0, 250.0],
                cells,
            },
            recording: RecordingStatus {
                segment: "capture-0001.fwc".into(),
                bytes: pulses_in * 1200,
                records: pulses_in,
                nav_records: k * 210,
                error: None,
            },
            disk: DiskStatus {
                path: "/data".into(),
                free_bytes: 400_000_000_000 - pulses_in * 1200,
                total_bytes: 1_000_000_000_000,
                seconds_left: Some((400_000_000_000 - pulses_in * 1200) as f64 / 120e6),
                alarm: false,
            },
            saturation: SaturationStatus {
                pulses: k * 3,
                recent_fraction: 3.0 / rate_in,
            },
            alerts,
        };
        let point = HistoryPoint {
            t,
            rate_in_hz: rate_in,
            rate_processed_hz: processed,
            rate_dropped_hz: dropped_rate,
            queue_fill: queue_len as f64 / 1024.0,
            e2e_p50_us: 280.0 + 40.0 * (kf / 9.0).sin(),
            e2e_p99_us: 1800.0
                + 300.0 * (kf / 5.0).sin()
                + if dropped_rate > 0.0 { 5000.0 } else { 0.0 },
            stage_p99_us: snap.stages.iter().map(|s| s.p99_us).collect(),
        };
        (snap, point)
    }

    fn demo_waveform(k: u64) -> WaveformView {
        let n = 120;
        let g = |t: f64, mu: f64, s: f64, a: f64| a * (-0.5 * ((t - mu) / s).powi(2)).exp();
        let shift = (k % 10) as f64;
        let clean: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64;
                g(t, 40.0 + shift, 3.0, 0.8) + g(t, 58.0 + shift, 3.5, 0.35)
            })
            .collect();
        let noise = |i: usize| ((i * 7919 + k as usize * 31) % 97) as f64 / 97.0 * 0.06 - 0.03;
        let raw: Vec<f32> = clean
            .iter()
            .enumerate()
            .map(|(i, v)| (v + noise(i)) as f32)
            .collect();
        let denoised: Vec<f32> = clean.iter().map(|v| (*v * 0.98) as f32).collect();
        let deconv: Vec<f32> = (0..n)
            .map(|i| {
                let t = i as f64;
                (g(t, 40.0 + shift, 1.5, 1.5) + g(t, 58.0 + shift, 1.8, 0.6)) as f32
            })
            .collect();
        WaveformView {
            pulse_id: 1_000_000 + k,
            gps_time: 345_600.123_456 + k as f64,
            sample_ns: 1.0,
            start_ns: 1200.0,
            steps: vec![
                WaveformStep {
                    name: "raw".into(),
                    values: raw,
                },
                WaveformStep {
                    name: "denoise".into(),
                    values: denoised,
                },
                WaveformStep {
                    name: "deconvolve".into(),
                    values: deconv,
                },
            ],
            returns: vec![
                FittedView {
                    time_ns: 1240.0 + shift,
                    amplitude: 1.5,
                    sigma_ns: 1.5,
                },
                FittedView {
                    time_ns: 1258.0 + shift,
                    amplitude: 0.6,
                    sigma_ns: 1.8,
                },
            ],
        }
    }

    #[test]
    fn demo_snapshots_render_valid_metrics_and_json() {
        for k in [0, 1, 31, 100] {
            let (snap, point) = demo_snapshot(k, 1.79e9);
            crate::qc::prometheus::tests::check_exposition(&crate::qc::prometheus::render(&snap));
            serde_json::to_string(&snap).unwrap();
            serde_json::to_string(&point).unwrap();
            serde_json::to_string(&demo_waveform(k)).unwrap();
        }
    }

    #[test]
    #[ignore = "serves a demonstration page until FWLIDAR_QC_DEMO_SECS have passed"]
    fn demo() {
        let addr = std::env::var("FWLIDAR_QC_DEMO_ADDR").unwrap_or("127.0.0.1:8787".into());
        let secs: u64 = std::env::var("FWLIDAR_QC_DEMO_SECS")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(60);
        let hub = Arc::new(QcHub::default());
        let start = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_secs_f64();
        // Some history already, as after two minutes of running.
        let history = 120;
        for k in 0..history {
            let (s, p) = demo_snapshot(k, start - history as f64);
            hub.publish(s, p);
        }
        let server = spawn(addr.parse().expect("FWLIDAR_QC_DEMO_ADDR"), hub.clone()).unwrap();
        println!("QC demo on http://{}/ for {secs} s", server.local_addr());
        for k in history..history + secs {
            let (s, p) = demo_snapshot(k, start - history as f64);
            hub.publish(s, p);
            if k % 2 == 0 {
                hub.set_waveform(demo_waveform(k));
            }
            std::thread::sleep(Duration::from_secs(1));
        }
        server.shutdown();
    }
}
