//! The status page and scene thumbnails against a real `rayd serve` (`proto/service.md`,
//! "Status page"): `/` negotiates between the page and the JSON index, the page and its
//! assets carry the security headers and need no token, uploads take a `name`, and every
//! uploaded (and demo) scene gets a 160×120 PNG thumbnail without the upload waiting for it.
//! The page's behaviour in a browser is tests/browser (headless Chromium).

#[path = "common/server.rs"]
mod server;
use server::{scenes, Server};

/// The width and height of a PNG, from its IHDR chunk.
fn png_size(bytes: &[u8]) -> (u32, u32) {
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "a PNG signature");
    assert_eq!(&bytes[12..16], b"IHDR");
    let be = |o: usize| u32::from_be_bytes(bytes[o..o + 4].try_into().unwrap());
    (be(16), be(20))
}

const CHROMIUM_ACCEPT: &str =
    "text/html,application/xhtml+xml,application/xml;q=0.9,image/avif,image/webp,*/*;q=0.8";

#[test]
fn the_page_and_the_index() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, "page-token\n").unwrap();
    let s = Server::start(
        &dir.path().join("data"),
        &["--token-file", tokens.to_str().unwrap()],
    );

    let page = s.req("GET", "/", &[("Accept", CHROMIUM_ACCEPT)], &[]);
    assert_eq!(page.status, 200, "the page needs no token");
    assert_eq!(
        page.header("content-type"),
        Some("text/html; charset=utf-8")
    );
    assert_eq!(page.header("vary"), Some("Accept"));
    let csp = page.header("content-security-policy").unwrap();
    for directive in [
        "default-src 'self'",
        "script-src 'self'",
        "img-src 'self' blob: data:",
        "frame-ancestors 'none'",
    ] {
        assert!(csp.contains(directive), "{directive} in {csp}");
    }
    assert!(!csp.contains("unsafe"), "{csp}");
    assert_eq!(page.header("x-content-type-options"), Some("nosniff"));
    assert!(page.header("access-control-allow-origin").is_none());
    let html = String::from_utf8(page.body).unwrap();
    assert!(html.contains("<script type=\"module\" src=\"/page/app.js\">"));

    // API clients keep the JSON index, which says a token is needed.
    let index = s.req("GET", "/", &[], &[]);
    assert_eq!(index.status, 200);
    assert_eq!(index.json()["auth"], "bearer");
    let index = s.req("GET", "/", &[("Accept", "application/json")], &[]);
    assert_eq!(index.json()["api"], "/v1");

    for (path, ty) in [
        ("/page/app.js", "text/javascript; charset=utf-8"),
        ("/page/style.css", "text/css; charset=utf-8"),
    ] {
        let r = s.req("GET", path, &[("Origin", "http://elsewhere.example")], &[]);
        assert_eq!(r.status, 200, "{path} needs no token");
        assert_eq!(r.header("content-type"), Some(ty));
        assert!(r.header("content-security-policy").is_some());
        assert!(r.header("access-control-allow-origin").is_none());
    }
    // The thumbnail is data: it needs the token.
    assert_eq!(
        s.req(
            "GET",
            &format!("/v1/scenes/{}/thumbnail", "ab".repeat(32)),
            &[],
            &[]
        )
        .status,
        401
    );
    s.stop();
}

#[test]
fn thumbnails_of_uploads_and_demo_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let s = Server::start(&data, &["--demo"]);
    let index = s.req("GET", "/", &[], &[]).json();
    assert_eq!(index["auth"], "none");

    // Every demo scene gets one.
    let list = s.req("GET", "/v1/scenes", &[], &[]).json();
    let demo = list["scenes"].as_array().unwrap();
    assert_eq!(demo.len(), 3);
    for scene in demo {
        let id = scene["id"].as_str().unwrap();
        let r = s.req("GET", &format!("/v1/scenes/{id}/thumbnail"), &[], &[]);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(r.header("content-type"), Some("image/png"));
        assert_eq!(r.header("cache-control"), Some("private, max-age=3600"));
        assert_eq!(png_size(&r.body), (160, 120));
    }

    // An upload with a name (markup is just text to the server).
    let name = "<img src=x onerror=alert(1)>";
    let q: String = form_urlencoded::Serializer::new(String::new())
        .append_pair("name", name)
        .finish();
    let bytes = std::fs::read(scenes().join("OrientationTest.glb")).unwrap();
    let up = s.req(
        "POST",
        &format!("/v1/scenes?{q}"),
        &[("Content-Type", "model/gltf-binary")],
        &bytes,
    );
    assert_eq!(up.status, 201, "{}", String::from_utf8_lossy(&up.body));
    let scene = up.json();
    assert_eq!(scene["name"], name);
    let id = scene["id"].as_str().unwrap().to_string();
    let thumb = s.req("GET", &format!("/v1/scenes/{id}/thumbnail"), &[], &[]);
    assert_eq!(thumb.status, 200);
    let first = thumb.body.clone();
    assert_eq!(png_size(&first), (160, 120));
    // Not a blank picture: the scene is in it.
    let decoder = png::Decoder::new(std::io::Cursor::new(&first));
    let mut reader = decoder.read_info().unwrap();
    let mut pixels = vec![
        0;
        reader
            .output_buffer_size()
            .expect("a thumbnail fits in memory")
    ];
    reader.next_frame(&mut pixels).unwrap();
    let background = &pixels[..3];
    let covered = pixels.chunks(3).filter(|p| p != &background).count();
    assert!(covered > 500, "{covered} pixels show the scene");
    let again = s.req("GET", &format!("/v1/scenes/{id}/thumbnail"), &[], &[]);
    assert_eq!(again.body, first, "made once, then kept");

    // Bad names are refused before any work, with the field.
    let bad = s.req(
        "POST",
        "/v1/scenes?name=a%0Ab",
        &[("Content-Type", "model/gltf-binary")],
        &std::fs::read(scenes().join("Triangle.glb")).unwrap(),
    );
    assert_eq!(bad.status, 400);
    assert_eq!(bad.json()["field"], "name");
    let unknown = s.req(
        "POST",
        "/v1/scenes?nmae=x",
        &[("Content-Type", "model/gltf-binary")],
        &bytes,
    );
    assert_eq!(unknown.status, 400);

    // No scene, no thumbnail; a deleted scene loses its thumbnail.
    let none = s.req(
        "GET",
        &format!("/v1/scenes/{}/thumbnail", "ab".repeat(32)),
        &[],
        &[],
    );
    assert_eq!(none.status, 404);
    assert_eq!(
        s.req("DELETE", &format!("/v1/scenes/{id}"), &[], &[])
            .status,
        204
    );
    assert_eq!(
        s.req("GET", &format!("/v1/scenes/{id}/thumbnail"), &[], &[])
            .status,
        404
    );
    s.stop();

    // After a restart, thumbnails are made again on first request.
    let s = Server::start(&data, &[]);
    let id = demo[0]["id"].as_str().unwrap();
    let r = s.req("GET", &format!("/v1/scenes/{id}/thumbnail"), &[], &[]);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(png_size(&r.body), (160, 120));
    s.stop();
}
