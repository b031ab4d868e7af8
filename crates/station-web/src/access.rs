//! Who may use a station: a random token printed in the station's URL and required on every
//! `/api/*` call (the live channel included), a `Host` allowlist against DNS rebinding, and an
//! `Origin` check on state-changing requests against cross-site forms.
//!
//! | request | answer |
//! |---|---|
//! | `Host` missing or not allowed ([`Access::host_allowed`]) | 403 |
//! | not GET/HEAD with an `Origin` other than `http://` + its `Host` | 403 |
//! | a page (not `/api/*`) with `?token=` the token | 303 to the same page without it, setting the station's cookie |
//! | a page with `?token=` another token | 403 |
//! | `/api/*` without a token (station cookie, `X-Station-Token` header, `Authorization: Bearer`, `?token=`) | 401 |
//! | `/api/*` with another token | 403 |
//!
//! The token leaves the address bar at the first page load: the page printed as
//! `http://ADDR/?token=TOKEN` answers with a redirect to `http://ADDR/` and an `HttpOnly`,
//! `SameSite=Strict` cookie holding the token, which the browser then sends with every API call
//! and the event stream (so it is neither in the history nor visible to the page's scripts).
//! The cookie is named after the station's port ([`Access::cookie_name`]): cookies are not
//! kept apart by port, and two stations on one host must not overwrite each other's. The pages
//! themselves hold no data and need no token; programs use the header or `?token=`.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::middleware::Next;
use axum::response::Response;
use axum::Router;

/// The header the pages send the token in.
pub const TOKEN_HEADER: &str = "x-station-token";

/// A station's access rules: its token and the `Host` names it answers to.
pub struct Access {
    token: String,
    /// Compared instead of the token itself: `blake3::Hash` equality is constant-time.
    token_hash: blake3::Hash,
    bind: IpAddr,
    cookie_name: String,
}

impl std::fmt::Debug for Access {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Access")
            .field("bind", &self.bind)
            .finish_non_exhaustive()
    }
}

impl Access {
    /// A fresh random 128-bit token for a station bound to `bind`.
    pub fn generate(bind: SocketAddr) -> Self {
        let bytes: [u8; 16] = rand::random();
        let token: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        Self::with_token(bind, token)
    }

    /// Access with a given token (tests).
    pub fn with_token(bind: SocketAddr, token: String) -> Self {
        Self {
            token_hash: blake3::hash(token.as_bytes()),
            token,
            bind: bind.ip(),
            cookie_name: format!("usal_station_{}", bind.port()),
        }
    }

    /// The cookie the token is kept in once a page was opened with it: `usal_station_PORT`.
    pub fn cookie_name(&self) -> &str {
        &self.cookie_name
    }

    /// The token.
    pub fn token(&self) -> &str {
        &self.token
    }

    /// The URL to open: `http://ADDR/?token=TOKEN`.
    pub fn url(&self, addr: SocketAddr) -> String {
        format!("http://{addr}/?token={}", self.token)
    }

    /// Whether `presented` is the token, in constant time.
    pub fn token_matches(&self, presented: &str) -> bool {
        blake3::hash(presented.as_bytes()) == self.token_hash
    }

    /// Whether a `Host` header value (`name[:port]`) names this station: `localhost`,
    /// `127.0.0.1`, `[::1]` or the bound address; bound to every interface, any IP literal
    /// (DNS rebinding needs a name, an address cannot be rebound).
    pub fn host_allowed(&self, host: &str) -> bool {
        let name = strip_port(host);
        if name.eq_ignore_ascii_case("localhost") {
            return true;
        }
        let literal = name.trim_start_matches('[').trim_end_matches(']');
        match literal.parse::<IpAddr>() {
            Ok(ip) => ip.is_loopback() || ip == self.bind || self.bind.is_unspecified(),
            Err(_) => false,
        }
    }

    /// Wraps `router` so every request goes through these rules first.
    pub fn guard(self: Arc<Self>, router: Router) -> Router {
        router.layer(axum::middleware::from_fn_with_state(self, check))
    }
}

/// `host[:port]` without the port (IPv6 literals keep their brackets).
fn strip_port(host: &str) -> &str {
    if host.starts_with('[') {
        return match host.find(']') {
            Some(end) => &host[..=end],
            None => host,
        };
    }
    match host.rsplit_once(':') {
        Some((name, port)) if port.bytes().all(|b| b.is_ascii_digit()) => name,
        _ => host,
    }
}

/// The token a request presents: its header, bearer, the station's cookie (named `cookie`),
/// or its `token=` query parameter, in that order.
fn presented_token<'a>(
    headers: &'a HeaderMap,
    query: Option<&'a str>,
    cookie: &str,
) -> Option<&'a str> {
    if let Some(v) = headers.get(TOKEN_HEADER).and_then(|v| v.to_str().ok()) {
        return Some(v.trim());
    }
    if let Some(v) = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
    {
        return Some(v.trim());
    }
    let from_cookie = headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .find_map(|pair| {
            let (name, value) = pair.trim().split_once('=')?;
            (name == cookie).then_some(value)
        });
    from_cookie.or_else(|| query_token(query))
}

/// The `token=` parameter of a query string.
fn query_token(query: Option<&str>) -> Option<&str> {
    query?
        .split('&')
        .find_map(|pair| pair.strip_prefix("token="))
}

/// A page opened with the token in its URL: a redirect to the same page without it, setting
/// the station's cookie; with another token, 403.
fn token_to_cookie(access: &Access, uri: &axum::http::Uri, token: &str) -> Response {
    if !access.token_matches(token) {
        return crate::error(StatusCode::FORBIDDEN, "wrong station token");
    }
    let rest: Vec<&str> = uri
        .query()
        .unwrap_or_default()
        .split('&')
        .filter(|pair| !pair.is_empty() && !pair.starts_with("token="))
        .collect();
    let location = if rest.is_empty() {
        uri.path().to_owned()
    } else {
        format!("{}?{}", uri.path(), rest.join("&"))
    };
    let cookie = format!(
        "{}={}; Path=/; HttpOnly; SameSite=Strict",
        access.cookie_name, access.token
    );
    Response::builder()
        .status(StatusCode::SEE_OTHER)
        .header(header::LOCATION, location)
        .header(header::SET_COOKIE, cookie)
        .header(header::CACHE_CONTROL, "no-store")
        .body(axum::body::Body::empty())
        .unwrap_or_else(|_| crate::error(StatusCode::INTERNAL_SERVER_ERROR, "redirect"))
}

async fn check(State(access): State<Arc<Access>>, req: Request, next: Next) -> Response {
    let headers = req.headers();
    let host = headers.get(header::HOST).and_then(|v| v.to_str().ok());
    let Some(host) = host.filter(|h| access.host_allowed(h)) else {
        tracing::debug!("refused: Host {host:?}");
        return crate::error(StatusCode::FORBIDDEN, "this Host is not allowed");
    };
    let changes_state = !matches!(*req.method(), Method::GET | Method::HEAD);
    if changes_state {
        if let Some(origin) = headers.get(header::ORIGIN) {
            let same = origin
                .to_str()
                .ok()
                .and_then(|o| o.strip_prefix("http://"))
                .is_some_and(|o| o.eq_ignore_ascii_case(host));
            if !same {
                tracing::debug!("refused: Origin {origin:?} on Host {host}");
                return crate::error(StatusCode::FORBIDDEN, "cross-origin request refused");
            }
        }
    }
    if !req.uri().path().starts_with("/api/") {
        if let Some(token) = query_token(req.uri().query()) {
            return token_to_cookie(&access, req.uri(), token);
        }
    } else {
        match presented_token(headers, req.uri().query(), &access.cookie_name) {
            None => return crate::error(StatusCode::UNAUTHORIZED, "the station token is missing"),
            Some(t) if !access.token_matches(t) => {
                return crate::error(StatusCode::FORBIDDEN, "wrong station token");
            }
            Some(_) => {}
        }
    }
    next.run(req).await
}

#[cfg(test)]
mod tests {
    use super::*;

    fn access(bind: [u8; 4]) -> Access {
        Access::with_token(SocketAddr::from((bind, 8081)), "t0k".into())
    }

    /// A guarded router with the common routes of a fake station plus one POST route, served
    /// on a free loopback port.
    async fn served() -> (SocketAddr, tokio_util::sync::CancellationToken) {
        use axum::routing::post;
        struct Fake(crate::Live);
        impl crate::Station for Fake {
            const PAGE: &'static str = "<p>page</p>";
            fn snapshot_json(&self) -> String {
                "{}".into()
            }
            fn live(&self) -> &crate::Live {
                &self.0
            }
        }
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let shared = Arc::new(Fake(crate::Live::default()));
        let cancel = shared.0.cancel.clone();
        let router = crate::routes::<Fake>()
            .route("/api/poke", post(|| async { StatusCode::NO_CONTENT }))
            .with_state(shared);
        let access = Arc::new(Access::with_token(addr, "s3cret".into()));
        tokio::spawn(crate::serve(listener, access.guard(router), cancel.clone()));
        (addr, cancel)
    }

    /// Sends `head` (request line and headers, without the final blank line); the status code
    /// and the answer's headers (names in lowercase).
    async fn answer(addr: SocketAddr, head: &str) -> (u16, Vec<(String, String)>) {
        use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
        let work = async {
            let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
            s.write_all(format!("{head}\r\nContent-Length: 0\r\n\r\n").as_bytes())
                .await
                .unwrap();
            let mut lines = BufReader::new(s).lines();
            let first = lines.next_line().await.unwrap().unwrap_or_default();
            let code = first.split_whitespace().nth(1).unwrap().parse().unwrap();
            let mut headers = Vec::new();
            while let Some(l) = lines.next_line().await.unwrap() {
                let Some((name, value)) = l.split_once(':') else {
                    break;
                };
                headers.push((name.to_ascii_lowercase(), value.trim().to_owned()));
            }
            (code, headers)
        };
        tokio::time::timeout(std::time::Duration::from_secs(10), work)
            .await
            .expect("answer in time")
    }

    /// The status code and whether the answer is an event stream.
    async fn status(addr: SocketAddr, head: &str) -> (u16, bool) {
        let (code, headers) = answer(addr, head).await;
        let sse = headers
            .iter()
            .any(|(n, v)| n == "content-type" && v == "text/event-stream");
        (code, sse)
    }

    #[tokio::test]
    async fn api_calls_need_the_token_a_local_host_and_a_same_origin() {
        let (addr, cancel) = served().await;
        let host = format!("Host: {addr}");
        let get = |path: &str, extra: &str| format!("GET {path} HTTP/1.1\r\n{host}{extra}");
        // The page needs no token; the API does.
        assert_eq!(status(addr, &get("/", "")).await.0, 200);
        assert_eq!(status(addr, &get("/api/state", "")).await.0, 401);
        assert_eq!(status(addr, &get("/api/state?token=nope", "")).await.0, 403);
        assert_eq!(
            status(addr, &get("/api/state?token=s3cret", "")).await.0,
            200
        );
        let header = "\r\nX-Station-Token: s3cret";
        assert_eq!(status(addr, &get("/api/state", header)).await.0, 200);
        let bearer = "\r\nAuthorization: Bearer s3cret";
        assert_eq!(status(addr, &get("/api/state", bearer)).await.0, 200);
        // The event stream likewise.
        assert_eq!(status(addr, &get("/api/events", "")).await, (401, false));
        assert_eq!(
            status(addr, &get("/api/events?token=s3cret", "")).await,
            (200, true)
        );
        // A rebound name, or none at all: refused even with the token.
        let rebound = "GET /api/state?token=s3cret HTTP/1.1\r\nHost: evil.example";
        assert_eq!(status(addr, rebound).await.0, 403);
        let no_host = "GET /api/state?token=s3cret HTTP/1.1\r\nX-A: b";
        assert_eq!(status(addr, no_host).await.0, 403);
        // State changes: cross-origin refused, same origin (or none, a script) accepted.
        let poke = |origin: &str| {
            format!("POST /api/poke HTTP/1.1\r\n{host}\r\nX-Station-Token: s3cret{origin}")
        };
        assert_eq!(
            status(addr, &poke("\r\nOrigin: http://evil.example"))
                .await
                .0,
            403
        );
        assert_eq!(status(addr, &poke("\r\nOrigin: null")).await.0, 403);
        let same = format!("\r\nOrigin: http://{addr}");
        assert_eq!(status(addr, &poke(&same)).await.0, 204);
        assert_eq!(status(addr, &poke("")).await.0, 204);
        let untokened = format!("POST /api/poke HTTP/1.1\r\n{host}{same}");
        assert_eq!(status(addr, &untokened).await.0, 401);
        cancel.cancel();
    }

    #[tokio::test]
    async fn a_page_opened_with_the_token_drops_it_from_the_url_for_a_private_cookie() {
        let (addr, cancel) = served().await;
        let host = format!("Host: {addr}");
        let get = |path: &str, extra: &str| format!("GET {path} HTTP/1.1\r\n{host}{extra}");
        let header = |headers: &[(String, String)], name: &str| {
            headers
                .iter()
                .find(|(n, _)| n == name)
                .map(|(_, v)| v.clone())
        };
        // The URL the station prints: answered by the page without the token, and a cookie.
        let (code, headers) = answer(addr, &get("/?token=s3cret", "")).await;
        assert_eq!(code, 303);
        assert_eq!(header(&headers, "location").as_deref(), Some("/"));
        let cookie = header(&headers, "set-cookie").expect("a cookie");
        let name = format!("usal_station_{}", addr.port());
        assert!(cookie.starts_with(&format!("{name}=s3cret;")), "{cookie}");
        for attribute in ["HttpOnly", "SameSite=Strict", "Path=/"] {
            assert!(cookie.contains(attribute), "{attribute} in {cookie}");
        }
        // Other parameters stay; a wrong token is refused, not turned into a cookie.
        let (code, headers) = answer(addr, &get("/fleet?a=1&token=s3cret&b=2", "")).await;
        assert_eq!(code, 303);
        assert_eq!(
            header(&headers, "location").as_deref(),
            Some("/fleet?a=1&b=2")
        );
        let (code, headers) = answer(addr, &get("/?token=nope", "")).await;
        assert_eq!(code, 403);
        assert_eq!(header(&headers, "set-cookie"), None);
        // The cookie opens the API and the event stream; another station's cookie does not.
        let jar = format!("\r\nCookie: other=1; {name}=s3cret");
        assert_eq!(status(addr, &get("/api/state", &jar)).await.0, 200);
        assert_eq!(status(addr, &get("/api/events", &jar)).await, (200, true));
        let wrong = format!("\r\nCookie: {name}=nope");
        assert_eq!(status(addr, &get("/api/state", &wrong)).await.0, 403);
        let elsewhere = "\r\nCookie: usal_station_1=s3cret";
        assert_eq!(status(addr, &get("/api/state", elsewhere)).await.0, 401);
        cancel.cancel();
    }

    #[test]
    fn hosts_allowed_are_loopback_names_and_the_bound_address() {
        let a = access([127, 0, 0, 1]);
        for ok in [
            "127.0.0.1:8081",
            "localhost:1",
            "LOCALHOST",
            "[::1]:80",
            "127.0.0.1",
        ] {
            assert!(a.host_allowed(ok), "{ok}");
        }
        for bad in [
            "evil.example:8081",
            "10.0.0.5:8081",
            "localhost.evil:1",
            "",
            "[::2]:1",
        ] {
            assert!(!a.host_allowed(bad), "{bad}");
        }
        let lan = access([10, 0, 0, 5]);
        assert!(lan.host_allowed("10.0.0.5:8081") && !lan.host_allowed("10.0.0.6:8081"));
        let any = access([0, 0, 0, 0]);
        assert!(any.host_allowed("192.168.1.9:8081") && !any.host_allowed("rebind.example"));
    }

    #[test]
    fn tokens_are_random_128_bit_hex_and_compared_whole() {
        let a = Access::generate(SocketAddr::from(([127, 0, 0, 1], 9)));
        let b = Access::generate(SocketAddr::from(([127, 0, 0, 1], 9)));
        assert_eq!(a.token().len(), 32);
        assert!(a.token().bytes().all(|c| c.is_ascii_hexdigit()));
        assert_ne!(a.token(), b.token());
        assert!(a.token_matches(a.token()));
        assert!(!a.token_matches(&a.token()[..31]) && !a.token_matches(""));
        let addr: SocketAddr = "127.0.0.1:9".parse().unwrap();
        assert_eq!(
            a.url(addr),
            format!("http://127.0.0.1:9/?token={}", a.token())
        );
    }

    #[test]
    fn the_token_is_read_from_header_bearer_cookie_or_query() {
        let mut h = HeaderMap::new();
        let c = "usal_station_9";
        assert_eq!(presented_token(&h, Some("a=1&token=x"), c), Some("x"));
        assert_eq!(presented_token(&h, Some("a=1"), c), None);
        h.insert(
            header::COOKIE,
            "usal_station_99=v; usal_station_9=w".parse().unwrap(),
        );
        assert_eq!(presented_token(&h, Some("token=x"), c), Some("w"));
        h.insert(header::AUTHORIZATION, "Bearer y".parse().unwrap());
        assert_eq!(presented_token(&h, None, c), Some("y"));
        h.insert(TOKEN_HEADER, "z".parse().unwrap());
        assert_eq!(presented_token(&h, Some("token=x"), c), Some("z"));
    }
}
