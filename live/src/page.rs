//! The built-in page: a quick look at the rig from any browser, without Foxglove.
//!
//! A small HTTP server (`tiny_http`: no async runtime of its own, no TLS, nothing the page
//! does not need) on its own address serves:
//!
//! | path | what |
//! |---|---|
//! | `/` | the page ([`PAGE`]): the live composite, the status and the lighting estimate |
//! | `/composite.jpg` | the newest composite, JPEG (503 before the first frame) |
//! | `/status.json` | `{"seq", "status", "lighting"}` |
//!
//! It is read-only: only `GET` and `HEAD`, and nothing it serves changes the daemon; control
//! stays on the Unix socket. Two threads answer, so one slow client does not hold the page
//! for the others, and neither is the render thread.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use serde_json::{Value, json};
use tiny_http::{Header, Method, Request, Response, Server};

use crate::LiveViewError;

/// The page, self-contained (no script or style from elsewhere, so it works offline).
pub const PAGE: &str = include_str!("page.html");

const WORKERS: usize = 2;

/// What the page shows, updated by the publisher.
#[derive(Debug, Default)]
pub struct PageState {
    composite: Mutex<Option<(u64, Arc<Vec<u8>>)>>,
    reports: Mutex<(Value, Option<Value>)>,
}

impl PageState {
    pub fn set_composite(&self, seq: u64, jpeg: Vec<u8>) {
        *self.composite.lock().unwrap_or_else(|e| e.into_inner()) = Some((seq, Arc::new(jpeg)));
    }

    pub fn set_reports(&self, status: Value, lighting: Option<Value>) {
        *self.reports.lock().unwrap_or_else(|e| e.into_inner()) = (status, lighting);
    }

    fn composite(&self) -> Option<(u64, Arc<Vec<u8>>)> {
        self.composite
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    fn status_json(&self) -> Value {
        let seq = self.composite().map(|(seq, _)| seq);
        let (status, lighting) = self
            .reports
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        json!({ "seq": seq, "status": status, "lighting": lighting })
    }
}

/// The running page server. Dropping it stops it.
pub struct PageServer {
    server: Arc<Server>,
    addr: SocketAddr,
    workers: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for PageServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PageServer")
            .field("addr", &self.addr)
            .finish_non_exhaustive()
    }
}

impl PageServer {
    pub fn start(addr: SocketAddr, state: Arc<PageState>) -> Result<Self, LiveViewError> {
        let server = Server::http(addr).map_err(|e| LiveViewError::Page {
            addr,
            message: e.to_string(),
        })?;
        let bound = server.server_addr().to_ip().unwrap_or(addr);
        let server = Arc::new(server);
        let workers = (0..WORKERS)
            .map(|i| {
                let server = Arc::clone(&server);
                let state = Arc::clone(&state);
                std::thread::Builder::new()
                    .name(format!("live-page-{i}"))
                    .spawn(move || {
                        // `recv` fails once the server is unblocked (dropped).
                        while let Ok(request) = server.recv() {
                            answer(request, &state);
                        }
                    })
            })
            .collect::<Result<_, _>>()?;
        Ok(Self {
            server,
            addr: bound,
            workers,
        })
    }

    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for PageServer {
    fn drop(&mut self) {
        for _ in &self.workers {
            self.server.unblock();
        }
        for worker in self.workers.drain(..) {
            drop(worker.join());
        }
    }
}

fn header(name: &str, value: &str) -> Header {
    Header::from_bytes(name.as_bytes(), value.as_bytes()).expect("a valid ASCII header")
}

fn answer(request: Request, state: &PageState) {
    if !matches!(request.method(), Method::Get | Method::Head) {
        let response = Response::from_string("the page is read-only: GET or HEAD\n")
            .with_status_code(405)
            .with_header(header("Allow", "GET, HEAD"));
        drop(request.respond(response));
        return;
    }
    let path = request.url().split('?').next().unwrap_or("/").to_owned();
    let no_store = header("Cache-Control", "no-store");
    let response = match path.as_str() {
        "/" | "/index.html" => Response::from_string(PAGE)
            .with_header(header("Content-Type", "text/html; charset=utf-8")),
        "/composite.jpg" => match state.composite() {
            Some((seq, jpeg)) => Response::from_data(jpeg.as_slice())
                .with_header(header("Content-Type", "image/jpeg"))
                .with_header(header("X-Relight-Seq", &seq.to_string()))
                .with_header(no_store),
            None => Response::from_string("no frame rendered yet\n").with_status_code(503),
        },
        "/status.json" => Response::from_string(state.status_json().to_string())
            .with_header(header("Content-Type", "application/json"))
            .with_header(no_store),
        _ => Response::from_string("not found\n").with_status_code(404),
    };
    // A client that went away is its own business.
    drop(request.respond(response));
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};
    use std::net::TcpStream;

    fn get(addr: SocketAddr, request: &str) -> String {
        let mut stream = TcpStream::connect(addr).unwrap();
        stream.write_all(request.as_bytes()).unwrap();
        let mut out = Vec::new();
        stream.read_to_end(&mut out).unwrap();
        String::from_utf8_lossy(&out).into_owned()
    }

    #[test]
    fn the_page_serves_the_newest_composite_and_refuses_writes() {
        let state = Arc::new(PageState::default());
        let server = PageServer::start("127.0.0.1:0".parse().unwrap(), Arc::clone(&state)).unwrap();
        let addr = server.addr();
        let close = "Connection: close\r\n\r\n";
        assert!(get(addr, &format!("GET /composite.jpg HTTP/1.1\r\n{close}")).contains(" 503 "));
        state.set_composite(7, vec![0xFF, 0xD8, 0xFF, 0xD9]);
        state.set_reports(json!({"engine": "differential"}), None);
        let image = get(addr, &format!("GET /composite.jpg?t=1 HTTP/1.1\r\n{close}"));
        assert!(
            image.contains(" 200 ") && image.contains("X-Relight-Seq: 7"),
            "{image}"
        );
        let status = get(addr, &format!("GET /status.json HTTP/1.1\r\n{close}"));
        assert!(status.contains(r#""engine":"differential""#) && status.contains(r#""seq":7"#));
        let page = get(addr, &format!("GET / HTTP/1.1\r\n{close}"));
        assert!(page.contains("<img") && page.contains("composite.jpg"));
        let post = get(
            addr,
            &format!("POST /status.json HTTP/1.1\r\nContent-Length: 0\r\n{close}"),
        );
        assert!(post.contains(" 405 "), "{post}");
        assert!(get(addr, &format!("GET /nosuch HTTP/1.1\r\n{close}")).contains(" 404 "));
    }
}
