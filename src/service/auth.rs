//! Bearer-token authentication of the `/v1` routes (`--token-file`; `proto/service.md`,
//! "Authentication").
//!
//! Tokens are compared in constant time and without saying which one matched: the server
//! keeps only SHA-256 digests of its tokens, hashes the presented token once, and compares
//! that digest with every stored digest with `subtle`, folding the answers without an early
//! exit. Hashing first makes every comparison the same length, so neither a token's bytes
//! nor its length can be learnt from timing. The file is read again on SIGHUP; a file that
//! no longer reads (or holds no token) keeps the old tokens, so a botched rotation never
//! locks everyone out or lets everyone in.

use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

use super::error::ApiError;

/// A problem with the token file.
#[derive(Debug, thiserror::Error)]
pub enum AuthError {
    /// The file cannot be read.
    #[error("token file {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A line is not a token.
    #[error("token file {path}, line {line}: {why}")]
    BadLine {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        why: &'static str,
    },
    /// The file holds no token: every request would be refused.
    #[error(
        "token file {path} holds no token (one a line; blank lines and # comments are ignored)"
    )]
    Empty {
        /// The file.
        path: PathBuf,
    },
}

type TokenDigest = [u8; 32];

/// The accepted tokens (or none: authentication off), shared by every request and
/// replaced whole on reload.
#[derive(Debug, Clone, Default)]
pub struct Auth {
    inner: Arc<AuthInner>,
}

#[derive(Debug, Default)]
struct AuthInner {
    file: Option<PathBuf>,
    digests: RwLock<Arc<Vec<TokenDigest>>>,
}

impl Auth {
    /// No authentication: every request is let through.
    pub fn disabled() -> Self {
        Auth::default()
    }

    /// Tokens from `file` (one a line; blank lines and lines starting with `#` ignored;
    /// surrounding whitespace trimmed).
    pub fn from_file(file: &Path) -> Result<Self, AuthError> {
        let digests = read_tokens(file)?;
        Ok(Auth {
            inner: Arc::new(AuthInner {
                file: Some(file.to_owned()),
                digests: RwLock::new(Arc::new(digests)),
            }),
        })
    }

    /// Whether a token is needed.
    pub fn enabled(&self) -> bool {
        self.inner.file.is_some()
    }

    /// Reads the token file again. On error the old tokens stay in force. Returns the
    /// number of tokens now accepted.
    pub fn reload(&self) -> Result<usize, AuthError> {
        let Some(file) = &self.inner.file else {
            return Ok(0);
        };
        let digests = read_tokens(file)?;
        let n = digests.len();
        *self
            .inner
            .digests
            .write()
            .unwrap_or_else(|poisoned| poisoned.into_inner()) = Arc::new(digests);
        Ok(n)
    }

    /// Whether `token` is one of the accepted tokens, in time independent of which one and
    /// of where it differs.
    pub fn accepts(&self, token: &[u8]) -> bool {
        let presented: TokenDigest = Sha256::digest(token).into();
        let digests = self
            .inner
            .digests
            .read()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .clone();
        let mut found = subtle::Choice::from(0u8);
        for d in digests.iter() {
            found |= d.ct_eq(&presented);
        }
        bool::from(found)
    }

    /// Checks a request's `Authorization` header.
    pub fn check(&self, authorization: Option<&[u8]>) -> Result<(), ApiError> {
        if !self.enabled() {
            return Ok(());
        }
        let Some(value) = authorization else {
            return Err(ApiError::unauthorized(
                "this route needs an `Authorization: Bearer TOKEN` header",
                false,
            )
            .with_field("Authorization"));
        };
        // RFC 9110: the scheme is case-insensitive; one or more spaces follow it.
        let token = value
            .split_at_checked(7)
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case(b"bearer "))
            .map(|(_, rest)| rest.trim_ascii())
            .filter(|t| !t.is_empty());
        let Some(token) = token else {
            return Err(ApiError::unauthorized(
                "the `Authorization` header must be `Bearer TOKEN`",
                false,
            )
            .with_field("Authorization"));
        };
        if self.accepts(token) {
            Ok(())
        } else {
            Err(
                ApiError::unauthorized("the bearer token is not one this server accepts", true)
                    .with_field("Authorization"),
            )
        }
    }
}

/// Parses a token file into digests.
fn read_tokens(path: &Path) -> Result<Vec<TokenDigest>, AuthError> {
    let text = std::fs::read_to_string(path).map_err(|source| AuthError::Read {
        path: path.to_owned(),
        source,
    })?;
    // A byte order mark, as editors on Windows write one, is not part of the first line.
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    let mut digests = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let t = line.trim();
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        let bad = |why| AuthError::BadLine {
            path: path.to_owned(),
            line: i + 1,
            why,
        };
        if t.chars().any(|c| c.is_whitespace()) {
            return Err(bad("a token cannot contain whitespace"));
        }
        if !t.chars().all(|c| c.is_ascii_graphic()) {
            return Err(bad("a token must be printable ASCII"));
        }
        digests.push(Sha256::digest(t.as_bytes()).into());
    }
    if digests.is_empty() {
        return Err(AuthError::Empty {
            path: path.to_owned(),
        });
    }
    Ok(digests)
}

/// Middleware of the `/v1` routes: 401 unless the request has an accepted token.
pub async fn require_token(State(auth): State<Auth>, req: Request, next: Next) -> Response {
    match auth.check(
        req.headers()
            .get(header::AUTHORIZATION)
            .map(|v| v.as_bytes()),
    ) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

/// Re-reads the token file on every SIGHUP until `shutdown`; a failed read is logged and
/// the old tokens stay.
#[cfg(unix)]
pub fn reload_on_sighup(auth: Auth, shutdown: super::Shutdown) -> std::io::Result<()> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut hup = signal(SignalKind::hangup())?;
    tokio::spawn(async move {
        loop {
            tokio::select! {
                got = hup.recv() => if got.is_none() { break },
                () = shutdown.cancelled() => break,
            }
            match auth.reload() {
                Ok(n) => tracing::info!(tokens = n, "SIGHUP: token file read again"),
                Err(e) => tracing::error!(error = %e, "SIGHUP: keeping the old tokens"),
            }
        }
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_file_rules() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("tokens");
        std::fs::write(&f, "# ops\n\n  alpha  \nbeta\n").unwrap();
        let auth = Auth::from_file(&f).unwrap();
        assert!(auth.accepts(b"alpha"));
        assert!(auth.accepts(b"beta"));
        assert!(!auth.accepts(b"alph"));
        assert!(!auth.accepts(b"# ops"));
        assert!(!auth.accepts(b""));
        assert!(auth.check(Some(b"Bearer alpha")).is_ok());
        assert!(auth.check(Some(b"bearer   beta ")).is_ok());
        assert!(auth.check(Some(b"Basic alpha")).is_err());
        assert!(auth.check(Some(b"Bearer")).is_err());
        assert!(auth.check(None).is_err());

        std::fs::write(&f, "gamma\nbad token\n").unwrap();
        let e = auth.reload().unwrap_err();
        assert!(e.to_string().contains("line 2"), "{e}");
        assert!(
            auth.accepts(b"alpha"),
            "a failed reload keeps the old tokens"
        );
        std::fs::write(&f, "# nothing\n").unwrap();
        assert!(matches!(auth.reload(), Err(AuthError::Empty { .. })));
        std::fs::write(&f, "gamma\n").unwrap();
        assert_eq!(auth.reload().unwrap(), 1);
        assert!(auth.accepts(b"gamma") && !auth.accepts(b"alpha"));
        // A file saved with a byte order mark: the mark is not part of its first line,
        // a comment there stays a comment.
        std::fs::write(&f, "\u{feff}# ops\r\ndelta\r\n").unwrap();
        assert_eq!(auth.reload().unwrap(), 1);
        assert!(auth.accepts(b"delta"));
        std::fs::write(&f, "\u{feff}epsilon\n").unwrap();
        assert_eq!(auth.reload().unwrap(), 1);
        assert!(auth.accepts(b"epsilon"));
        assert!(Auth::disabled().check(None).is_ok());
    }
}
