//! The viewer, served on a loopback address with axum: a hand-written page drawing a live
//! skeleton, and for a finished file (`choreod view`) a three.js player of the mannequin glTF
//! with the song. Pages and three.js are embedded in the binary (three.js from the npm package
//! scripts/setup installs, see build.rs). Routes:
//!
//! - `GET /` — the live page, or the player for a file.
//! - `GET /skeleton.json` — `{fps, joint_names, parents}` of what is shown.
//! - `GET /ws` — live frames, one JSON text message each (`{frame, time, joints}`, or
//!   `{status}` while the session waits for audio), from a broadcast channel; a client too
//!   slow to keep up skips frames instead of slowing the loop.
//! - `GET /motion.glb` — a finished file as glTF (what `choreod convert -o X.glb` writes).
//! - `GET /audio.wav` — its song, decoded (404 without one).
//! - `GET /vendor/three/...` — the three.js modules the player imports.
//!
//! Every request must name this server by a loopback address or `localhost` in `Host`, and a
//! browser's `Origin`, when sent, must be this server: another web page (directly or through
//! DNS rebinding) gets 403 instead of the motion.

use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::Context;
use axum::Router;
use axum::extract::Request;
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde::Serialize;
use tokio::sync::broadcast;

const PAGE: &str = include_str!("../../assets/viewer/index.html");
const PLAYER: &str = include_str!("../../assets/viewer/player.html");
const PLAYER_JS: &str = include_str!("../../assets/viewer/player.js");

// `THREE_FILES`: (path under node_modules/, bytes), written by build.rs.
include!(concat!(env!("OUT_DIR"), "/viewer_vendor.rs"));

/// A finished motion as the player shows it.
#[derive(Debug, Clone)]
pub struct ViewFile {
    /// The motion as binary glTF.
    pub glb: Vec<u8>,
    /// The song as a WAV file, if there is one.
    pub audio_wav: Option<Vec<u8>>,
}

/// What the page shows about the skeleton.
#[derive(Debug, Clone, Serialize)]
pub struct SkeletonInfo {
    pub fps: f64,
    pub joint_names: Vec<String>,
    pub parents: Vec<i32>,
}

/// One live frame as the WebSocket sends it.
#[derive(Debug, Serialize)]
pub struct FrameMessage<'a> {
    pub frame: usize,
    pub time: f64,
    pub joints: &'a [[f32; 3]],
}

/// A session state the page shows while no frames come (`{"status": "waiting for audio"}`).
#[derive(Debug, Serialize)]
pub struct StatusMessage {
    pub status: &'static str,
}

#[derive(Debug)]
struct AppState {
    skeleton: String,
    file: Option<ViewFile>,
    frames: Option<broadcast::Sender<Arc<str>>>,
}

/// A running viewer server; dropping it stops the server.
#[derive(Debug)]
pub struct Viewer {
    pub addr: SocketAddr,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Viewer {
    fn drop(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Serve the page on `bind` (port 0 picks a free one): live frames from `frames`, or a
/// finished motion `file`.
pub fn serve(
    bind: SocketAddr,
    skeleton: &SkeletonInfo,
    frames: Option<broadcast::Sender<Arc<str>>>,
    file: Option<ViewFile>,
) -> anyhow::Result<Viewer> {
    let state = Arc::new(AppState {
        skeleton: serde_json::to_string(skeleton)?,
        file,
        frames,
    });
    let listener = std::net::TcpListener::bind(bind)
        .with_context(|| format!("cannot listen on {bind} for the viewer"))?;
    listener.set_nonblocking(true)?;
    let addr = listener.local_addr()?;
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let app = Router::new()
        .route("/", get(page))
        .route("/skeleton.json", get(skeleton_json))
        .route("/motion.glb", get(motion_glb))
        .route("/audio.wav", get(audio_wav))
        .route("/player.js", get(player_js))
        .route("/vendor/{*path}", get(vendor))
        .route("/ws", get(ws_route))
        .with_state(state)
        .layer(axum::middleware::from_fn_with_state(addr, same_origin));
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the viewer's runtime")?;
    let thread = std::thread::Builder::new()
        .name("viewer".into())
        .spawn(move || {
            runtime.block_on(async move {
                let listener = match tokio::net::TcpListener::from_std(listener) {
                    Ok(l) => l,
                    Err(e) => {
                        tracing::error!(error = %e, "viewer listener");
                        return;
                    }
                };
                let server = axum::serve(listener, app).with_graceful_shutdown(async {
                    let _ = rx.await;
                });
                if let Err(e) = server.await {
                    tracing::error!(error = %e, "viewer server stopped");
                }
            });
        })?;
    Ok(Viewer {
        addr,
        shutdown: Some(tx),
        thread: Some(thread),
    })
}

/// Refuse (403) a request that does not name this server in `Host` or comes from another
/// site's page (`Origin`).
async fn same_origin(State(addr): State<SocketAddr>, request: Request, next: Next) -> Response {
    if from_this_server(request.headers(), addr) {
        next.run(request).await
    } else {
        (
            StatusCode::FORBIDDEN,
            "the viewer answers only pages of its own loopback address\n",
        )
            .into_response()
    }
}

/// `Host` is the bound address or `localhost` with its port, and `Origin` is absent or
/// `http://` and one of those.
fn from_this_server(headers: &HeaderMap, addr: SocketAddr) -> bool {
    let ours =
        |host: &str| host == addr.to_string() || host == format!("localhost:{}", addr.port());
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    let origin = headers.get(header::ORIGIN).map(|o| o.to_str().ok());
    host.is_some_and(ours)
        && match origin {
            None => true,
            Some(origin) => origin
                .and_then(|o| o.strip_prefix("http://"))
                .is_some_and(ours),
        }
}

fn json(body: String) -> Response {
    ([(header::CONTENT_TYPE, "application/json")], body).into_response()
}

async fn page(State(s): State<Arc<AppState>>) -> impl IntoResponse {
    let page = if s.file.is_some() { PLAYER } else { PAGE };
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], page)
}

async fn player_js() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        PLAYER_JS,
    )
}

fn not_found(why: &'static str) -> Response {
    (axum::http::StatusCode::NOT_FOUND, why).into_response()
}

async fn motion_glb(State(s): State<Arc<AppState>>) -> Response {
    match &s.file {
        Some(f) => ([(header::CONTENT_TYPE, "model/gltf-binary")], f.glb.clone()).into_response(),
        None => not_found("live session: no file"),
    }
}

async fn audio_wav(State(s): State<Arc<AppState>>) -> Response {
    match s.file.as_ref().and_then(|f| f.audio_wav.as_ref()) {
        Some(wav) => ([(header::CONTENT_TYPE, "audio/wav")], wav.clone()).into_response(),
        None => not_found("no song"),
    }
}

async fn vendor(axum::extract::Path(path): axum::extract::Path<String>) -> Response {
    match THREE_FILES.iter().find(|(p, _)| *p == path) {
        Some((_, bytes)) => (
            [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
            *bytes,
        )
            .into_response(),
        None => not_found("not bundled: run scripts/setup (npm ci), then rebuild choreod"),
    }
}

async fn skeleton_json(State(s): State<Arc<AppState>>) -> Response {
    json(s.skeleton.clone())
}

async fn ws_route(ws: WebSocketUpgrade, State(s): State<Arc<AppState>>) -> Response {
    match &s.frames {
        Some(tx) => {
            let rx = tx.subscribe();
            ws.on_upgrade(move |socket| forward(socket, rx))
        }
        None => (StatusCode::NOT_FOUND, "not a live session").into_response(),
    }
}

async fn forward(mut socket: WebSocket, mut rx: broadcast::Receiver<Arc<str>>) {
    loop {
        match rx.recv().await {
            Ok(text) => {
                if socket
                    .send(Message::Text(text.as_ref().into()))
                    .await
                    .is_err()
                {
                    return;
                }
            }
            Err(broadcast::error::RecvError::Lagged(_)) => continue,
            Err(broadcast::error::RecvError::Closed) => {
                let _ = socket.send(Message::Close(None)).await;
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_requests_naming_this_server_from_its_own_pages_pass() {
        let addr: SocketAddr = "127.0.0.1:8080".parse().unwrap();
        let check = |host: Option<&str>, origin: Option<&str>| {
            let mut h = HeaderMap::new();
            if let Some(v) = host {
                h.insert(header::HOST, v.parse().unwrap());
            }
            if let Some(v) = origin {
                h.insert(header::ORIGIN, v.parse().unwrap());
            }
            from_this_server(&h, addr)
        };
        assert!(check(Some("127.0.0.1:8080"), None));
        assert!(check(Some("localhost:8080"), Some("http://localhost:8080")));
        assert!(check(Some("127.0.0.1:8080"), Some("http://127.0.0.1:8080")));
        assert!(!check(None, None), "no Host");
        assert!(!check(Some("evil.example:8080"), None), "DNS rebinding");
        assert!(!check(Some("127.0.0.1:9999"), None));
        assert!(!check(Some("127.0.0.1:8080"), Some("http://evil.example")));
        assert!(!check(Some("127.0.0.1:8080"), Some("null")));
        assert!(!check(
            Some("127.0.0.1:8080"),
            Some("https://127.0.0.1:8080")
        ));
        let v6: SocketAddr = "[::1]:8080".parse().unwrap();
        let mut h = HeaderMap::new();
        h.insert(header::HOST, "[::1]:8080".parse().unwrap());
        assert!(from_this_server(&h, v6));
    }
}
