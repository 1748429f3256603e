//! The HTTP side of callbacks (`proto/service.md`, "Callbacks"): which URLs may be called
//! back (`--callback-allow`), how a POST is signed (`--callback-secret-file`) and made.
//!
//! Each attempt opens one HTTP/1.1 connection with hyper's client, sends one POST and reads
//! the status; it never follows a redirect (a 3xx is a failed delivery), and the whole
//! attempt (resolving, connecting, sending, the answer's head) has `--callback-timeout`
//! seconds. Only `http://` URLs whose host and port are on the allow-list are accepted:
//! the list, not the client, decides whom the server talks to, which keeps a job's
//! submitter from using the server to reach other hosts of its network. TLS to a receiver
//! is a proxy's job, as it is for clients (put the proxy on the list).

use std::path::Path;
use std::time::Duration;

use hmac::{KeyInit, Mac};
use http::Uri;
use http_body_util::Full;

use crate::app::{CallbackFailure, CallbackSender, SendFuture};

/// The header with the signature: `sha256=` and the lowercase hex HMAC-SHA256, under the
/// secret, of the timestamp header's value, a `.`, and the body.
pub const SIGNATURE_HEADER: &str = "rayd-signature";
/// The header with the attempt's time in whole seconds since the Unix epoch; signed with
/// the body, so a receiver that refuses old timestamps refuses replays.
pub const TIMESTAMP_HEADER: &str = "rayd-timestamp";
/// The header naming the job, for receivers that deduplicate (delivery is at least once).
pub const JOB_HEADER: &str = "rayd-job";

/// The longest callback URL accepted.
const MAX_URL: usize = 2048;

/// Why the callback options cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum CallbackError {
    /// An allow-list entry is not `host` or `host:port`.
    #[error("--callback-allow entry {entry:?}: {reason}")]
    BadEntry {
        /// The entry.
        entry: String,
        /// What is wrong.
        reason: &'static str,
    },
    /// Hosts are allowed but there is no key to sign with.
    #[error("--callback-allow needs --callback-secret-file: every callback is signed")]
    NoSecret,
    /// The secret file cannot be read or holds no secret.
    #[error("--callback-secret-file {path}: {reason}")]
    Secret {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
}

/// One allowed receiver: a lowercase host name or IP literal and a port.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Allowed {
    host: String,
    port: u16,
}

/// The service's [`CallbackSender`].
pub struct CallbackClient {
    allow: Vec<Allowed>,
    secret: Vec<u8>,
    timeout: Duration,
    attempts: u32,
}

impl std::fmt::Debug for CallbackClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CallbackClient")
            .field("allow", &self.allow)
            .field("timeout", &self.timeout)
            .field("attempts", &self.attempts)
            .finish_non_exhaustive()
    }
}

/// A callback URL taken apart.
struct Target {
    host: String,
    port: u16,
    path: String,
    authority: String,
}

/// Splits `host[:port]` (an IPv6 literal in brackets) into a lowercase host and a port,
/// 80 when absent.
fn host_port(s: &str) -> Option<(String, u16)> {
    let (host, port) = if let Some(rest) = s.strip_prefix('[') {
        let (h, after) = rest.split_once(']')?;
        let port = match after.strip_prefix(':') {
            Some(p) => Some(p),
            None if after.is_empty() => None,
            None => return None,
        };
        (format!("[{}]", h.to_ascii_lowercase()), port)
    } else {
        match s.rsplit_once(':') {
            Some((h, p)) => (h.to_ascii_lowercase(), Some(p)),
            None => (s.to_ascii_lowercase(), None),
        }
    };
    let port = match port {
        Some(p) => p.parse::<u16>().ok().filter(|p| *p > 0)?,
        None => 80,
    };
    let ok = |b: u8| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'-' | b'[' | b']' | b':');
    (!host.is_empty() && host.bytes().all(ok)).then_some((host, port))
}

impl CallbackClient {
    /// The client for `--callback-allow` entries (`host` means port 80), the secret in
    /// `secret_file` (its bytes, surrounding whitespace trimmed), `attempts` in all and a
    /// per-attempt `timeout`. `Ok(None)` when no host is allowed: callbacks are off.
    pub fn from_options(
        allow: &[String],
        secret_file: Option<&Path>,
        attempts: u32,
        timeout: Duration,
    ) -> Result<Option<CallbackClient>, CallbackError> {
        let mut list = Vec::new();
        for entry in allow.iter().map(|e| e.trim()).filter(|e| !e.is_empty()) {
            if entry.contains('/') || entry.contains('@') {
                return Err(CallbackError::BadEntry {
                    entry: entry.into(),
                    reason: "give host or host:port, without a scheme, path or user",
                });
            }
            let (host, port) = host_port(entry).ok_or_else(|| CallbackError::BadEntry {
                entry: entry.into(),
                reason: "not a host name or IP address with an optional port 1-65535",
            })?;
            list.push(Allowed { host, port });
        }
        if list.is_empty() {
            return Ok(None);
        }
        let path = secret_file.ok_or(CallbackError::NoSecret)?;
        let secret_err = |reason: String| CallbackError::Secret {
            path: path.display().to_string(),
            reason,
        };
        let bytes = std::fs::read(path).map_err(|e| secret_err(e.to_string()))?;
        let secret = bytes.trim_ascii().to_vec();
        if secret.len() < 16 {
            return Err(secret_err(format!(
                "holds {} bytes; a secret needs at least 16",
                secret.len()
            )));
        }
        Ok(Some(CallbackClient {
            allow: list,
            secret,
            timeout,
            attempts: attempts.max(1),
        }))
    }

    fn target(&self, url: &str) -> Result<Target, String> {
        if url.len() > MAX_URL {
            return Err(format!("is longer than {MAX_URL} bytes"));
        }
        let uri: Uri = url
            .parse()
            .map_err(|e| format!("{url:?} is not a URL: {e}"))?;
        match uri.scheme_str() {
            Some("http") => {}
            Some(other) => {
                return Err(format!(
                    "{url:?}: only http:// callbacks are sent, not {other}:// (TLS is a \
                     proxy's job: allow the proxy)"
                ))
            }
            None => return Err(format!("{url:?} is not an absolute http:// URL")),
        }
        let authority = uri
            .authority()
            .ok_or_else(|| format!("{url:?} has no host"))?
            .as_str()
            .to_string();
        if authority.contains('@') {
            return Err(format!("{url:?}: user information is not allowed"));
        }
        let (host, port) =
            host_port(&authority).ok_or_else(|| format!("{url:?}: bad host or port"))?;
        let path = uri
            .path_and_query()
            .map_or("/".to_string(), |p| p.as_str().to_string());
        Ok(Target {
            host,
            port,
            path,
            authority,
        })
    }

    /// The signature header's value for `body` sent at `timestamp`.
    pub fn sign(&self, timestamp: &str, body: &[u8]) -> String {
        signature(&self.secret, timestamp, body)
    }
}

/// `sha256=<hex>` of HMAC-SHA256 under `secret` over `timestamp`, `.`, `body`: what a
/// receiver recomputes to check a callback.
pub fn signature(secret: &[u8], timestamp: &str, body: &[u8]) -> String {
    let mut mac =
        hmac::Hmac::<sha2::Sha256>::new_from_slice(secret).expect("HMAC takes keys of any length");
    mac.update(timestamp.as_bytes());
    mac.update(b".");
    mac.update(body);
    let tag = mac.finalize().into_bytes();
    let mut out = String::with_capacity(7 + 64);
    out.push_str("sha256=");
    for b in tag.iter() {
        out.push_str(&format!("{b:02x}"));
    }
    out
}

fn retry(detail: String) -> CallbackFailure {
    CallbackFailure {
        retry: true,
        detail,
    }
}

impl CallbackSender for CallbackClient {
    fn check(&self, url: &str) -> Result<(), String> {
        let t = self.target(url)?;
        if self
            .allow
            .iter()
            .any(|a| a.host == t.host && a.port == t.port)
        {
            Ok(())
        } else {
            Err(format!(
                "{}:{} is not on this server's --callback-allow list",
                t.host, t.port
            ))
        }
    }

    fn attempts(&self) -> u32 {
        self.attempts
    }

    fn send(&self, url: &str, job: &str, body: Vec<u8>) -> SendFuture {
        let target = match self.check(url).and_then(|()| self.target(url)) {
            Ok(t) => t,
            Err(detail) => {
                return Box::pin(async move {
                    Err(CallbackFailure {
                        retry: false,
                        detail,
                    })
                })
            }
        };
        let timestamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs())
            .to_string();
        let signature = self.sign(&timestamp, &body);
        let (timeout, job) = (self.timeout, job.to_string());
        Box::pin(async move {
            let attempt = post(target, timestamp, signature, job, body);
            match tokio::time::timeout(timeout, attempt).await {
                Ok(r) => r,
                Err(_) => Err(retry(format!(
                    "no answer within {} s",
                    timeout.as_secs_f64()
                ))),
            }
        })
    }
}

/// One POST on a fresh connection; the status decides.
async fn post(
    t: Target,
    timestamp: String,
    signature: String,
    job: String,
    body: Vec<u8>,
) -> Result<(), CallbackFailure> {
    let host = t.host.trim_start_matches('[').trim_end_matches(']');
    let stream = tokio::net::TcpStream::connect((host, t.port))
        .await
        .map_err(|e| retry(format!("cannot connect to {}: {e}", t.authority)))?;
    let (mut sender, conn) =
        hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream))
            .await
            .map_err(|e| retry(format!("HTTP handshake with {} failed: {e}", t.authority)))?;
    // The connection is driven beside the request and ends with it.
    tokio::spawn(async move {
        let _ = conn.await;
    });
    let request = http::Request::post(t.path.as_str())
        .header(http::header::HOST, t.authority.as_str())
        .header(http::header::CONTENT_TYPE, "application/json")
        .header(
            http::header::USER_AGENT,
            concat!("rayd/", env!("CARGO_PKG_VERSION")),
        )
        .header(TIMESTAMP_HEADER, timestamp)
        .header(SIGNATURE_HEADER, signature)
        .header(JOB_HEADER, job)
        .body(Full::new(bytes::Bytes::from(body)))
        .map_err(|e| CallbackFailure {
            retry: false,
            detail: format!("cannot build the request: {e}"),
        })?;
    let answer = sender
        .send_request(request)
        .await
        .map_err(|e| retry(format!("POST to {} failed: {e}", t.authority)))?;
    let status = answer.status();
    if status.is_success() {
        return Ok(());
    }
    let detail = if status.is_redirection() {
        let to = answer
            .headers()
            .get(http::header::LOCATION)
            .and_then(|l| l.to_str().ok())
            .unwrap_or("nowhere");
        format!("answered {status} to {to}: redirects are not followed")
    } else {
        format!("answered {status}")
    };
    let again = status.is_server_error()
        || status == http::StatusCode::REQUEST_TIMEOUT
        || status == http::StatusCode::TOO_MANY_REQUESTS;
    Err(CallbackFailure {
        retry: again,
        detail,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn client(allow: &[&str]) -> CallbackClient {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("secret");
        std::fs::write(&f, "  a secret of enough bytes\n").unwrap();
        let allow: Vec<String> = allow.iter().map(|s| s.to_string()).collect();
        CallbackClient::from_options(&allow, Some(&f), 3, Duration::from_secs(1))
            .unwrap()
            .unwrap()
    }

    #[test]
    fn only_listed_hosts_and_ports_are_allowed() {
        let c = client(&["hooks.example", "127.0.0.1:9000", "[::1]:81"]);
        assert!(c.check("http://hooks.example/done").is_ok());
        assert!(c.check("http://HOOKS.example:80/done?x=1").is_ok());
        assert!(
            c.check("http://hooks.example:8080/").is_err(),
            "a host entry is port 80"
        );
        assert!(c.check("http://127.0.0.1:9000/x").is_ok());
        assert!(c.check("http://127.0.0.1:9001/x").is_err());
        assert!(c.check("http://[::1]:81/").is_ok());
        assert!(c.check("http://evil.example/").is_err());
        assert!(c.check("http://hooks.example.evil.example/").is_err());
        let e = c.check("https://hooks.example/").unwrap_err();
        assert!(e.contains("only http://"), "{e}");
        assert!(c.check("http://user@hooks.example/").is_err());
        assert!(c.check("/relative").is_err());
        assert!(c
            .check(&format!("http://hooks.example/{}", "a".repeat(3000)))
            .is_err());
    }

    #[test]
    fn options_are_checked() {
        let none = CallbackClient::from_options(&[], None, 5, Duration::from_secs(1)).unwrap();
        assert!(none.is_none());
        assert!(matches!(
            CallbackClient::from_options(&["h".into()], None, 5, Duration::from_secs(1)),
            Err(CallbackError::NoSecret)
        ));
        for bad in ["http://h", "h:0", "h:99999", "a b", "u@h"] {
            assert!(
                matches!(
                    CallbackClient::from_options(&[bad.into()], None, 5, Duration::from_secs(1)),
                    Err(CallbackError::BadEntry { .. })
                ),
                "{bad}"
            );
        }
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("short");
        std::fs::write(&f, "short\n").unwrap();
        assert!(matches!(
            CallbackClient::from_options(&["h".into()], Some(&f), 5, Duration::from_secs(1)),
            Err(CallbackError::Secret { .. })
        ));
    }

    #[test]
    fn the_signature_covers_timestamp_and_body() {
        let c = client(&["h"]);
        let s = c.sign("1700000000", b"{\"id\":1}");
        assert_eq!(
            s,
            signature(b"a secret of enough bytes", "1700000000", b"{\"id\":1}")
        );
        assert!(s.starts_with("sha256=") && s.len() == 7 + 64);
        assert_ne!(s, c.sign("1700000001", b"{\"id\":1}"));
        assert_ne!(s, c.sign("1700000000", b"{\"id\":2}"));
        // The value Python's hmac module gives for the same key and signed bytes.
        assert_eq!(
            signature(b"Jefe", "1700000000", b"what do ya want for nothing?"),
            "sha256=1cdd0650c8be1cb0974b1788d458b1e781206cfef59b85faafc582d2e182c57e"
        );
    }
}
