//! The viewer, served on a loopback address with axum: the mannequin choreod's glTF files
//! carry, drawn by three.js, posed live from a session's frames or playing a finished file
//! (`choreod view`) with its song. Pages and three.js are embedded in the binary (three.js from
//! the npm package scripts/setup installs, see build.rs). Routes:
//!
//! - `GET /` — the live page, or the player for a file.
//! - `GET /skeleton.json` — `{fps, joint_names, parents, nodes}` of what is shown (`nodes`: the
//!   glTF node of every joint).
//! - `GET /mannequin.glb` — live: the skeleton's mannequin in its rest pose
//!   ([`choreo_datasets::rest_mannequin_glb`]), which the page poses from the frames.
//! - `GET /ws` — live messages, one JSON text each, all with `"v": 2` (the wire's version):
//!   `{v, rest}` the session's rest offsets (metres, each joint from its parent; sent before
//!   its first frame and to every client that connects later), `{v, frame, time, root,
//!   rotations}` a frame (root joint position, metres; every joint's global rotation of its
//!   rest offset as a quaternion `[x, y, z, w]`: the rigid fit's, as the glTF writer's), or
//!   `{v, status}` while the session waits for audio. From a broadcast channel: a client too
//!   slow to keep up skips frames instead of slowing the loop.
//! - `GET /motion.glb` — a finished file as glTF (what `choreod convert -o X.glb` writes).
//! - `GET /audio.wav` — its song, decoded (404 without one).
//! - `GET /vendor/three/...` — the three.js modules the pages import.
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
/// The pages' scripts: (route, source).
const SCRIPTS: [(&str, &str); 3] = [
    ("stage.js", include_str!("../../assets/viewer/stage.js")),
    ("player.js", include_str!("../../assets/viewer/player.js")),
    ("live.js", include_str!("../../assets/viewer/live.js")),
];
/// Version of the WebSocket's messages (`v`); the page refuses others.
pub const WIRE_VERSION: u32 = 2;

// `THREE_FILES`: (path under node_modules/, bytes), written by build.rs.
include!(concat!(env!("OUT_DIR"), "/viewer_vendor.rs"));

/// A finished motion as the player shows it.
#[derive(Debug, Clone)]
pub struct ViewFile {
    /// The motion as binary glTF.
    pub glb: Vec<u8>,
    /// The song as a WAV file, or why there is none (the page shows it).
    pub audio: Result<Vec<u8>, String>,
}

/// What the page shows about the skeleton.
#[derive(Debug, Clone, Serialize)]
pub struct SkeletonInfo {
    pub fps: f64,
    pub joint_names: Vec<String>,
    pub parents: Vec<i32>,
    /// The glTF node of every joint (choreod writes joint k as node k).
    pub nodes: Vec<usize>,
}

impl SkeletonInfo {
    /// A skeleton whose joint k is glTF node k (every file choreod writes).
    pub fn of(fps: f64, skeleton: &choreo_datasets::SkeletonKind) -> Self {
        let parents = skeleton.parents().to_vec();
        Self {
            fps,
            joint_names: skeleton.joint_names(),
            nodes: (0..parents.len()).collect(),
            parents,
        }
    }
}

/// Quaternion components and root coordinates on the wire are rounded to this: a rotation off
/// by 5e-5 per component turns a bone by about 1e-4 rad, 0.1 mm at a metre; the root moves by
/// 0.05 mm at most. Whole frames are ~0.8 kB for 24 joints.
const WIRE_STEP: f32 = 1e-4;

fn rounded<const N: usize>(v: [f32; N]) -> [f32; N] {
    v.map(|c| (c / WIRE_STEP).round() * WIRE_STEP)
}

/// One live frame as the WebSocket sends it.
#[derive(Debug, Serialize)]
struct FrameMessage {
    v: u32,
    frame: usize,
    time: f64,
    root: [f32; 3],
    rotations: Vec<[f32; 4]>,
}

/// A session's rest offsets as the WebSocket sends them.
#[derive(Debug, Serialize)]
struct RestMessage<'a> {
    v: u32,
    rest: &'a [[f32; 3]],
}

/// A session state the page shows while no frames come (`{"v": 2, "status": "waiting for
/// audio"}`).
#[derive(Debug, Serialize)]
struct StatusMessage {
    v: u32,
    status: &'static str,
}

/// The messages of one session for the WebSocket: its rest offsets before its first frame,
/// then its frames.
#[derive(Debug, Default)]
pub struct WireEncoder {
    rest_sent: Option<Vec<[f32; 3]>>,
}

impl WireEncoder {
    /// Frame `i` of `pose`, the session's frame `index` at `time` seconds: one message, or two
    /// when the rest offsets are new.
    pub fn frame(
        &mut self,
        pose: &choreo_datasets::RigidPose,
        i: usize,
        index: usize,
        time: f64,
    ) -> Vec<Arc<str>> {
        let mut out = Vec::with_capacity(2);
        if self.rest_sent.as_deref() != Some(&pose.offsets) {
            let rest: Vec<[f32; 3]> = pose.offsets.iter().map(|o| rounded(*o)).collect();
            out.extend(text(&RestMessage {
                v: WIRE_VERSION,
                rest: &rest,
            }));
            self.rest_sent = Some(pose.offsets.clone());
        }
        let nj = pose.offsets.len();
        let rotations = (0..nj)
            .map(|k| {
                let [w, x, y, z] = choreo_datasets::rotation::mat_to_quat(pose.rotation(i, k));
                rounded([x, y, z, w])
            })
            .collect();
        let root = rounded([0, 1, 2].map(|c| pose.joints[[i, 0, c]]));
        out.extend(text(&FrameMessage {
            v: WIRE_VERSION,
            frame: index,
            time,
            root,
            rotations,
        }));
        out
    }

    /// A session state (e.g. "waiting for audio").
    pub fn status(status: &'static str) -> Option<Arc<str>> {
        text(&StatusMessage {
            v: WIRE_VERSION,
            status,
        })
    }
}

fn text(message: &impl Serialize) -> Option<Arc<str>> {
    serde_json::to_string(message).ok().map(Arc::from)
}

/// Whether a wire message is a rest message (kept for pages that connect later).
fn is_rest(text: &str) -> bool {
    serde_json::from_str::<serde_json::Value>(text).is_ok_and(|v| v["rest"].is_array())
}

#[derive(Debug)]
struct AppState {
    skeleton: String,
    file: Option<ViewFile>,
    frames: Option<broadcast::Sender<Arc<str>>>,
    /// Live: the mannequin to pose, and the latest session's rest message.
    mannequin: Option<Vec<u8>>,
    rest: std::sync::Mutex<Option<Arc<str>>>,
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

/// Serve the page on `bind` (port 0 picks a free one): live frames from `frames` (messages
/// of a [`WireEncoder`]), or a finished motion `file`.
pub fn serve(
    bind: SocketAddr,
    skeleton: &SkeletonInfo,
    frames: Option<broadcast::Sender<Arc<str>>>,
    file: Option<ViewFile>,
) -> anyhow::Result<Viewer> {
    let mannequin = match &frames {
        Some(_) => Some(live_mannequin(skeleton)?),
        None => None,
    };
    let state = Arc::new(AppState {
        skeleton: serde_json::to_string(skeleton)?,
        file,
        frames,
        mannequin,
        rest: std::sync::Mutex::new(None),
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
        .route("/mannequin.glb", get(mannequin_glb))
        .route("/{script}", get(script))
        .route("/vendor/{*path}", get(vendor))
        .route("/ws", get(ws_route))
        .with_state(Arc::clone(&state))
        .layer(axum::middleware::from_fn_with_state(addr, same_origin));
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the viewer's runtime")?;
    let thread = std::thread::Builder::new()
        .name("viewer".into())
        .spawn(move || {
            runtime.block_on(async move {
                if let Some(tx) = &state.frames {
                    tokio::spawn(keep_rest(Arc::clone(&state), tx.subscribe()));
                }
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

async fn script(axum::extract::Path(name): axum::extract::Path<String>) -> Response {
    match SCRIPTS.iter().find(|(n, _)| *n == name) {
        Some((_, source)) => (
            [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
            *source,
        )
            .into_response(),
        None => not_found("no such page"),
    }
}

/// The rest-pose mannequin of a live skeleton (SMPL-24 or t2m-22, the skeletons a package's
/// live output has).
fn live_mannequin(skeleton: &SkeletonInfo) -> anyhow::Result<Vec<u8>> {
    use choreo_datasets::SkeletonKind;
    let kind = [SkeletonKind::Smpl24, SkeletonKind::T2m22]
        .into_iter()
        .find(|k| k.parents() == skeleton.parents.as_slice())
        .context("the live viewer draws SMPL-24 and t2m-22 skeletons only")?;
    Ok(choreo_datasets::rest_mannequin_glb(&kind)?)
}

async fn mannequin_glb(State(s): State<Arc<AppState>>) -> Response {
    match &s.mannequin {
        Some(glb) => ([(header::CONTENT_TYPE, "model/gltf-binary")], glb.clone()).into_response(),
        None => not_found("not a live session"),
    }
}

/// Remember the latest rest message for pages that connect after it was sent.
async fn keep_rest(state: Arc<AppState>, mut rx: broadcast::Receiver<Arc<str>>) {
    loop {
        match rx.recv().await {
            Ok(text) if is_rest(&text) => {
                if let Ok(mut rest) = state.rest.lock() {
                    *rest = Some(text);
                }
            }
            Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
            Err(broadcast::error::RecvError::Closed) => return,
        }
    }
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
    match s.file.as_ref().map(|f| &f.audio) {
        Some(Ok(wav)) => ([(header::CONTENT_TYPE, "audio/wav")], wav.clone()).into_response(),
        Some(Err(why)) => (StatusCode::NOT_FOUND, format!("no song: {why}")).into_response(),
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
            // Subscribed before the rest is read: a rest sent in between comes twice, not never.
            let rx = tx.subscribe();
            let rest = s.rest.lock().ok().and_then(|r| r.clone());
            ws.on_upgrade(move |socket| forward(socket, rest, rx))
        }
        None => (StatusCode::NOT_FOUND, "not a live session").into_response(),
    }
}

async fn forward(
    mut socket: WebSocket,
    rest: Option<Arc<str>>,
    mut rx: broadcast::Receiver<Arc<str>>,
) {
    if let Some(rest) = rest
        && socket
            .send(Message::Text(rest.as_ref().into()))
            .await
            .is_err()
    {
        return;
    }
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
