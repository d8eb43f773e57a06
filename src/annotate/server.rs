//! Routing of requests to the page's files and the API handlers, and the
//! HTTP loop (`tiny_http`, a few worker threads, no async runtime).

use super::api::{self, Reply, MAX_BODY_BYTES};
use super::session::Session;
use std::io::Read;
use std::net::SocketAddr;
use std::sync::Arc;

/// Threads answering requests (a preview may take a second; the page keeps loading).
const WORKERS: usize = 3;

const INDEX_HTML: &str = include_str!("page/index.html");
const APP_JS: &str = include_str!("page/app.js");
const STYLE_CSS: &str = include_str!("page/style.css");

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cannot listen on {addr}: {message}")]
    Bind { addr: String, message: String },
}

fn text(content_type: &'static str, body: &str) -> Reply {
    Reply {
        status: 200,
        content_type,
        body: body.as_bytes().to_vec(),
    }
}

/// The reply to one request; `body` is the request body.
pub fn route(session: &Session, method: &str, url: &str, body: &[u8]) -> Reply {
    let path = url.split(['?', '#']).next().unwrap_or("");
    match (method, path) {
        ("GET", "/" | "/index.html") => text("text/html; charset=utf-8", INDEX_HTML),
        ("GET", "/app.js") => text("text/javascript; charset=utf-8", APP_JS),
        ("GET", "/style.css") => text("text/css; charset=utf-8", STYLE_CSS),
        ("GET", "/api/info") => api::info(session),
        ("GET", "/api/boxes") => api::get_boxes(session),
        ("PUT", "/api/boxes") => api::put_boxes(session, body),
        ("POST", "/api/fit") => api::fit(session, body),
        ("GET", "/api/frames") => api::frames(session),
        ("GET", "/api/cloud.bin") => api::cloud(session),
        (m, p) if preview_stem(p).is_some() => {
            let stem = preview_stem(p).unwrap_or_default();
            match m {
                "GET" => api::preview(session, stem, None),
                "POST" => api::preview(session, stem, Some(body)),
                _ => Reply::error(405, format!("{m} {p}: use GET or POST")),
            }
        }
        (m, p) => Reply::error(404, format!("no such page or API call: {m} {p}")),
    }
}

/// The frame stem of a `/api/frames/{stem}/preview.png` path.
fn preview_stem(path: &str) -> Option<&str> {
    let stem = path.strip_prefix("/api/frames/")?.strip_suffix("/preview.png")?;
    (!stem.is_empty() && !stem.contains('/')).then_some(stem)
}

/// Listen on `host:port` (port 0: a free one); `ready` gets the bound
/// address before requests are served. Serves until the process ends.
pub fn serve(session: Arc<Session>, host: &str, port: u16, ready: impl FnOnce(SocketAddr)) -> Result<(), ServeError> {
    // An IPv6 address takes brackets before its port.
    let addr = if host.contains(':') && !host.starts_with('[') {
        format!("[{host}]:{port}")
    } else {
        format!("{host}:{port}")
    };
    let server = tiny_http::Server::http(addr.as_str()).map_err(|e| ServeError::Bind {
        addr: addr.clone(),
        message: e.to_string(),
    })?;
    let bound = server.server_addr().to_ip().ok_or_else(|| ServeError::Bind {
        addr: addr.clone(),
        message: "not an IP address".into(),
    })?;
    ready(bound);
    let loopback = bound.ip().is_loopback();
    let server = Arc::new(server);
    let workers: Vec<_> = (0..WORKERS)
        .map(|_| {
            let (server, session) = (Arc::clone(&server), Arc::clone(&session));
            std::thread::spawn(move || {
                for request in server.incoming_requests() {
                    answer(&session, request, loopback);
                }
            })
        })
        .collect();
    for w in workers {
        let _ = w.join();
    }
    Ok(())
}

/// Whether a request's `Host` header names this machine. A server on the
/// loopback address answers only such requests, so a web page elsewhere
/// cannot reach it through a DNS name rebound to 127.0.0.1.
pub fn local_host(host: Option<&str>) -> bool {
    let Some(host) = host else {
        return false;
    };
    let name = match host.rsplit_once(':') {
        Some((name, port)) if port.bytes().all(|b| b.is_ascii_digit()) => name,
        _ => host,
    };
    matches!(name.to_ascii_lowercase().as_str(), "127.0.0.1" | "localhost" | "[::1]")
}

fn answer(session: &Session, mut request: tiny_http::Request, loopback: bool) {
    let method = request.method().as_str().to_string();
    let url = request.url().to_string();
    let host = (request.headers().iter())
        .find(|h| h.field.equiv("Host"))
        .map(|h| h.value.as_str().to_string());
    let mut body = Vec::new();
    let read = request.as_reader().take(MAX_BODY_BYTES + 1).read_to_end(&mut body);
    let reply = match read {
        _ if loopback && !local_host(host.as_deref()) => {
            Reply::error(403, "this server answers requests for 127.0.0.1 or localhost only")
        }
        Err(e) => Reply::error(400, format!("cannot read the request body: {e}")),
        Ok(_) if body.len() as u64 > MAX_BODY_BYTES => {
            Reply::error(413, format!("the request body is larger than {MAX_BODY_BYTES} bytes"))
        }
        // A bug in one handler answers 500 and keeps the worker serving.
        Ok(_) => std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| route(session, &method, &url, &body)))
            .unwrap_or_else(|_| Reply::error(500, format!("{method} {url}: internal error (see the server's log)"))),
    };
    let mut response = tiny_http::Response::from_data(reply.body).with_status_code(reply.status);
    for (name, value) in [("Content-Type", reply.content_type), ("Cache-Control", "no-store")] {
        if let Ok(h) = tiny_http::Header::from_bytes(name.as_bytes(), value.as_bytes()) {
            response.add_header(h);
        }
    }
    // A client that went away needs no answer.
    let _ = request.respond(response);
}

#[cfg(test)]
mod tests {
    use super::{local_host, preview_stem};

    #[test]
    fn preview_paths_name_one_stem() {
        assert_eq!(preview_stem("/api/frames/000012/preview.png"), Some("000012"));
        for bad in [
            "/api/frames/preview.png",
            "/api/frames//preview.png",
            "/api/frames/a/b/preview.png",
        ] {
            assert_eq!(preview_stem(bad), None, "{bad}");
        }
    }

    #[test]
    fn only_local_host_names_are_answered_on_loopback() {
        for ok in ["127.0.0.1:8080", "localhost:1", "LOCALHOST", "[::1]:9000"] {
            assert!(local_host(Some(ok)), "{ok}");
        }
        for bad in ["evil.example:8080", "127.0.0.1.evil.example", "", "10.0.0.1:80"] {
            assert!(!local_host(Some(bad)), "{bad}");
        }
        assert!(!local_host(None));
    }
}
