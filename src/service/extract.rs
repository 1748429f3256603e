//! Extractors whose rejections are problem documents: `ApiJson`, `ApiQuery` and `ApiPath`
//! replace axum's `Json`, `Query` and `Path`, whose rejections are plain text.
//!
//! Deserialising through `serde_path_to_error` tells which field failed (`frames.step`,
//! `accel`), which goes into the problem's `field` member; for JSON the line and column go
//! into `line` and `column`.

use axum::extract::rejection::BytesRejection;
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, StatusCode};
use bytes::Bytes;
use serde::de::DeserializeOwned;

use super::error::ApiError;

/// A JSON body (`Content-Type: application/json` or `…+json`), deserialised into `T`.
/// Bodies are read under axum's default limit (2 MiB): JSON bodies here are options, never
/// bulk data.
#[derive(Debug, Clone)]
pub struct ApiJson<T>(pub T);

impl<T, S> FromRequest<S> for ApiJson<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, ApiError> {
        check_json_content_type(req.headers())?;
        let bytes = Bytes::from_request(req, state)
            .await
            .map_err(bytes_rejection)?;
        parse_json(&bytes).map(ApiJson)
    }
}

/// Refuses a body that does not say it is JSON, with 415.
fn check_json_content_type(headers: &HeaderMap) -> Result<(), ApiError> {
    let accepted = ["application/json"];
    let Some(ct) = headers.get(header::CONTENT_TYPE) else {
        return Err(ApiError::unsupported_media_type(
            "this route takes a JSON body: send `Content-Type: application/json`",
            &accepted,
        ));
    };
    let essence = ct
        .to_str()
        .ok()
        .and_then(|s| s.split(';').next())
        .map(|s| s.trim().to_ascii_lowercase());
    match essence {
        Some(e)
            if e == "application/json"
                || (e.starts_with("application/") && e.ends_with("+json")) =>
        {
            Ok(())
        }
        _ => Err(ApiError::unsupported_media_type(
            format!(
                "this route takes a JSON body, not `{}`",
                String::from_utf8_lossy(ct.as_bytes())
            ),
            &accepted,
        )),
    }
}

/// Maps a failure to read the body: over the default limit is 413, anything else 400.
fn bytes_rejection(r: BytesRejection) -> ApiError {
    if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::payload_too_large(
            "a JSON body may be at most 2 MiB (2097152 bytes)",
            2 * 1024 * 1024,
        )
    } else if let Some(why) = super::body::timeout_cause(&r) {
        ApiError::request_timeout(format!("the request body was cut off: {why}"))
    } else {
        ApiError::bad_request(format!(
            "the request body could not be read: {}",
            r.body_text()
        ))
    }
}

/// Deserialises a JSON document into `T`, naming the field and place of the first error.
/// Every body this API takes is an object: serde would also fill a struct from an array,
/// field by field in order, which no schema here allows.
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    if let Some(&first) = bytes.iter().find(|b| !b.is_ascii_whitespace()) {
        if first != b'{' {
            return Err(ApiError::bad_request(
                "the JSON body must be an object (`{ … }`)",
            ));
        }
    }
    let de = &mut serde_json::Deserializer::from_slice(bytes);
    let value: T = serde_path_to_error::deserialize(&mut *de).map_err(|e| {
        let inner = e.inner().to_string();
        let field = field_of(&e.path().to_string(), &inner);
        if e.inner().classify() == serde_json::error::Category::Data
            && names_no_version(field.as_deref(), &inner)
        {
            return no_such_version(&inner);
        }
        json_error(e.inner(), field)
    })?;
    // Characters after the document are an error too.
    de.end().map_err(|e| json_error(&e, None))?;
    Ok(value)
}

/// The 400 for a JSON error, with its place.
fn json_error(inner: &serde_json::Error, field: Option<String>) -> ApiError {
    let what = match inner.classify() {
        serde_json::error::Category::Syntax | serde_json::error::Category::Eof => {
            "the body is not valid JSON"
        }
        _ => "the JSON body does not match this route's schema",
    };
    let mut err = ApiError::bad_request(match &field {
        Some(f) => format!("{what}: {f}: {inner}"),
        None => format!("{what}: {inner}"),
    })
    .with("line", inner.line())
    .with("column", inner.column());
    if let Some(f) = field {
        err = err.with_field(f);
    }
    err
}

/// A query string deserialised into `T` (`serde_urlencoded`), naming the parameter that
/// failed.
#[derive(Debug, Clone)]
pub struct ApiQuery<T>(pub T);

impl<T, S> FromRequestParts<S> for ApiQuery<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, ApiError> {
        parse_query(parts.uri.query().unwrap_or("")).map(ApiQuery)
    }
}

/// The first parameter of `query` whose name or value is not UTF-8 once percent-decoded
/// (`form_urlencoded` would replace such bytes with U+FFFD, and a name would be stored
/// changed): its name, as far as it decodes. (`+` stands for a space, which changes no
/// byte's validity, so only the key it names is spelled with it.)
fn non_utf8_parameter(query: &str) -> Option<String> {
    use percent_encoding::percent_decode_str;
    query.split('&').filter(|p| !p.is_empty()).find_map(|pair| {
        let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
        let key = percent_decode_str(k);
        (key.clone().decode_utf8().is_err() || percent_decode_str(v).decode_utf8().is_err())
            .then(|| key.decode_utf8_lossy().replace('+', " "))
    })
}

/// Deserialises a query string into `T`, naming the parameter of the first error.
pub fn parse_query<T: DeserializeOwned>(query: &str) -> Result<T, ApiError> {
    if let Some(name) = non_utf8_parameter(query) {
        return Err(ApiError::bad_request(format!(
            "query parameter `{name}` is not UTF-8 once percent-decoded"
        ))
        .with_field(name));
    }
    let de = serde_urlencoded::Deserializer::new(form_urlencoded::parse(query.as_bytes()));
    serde_path_to_error::deserialize(de).map_err(|e| {
        let inner = e.inner().to_string();
        let field = field_of(&e.path().to_string(), &inner);
        if names_no_version(field.as_deref(), &inner) {
            return no_such_version(&inner);
        }
        let mut err = ApiError::bad_request(match &field {
            Some(f) => format!("query parameter `{f}`: {inner}"),
            None => format!("the query string is not valid: {inner}"),
        });
        if let Some(f) = field {
            err = err.with_field(f);
        }
        err
    })
}

/// Whether a parameter or body field that failed to deserialise is a `version` of a form
/// no version has (`-1`, `abc`, `1.5`, past u32): a version is an id, and an id that names
/// nothing is 404 whatever its form (contract §5). A `version` given twice stays a
/// malformed request.
fn names_no_version(field: Option<&str>, message: &str) -> bool {
    field == Some("version") && !message.starts_with("duplicate field")
}

/// The 404 of a `version` of a form no version has.
fn no_such_version(why: &str) -> ApiError {
    ApiError::not_found(format!("the version names no version of the scene: {why}"))
        .with_field("version")
}

/// Path parameters deserialised into `T`. A path that does not parse names nothing, so it
/// is 404 (contract: any id that names nothing is 404, whatever its form).
#[derive(Debug, Clone)]
pub struct ApiPath<T>(pub T);

impl<T, S> FromRequestParts<S> for ApiPath<T>
where
    T: DeserializeOwned + Send,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        match axum::extract::Path::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Path(v)) => Ok(ApiPath(v)),
            Err(e) => Err(ApiError::not_found(format!(
                "{} names nothing: {}",
                parts.uri.path(),
                e.body_text()
            ))),
        }
    }
}

/// The field an error is about: the deserialiser's path, extended by the name serde puts
/// in backticks for unknown and missing fields (their path is the enclosing object).
fn field_of(path: &str, message: &str) -> Option<String> {
    // `?` is where serde_path_to_error could not tell (a syntax error mid-object): the
    // line and column say where instead.
    let base = if path == "." || path == "?" || path.is_empty() {
        None
    } else {
        Some(path.to_owned())
    };
    let named = ["unknown field `", "missing field `", "duplicate field `"]
        .iter()
        .find_map(|p| message.strip_prefix(p))
        .and_then(|rest| rest.split('`').next())
        .map(str::to_owned);
    match (base, named) {
        // An unknown field's path already ends with it; a missing one's is its parent.
        (Some(b), Some(n)) if b == n || b.ends_with(&format!(".{n}")) => Some(b),
        (Some(b), Some(n)) => Some(format!("{b}.{n}")),
        (None, Some(n)) => Some(n),
        (b, None) => b,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(serde::Deserialize, Debug)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Frames {
        start: f64,
        end: f64,
    }

    #[derive(serde::Deserialize, Debug)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Body {
        width: u32,
        frames: Option<Frames>,
    }

    #[test]
    fn a_version_of_no_version_s_form_is_404_and_other_errors_400() {
        #[derive(Debug, serde::Deserialize)]
        #[serde(deny_unknown_fields)]
        #[allow(dead_code)]
        struct V {
            version: Option<u32>,
            width: Option<u32>,
        }
        for q in [
            "version=-1",
            "version=abc",
            "version=1.0",
            "version=4294967296",
            "version=",
        ] {
            let e = parse_query::<V>(q).unwrap_err();
            assert_eq!(
                (e.status().as_u16(), &e.extensions()["field"]),
                (404, &serde_json::json!("version")),
                "{q}"
            );
        }
        for q in ["version=1&version=2", "width=-1"] {
            assert_eq!(
                parse_query::<V>(q).unwrap_err().status().as_u16(),
                400,
                "{q}"
            );
        }
        for b in [
            r#"{"version": -1}"#,
            r#"{"version": "2"}"#,
            r#"{"version": 1.5}"#,
        ] {
            assert_eq!(
                parse_json::<V>(b.as_bytes()).unwrap_err().status().as_u16(),
                404,
                "{b}"
            );
        }
        for b in [
            r#"{"version": 1, "version": 2}"#,
            r#"{"version": 1x}"#,
            r#"{"width": -1}"#,
        ] {
            assert_eq!(
                parse_json::<V>(b.as_bytes()).unwrap_err().status().as_u16(),
                400,
                "{b}"
            );
        }
    }

    #[test]
    fn json_errors_name_the_field() {
        let e = parse_json::<Body>(br#"{"width": "wide"}"#).unwrap_err();
        assert_eq!(e.extensions()["field"], "width");
        let e = parse_json::<Body>(br#"{"width": 3, "frames": {"start": 0}}"#).unwrap_err();
        assert_eq!(e.extensions()["field"], "frames.end");
        let e = parse_json::<Body>(br#"{"width": 3, "colour": 1}"#).unwrap_err();
        assert_eq!(e.extensions()["field"], "colour");
        let e = parse_json::<Body>(b"{\"width\": 3,\n  oops}").unwrap_err();
        assert_eq!(e.extensions()["line"], 2);
        assert!(e.detail().contains("not valid JSON"), "{}", e.detail());
        let e = parse_json::<Body>(br#"{"width": 3} {}"#).unwrap_err();
        assert!(e.detail().contains("trailing"), "{}", e.detail());
        // A key given twice names it; a syntax error mid-object names no field.
        let e = parse_json::<Body>(br#"{"width": 3, "width": 4}"#).unwrap_err();
        assert_eq!(e.extensions()["field"], "width");
        let e = parse_json::<Body>(b" [3, null]").unwrap_err();
        assert!(e.detail().contains("must be an object"), "{}", e.detail());
        let e = parse_json::<Body>(br#"{"width": 3,}"#).unwrap_err();
        assert!(
            e.extensions().get("field").is_none(),
            "{:?}",
            e.extensions()
        );
        assert_eq!(e.extensions()["column"], 13);
        assert_eq!(parse_json::<Body>(br#"{"width": 3}"#).unwrap().width, 3);
    }

    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct Q {
        limit: Option<u32>,
    }

    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct N {
        name: Option<String>,
    }

    #[test]
    fn query_errors_name_the_parameter() {
        let e = parse_query::<Q>("limit=lots").unwrap_err();
        assert_eq!(e.extensions()["field"], "limit");
        let e = parse_query::<Q>("limit=1&limit=2").unwrap_err();
        assert_eq!(e.extensions()["field"], "limit");
        // Bytes that are not UTF-8 are refused, not replaced; encoded UTF-8 passes.
        let e = parse_query::<N>("name=%FF%FE").unwrap_err();
        assert_eq!(e.extensions()["field"], "name");
        assert_eq!(
            parse_query::<N>("name=caf%C3%A9+x")
                .unwrap()
                .name
                .as_deref(),
            Some("café x")
        );
        assert_eq!(
            parse_query::<N>("name=100%").unwrap().name.as_deref(),
            Some("100%")
        );
        assert_eq!(parse_query::<Q>("limit=7").unwrap().limit, Some(7));
        assert_eq!(parse_query::<Q>("").unwrap().limit, None);
    }
}
