//! The viewer: one hand-written page (embedded in the binary) that draws a skeleton, served on
//! a loopback address with axum. Routes:
//!
//! - `GET /` — the page.
//! - `GET /skeleton.json` — `{fps, joint_names, parents}` of what is shown.
//! - `GET /ws` — live frames, one JSON text message each (`{frame, time, joints}`, or
//!   `{status}` while the session waits for audio), from a broadcast channel; a client too slow to keep up skips frames instead of slowing the loop.
//! - `GET /motion.json` — a finished file's frames (`{fps, joints}`), for `choreod view`.

use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::Context;
use axum::Router;
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde::Serialize;
use tokio::sync::broadcast;

const PAGE: &str = include_str!("../../assets/viewer/index.html");

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
    motion: Option<String>,
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
/// finished motion's `motion_json`.
pub fn serve(
    bind: SocketAddr,
    skeleton: &SkeletonInfo,
    frames: Option<broadcast::Sender<Arc<str>>>,
    motion_json: Option<String>,
) -> anyhow::Result<Viewer> {
    let state = Arc::new(AppState {
        skeleton: serde_json::to_string(skeleton)?,
        motion: motion_json,
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
        .route("/motion.json", get(motion_json_route))
        .route("/ws", get(ws_route))
        .with_state(state);
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

fn json(body: String) -> Response {
    ([(header::CONTENT_TYPE, "application/json")], body).into_response()
}

async fn page() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], PAGE)
}

async fn skeleton_json(State(s): State<Arc<AppState>>) -> Response {
    json(s.skeleton.clone())
}

async fn motion_json_route(State(s): State<Arc<AppState>>) -> Response {
    match &s.motion {
        Some(m) => json(m.clone()),
        None => (axum::http::StatusCode::NOT_FOUND, "live session: no file").into_response(),
    }
}

async fn ws_route(ws: WebSocketUpgrade, State(s): State<Arc<AppState>>) -> Response {
    match &s.frames {
        Some(tx) => {
            let rx = tx.subscribe();
            ws.on_upgrade(move |socket| forward(socket, rx))
        }
        None => (axum::http::StatusCode::NOT_FOUND, "not a live session").into_response(),
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
