//! A headless Chromium showing a page, driven through the DevTools protocol (the viewer tests).

use std::io::{Read, Write};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::daemon::free_port;

/// A headless Chromium (Debian's, scripts/setup installs it) showing one page.
pub struct Browser {
    child: Child,
    socket: tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<std::net::TcpStream>>,
    _profile: tempfile::TempDir,
    next_id: u64,
}

impl std::fmt::Debug for Browser {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Browser")
            .field("pid", &self.child.id())
            .finish()
    }
}

impl Browser {
    /// Chromium at 640×480 showing `url`.
    pub fn open(url: &str) -> Browser {
        Self::open_with(url, &[])
    }

    /// [`Browser::open`] with extra command-line switches (e.g. an autoplay policy).
    pub fn open_with(url: &str, extra: &[&str]) -> Browser {
        let profile = tempfile::tempdir().expect("a temporary profile folder");
        let port = free_port();
        let mut child = Command::new("/usr/bin/chromium")
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                // WebGL (the player's three.js) on the CPU: Chromium no longer falls back to
                // SwiftShader by itself.
                "--enable-unsafe-swiftshader",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--window-size=640,480",
                &format!("--remote-debugging-port={port}"),
                &format!("--user-data-dir={}", profile.path().display()),
            ])
            .args(extra)
            .arg(url)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromium installed (scripts/setup)");
        let t0 = Instant::now();
        let ws_url = loop {
            if t0.elapsed() > Duration::from_secs(20) {
                // Do not leave the browser behind when the test fails.
                let _ = child.kill();
                let _ = child.wait();
                panic!("chromium DevTools did not answer on port {port}");
            }
            if let Ok(list) = http_get(port, "/json/list")
                && let Ok(v) = serde_json::from_str::<serde_json::Value>(&list)
                && let Some(u) = v.as_array().and_then(|a| {
                    a.iter()
                        .find(|t| t["type"] == "page")
                        .and_then(|t| t["webSocketDebuggerUrl"].as_str())
                })
            {
                break u.to_owned();
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        let socket = match tungstenite::connect(ws_url.as_str()) {
            Ok((socket, _)) => socket,
            Err(e) => {
                let _ = child.kill();
                let _ = child.wait();
                panic!("DevTools socket {ws_url}: {e}");
            }
        };
        Browser {
            child,
            socket,
            _profile: profile,
            next_id: 0,
        }
    }

    /// Send one DevTools command and return its `result`.
    pub fn call(&mut self, method: &str, params: serde_json::Value) -> serde_json::Value {
        self.next_id += 1;
        let id = self.next_id;
        let msg = serde_json::json!({"id": id, "method": method, "params": params});
        self.socket
            .send(tungstenite::Message::text(msg.to_string()))
            .expect("DevTools socket open");
        loop {
            let m = self.socket.read().expect("DevTools reply");
            if let Ok(text) = m.to_text()
                && let Ok(v) = serde_json::from_str::<serde_json::Value>(text)
                && v["id"] == id
            {
                return v["result"].clone();
            }
        }
    }

    /// Evaluate a JS expression in the page (its value as JSON; promises are awaited).
    pub fn eval(&mut self, expression: &str) -> serde_json::Value {
        self.call(
            "Runtime.evaluate",
            serde_json::json!({"expression": expression, "returnByValue": true,
                "awaitPromise": true}),
        )["result"]["value"]
            .clone()
    }

    /// Wait up to `timeout` for `expression` to be true in the page.
    pub fn wait_for(&mut self, expression: &str, timeout: Duration) -> bool {
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            if self.eval(expression) == serde_json::Value::Bool(true) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        false
    }

    /// A PNG screenshot of the page.
    pub fn screenshot(&mut self) -> Vec<u8> {
        use base64::Engine;
        let data = self.call(
            "Page.captureScreenshot",
            serde_json::json!({"format": "png"}),
        );
        base64::engine::general_purpose::STANDARD
            .decode(data["data"].as_str().expect("screenshot data"))
            .expect("base64 screenshot")
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `GET path` from a loopback port (Chromium's DevTools list).
pub fn http_get(port: u16, path: &str) -> std::io::Result<String> {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port))?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"
    )?;
    // Chromium keeps the connection open: read the headers, then Content-Length bytes.
    let mut data = Vec::new();
    let mut buf = [0u8; 8192];
    loop {
        let n = s.read(&mut buf)?;
        if n == 0 {
            break;
        }
        data.extend_from_slice(&buf[..n]);
        let text = String::from_utf8_lossy(&data);
        if let Some((head, body)) = text.split_once("\r\n\r\n") {
            let len = head
                .lines()
                .find_map(|l| {
                    let (k, v) = l.split_once(':')?;
                    k.eq_ignore_ascii_case("content-length")
                        .then(|| v.trim().parse::<usize>().ok())?
                })
                .unwrap_or(usize::MAX);
            if body.len() >= len {
                return Ok(body.to_owned());
            }
        }
    }
    let text = String::from_utf8_lossy(&data).into_owned();
    Ok(text
        .split_once("\r\n\r\n")
        .map_or(text.clone(), |(_, b)| b.to_owned()))
}

/// Canvas pixels of `#view` that are not the page's background (#16181d): what is drawn, on
/// a 2D canvas or a WebGL one (the player keeps its drawing buffer for this).
pub const INKED_JS: &str = r#"(() => { const c = document.getElementById("view");
    const o = document.createElement("canvas"); o.width = c.width; o.height = c.height;
    const x = o.getContext("2d"); x.drawImage(c, 0, 0);
    const d = x.getImageData(0, 0, o.width, o.height).data;
    let n = 0;
    for (let i = 0; i < d.length; i += 4)
        if (d[i] !== 0x16 || d[i + 1] !== 0x18 || d[i + 2] !== 0x1d) n++;
    return n; })()"#;
