//! The dashboard in a real browser: chromedriver and headless Chromium drive the page a
//! local cluster's coordinator serves on `--http`, speaking the W3C WebDriver protocol over
//! plain HTTP. The page lists the workers and the submitted (progressive) job; the running
//! frame's preview appears and changes at least once, and the page says which subframe is
//! rendering; the cancel button cancels the job, as the gRPC API
//! (`rayfarm jobs`) then says. SKIPPED when chromium or chromedriver is not installed.
//!
//! With `RAYFARM_DASHBOARD_SCREENSHOT=PATH` the page mid-frame is saved there as PNG (how
//! docs/dashboard.png is made).

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use rayfarm_tests::{Cluster, ClusterOpts, WorkerOpts, job, jobs, prepare_nbody, wait_until};
use serde_json::{Value, json};

const FRAME: [&str; 8] = [
    "--width", "400", "--height", "300", "--spp", "64", "--depth", "3",
];
const TIMEOUT: Duration = Duration::from_secs(120);
/// The key of an element reference in WebDriver answers.
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

/// A chromedriver process on a port it chose, and one browser session on it.
struct Browser {
    driver: Child,
    addr: String,
    session: String,
}

impl Browser {
    fn start(profile: &Path) -> Browser {
        let mut driver = Command::new("chromedriver")
            .arg("--port=0")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let mut lines = BufReader::new(driver.stdout.take().unwrap()).lines();
        let port = loop {
            let line = lines.next().expect("chromedriver says its port").unwrap();
            if let Some(rest) = line.split("started successfully on port ").nth(1) {
                break rest.trim_end_matches('.').trim().to_string();
            }
        };
        // Its further output is read and dropped, so it never blocks on a full pipe.
        std::thread::spawn(move || lines.for_each(drop));
        let addr = format!("127.0.0.1:{port}");
        let mut browser = Browser {
            driver,
            addr,
            session: String::new(),
        };
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {
                "binary": which("chromium").unwrap(),
                "args": ["--headless=new", "--no-sandbox", "--disable-gpu",
                         "--disable-dev-shm-usage", "--window-size=1400,1100",
                         format!("--user-data-dir={}", profile.display())],
            },
        }}});
        let answer = browser.call("POST", "/session", &caps);
        browser.session = answer["sessionId"].as_str().expect("a session").to_string();
        browser
    }

    /// One WebDriver command; its `value`. Panics on a transport error.
    fn call(&self, method: &str, path: &str, body: &Value) -> Value {
        let body = body.to_string();
        let headers = [("Content-Type", "application/json")];
        let (status, text) =
            rayfarm_tests::try_http_request(&self.addr, method, path, &headers, &body)
                .unwrap_or_else(|e| panic!("WebDriver {method} {path}: {e}"));
        let value: Value = serde_json::from_str(&text)
            .unwrap_or_else(|_| panic!("WebDriver {method} {path}: {status} {text}"));
        if status != 200 {
            return json!({"error": value["value"].clone()});
        }
        value["value"].clone()
    }

    fn session(&self, method: &str, path: &str, body: &Value) -> Value {
        self.call(method, &format!("/session/{}{path}", self.session), body)
    }

    fn script(&self, script: &str) -> Value {
        self.session(
            "POST",
            "/execute/sync",
            &json!({"script": script, "args": []}),
        )
    }

    /// Clicks the element `css` selects; false if there is none or it went stale (the page
    /// redraws its tables every second).
    fn click(&self, css: &str) -> bool {
        let found = self.session(
            "POST",
            "/element",
            &json!({"using": "css selector", "value": css}),
        );
        let Some(element) = found[ELEMENT].as_str() else {
            eprintln!("no {css} to click: {found}");
            return false;
        };
        let clicked = self.session("POST", &format!("/element/{element}/click"), &json!({}));
        if let Some(error) = clicked.get("error") {
            eprintln!("clicking {css}: {error}");
            return false;
        }
        true
    }

    fn screenshot(&self) -> Vec<u8> {
        let b64 = self.session("GET", "/screenshot", &json!({}));
        decode_base64(b64.as_str().expect("a screenshot"))
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            let _ = rayfarm_tests::try_http_request(
                &self.addr,
                "DELETE",
                &format!("/session/{}", self.session),
                &[],
                "",
            );
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

fn which(program: &str) -> Option<String> {
    std::env::var_os("PATH")?
        .to_str()?
        .split(':')
        .map(|dir| Path::new(dir).join(program))
        .find(|p| p.is_file())
        .map(|p| p.display().to_string())
}

/// Standard base64 (what WebDriver screenshots are).
fn decode_base64(text: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let digits: Vec<u8> = text
        .bytes()
        .filter(|&c| c != b'=' && !c.is_ascii_whitespace())
        .map(value)
        .collect();
    let mut out = Vec::with_capacity(digits.len() * 3 / 4);
    for chunk in digits.chunks(4) {
        let n = chunk
            .iter()
            .enumerate()
            .fold(0u32, |n, (i, &d)| n | u32::from(d) << (18 - 6 * i));
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

/// What the page shows: the workers' ids, "job:state" per job row, and the preview's
/// sequence number and width once an image is in.
const PAGE_STATE: &str = "
    const img = document.getElementById('preview');
    return {
      workers: Array.from(document.querySelectorAll('#workers tbody tr')).map(r => r.dataset.workerId),
      jobs: Array.from(document.querySelectorAll('#jobs tbody tr')).map(r => r.dataset.jobId + ':' + r.dataset.state),
      sequence: img.complete && img.naturalWidth > 0 ? img.dataset.sequence : '',
      width: img.naturalWidth,
      note: document.getElementById('preview-note').textContent,
      progress: Array.from(document.querySelectorAll('#jobs tbody tr td:nth-child(3)')).map(c => c.textContent),
    };";

#[test]
fn the_dashboard_lists_the_cluster_previews_the_frame_and_cancels_from_the_page() {
    let (Some(_), Some(_)) = (which("chromium"), which("chromedriver")) else {
        eprintln!(
            "SKIPPED: chromium and chromedriver are needed (apt-get install chromium chromium-driver)"
        );
        return;
    };
    let root = tempfile::tempdir().expect("temp dir");
    prepare_nbody(root.path(), "nb", 20_000, 4);
    let opts = ClusterOpts {
        coordinator_args: vec!["--http".into(), "127.0.0.1:0".into()],
        ..Default::default()
    };
    let cluster = Cluster::start_with(
        root.path(),
        Some("nb"),
        &opts,
        &vec![WorkerOpts::default(); 2],
    );
    cluster.wait_for_workers(2, TIMEOUT);
    let http = cluster
        .coordinator_http()
        .expect("the dashboard's address")
        .to_string();
    let browser = Browser::start(&root.path().join("chromium-profile"));
    browser.session("POST", "/url", &json!({"url": format!("http://{http}/")}));

    // In subframes (1, 1, 2, 4, ... 32 samples), so the page shows which one is rendering
    // and the preview sharpens as they commit.
    let mut args = vec!["submit", "--progressive", "doubling"];
    args.extend_from_slice(&FRAME);
    let out = cluster.rayfarm_ok(&args);
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let workers: Vec<String> = cluster.status()["workers"]
        .as_array()
        .expect("workers")
        .iter()
        .map(|w| w["worker_id"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(workers.len(), 2);

    let mut page = Value::Null;
    wait_until(
        "the page lists both workers and the running job",
        TIMEOUT,
        || {
            page = browser.script(PAGE_STATE);
            let listed = page["workers"].as_array().map_or(0, |w| {
                workers
                    .iter()
                    .filter(|id| w.iter().any(|v| v == id.as_str()))
                    .count()
            });
            listed == 2
                && page["jobs"]
                    .as_array()
                    .is_some_and(|j| j.iter().any(|v| v == &json!(format!("{id}:running"))))
        },
    );
    wait_until("a preview on the page", TIMEOUT, || {
        page = browser.script(PAGE_STATE);
        page["sequence"].as_str().is_some_and(|s| !s.is_empty())
    });
    let first = page["sequence"].clone();
    assert_eq!(page["width"], 400, "{page}");
    wait_until("a newer preview on the page", TIMEOUT, || {
        page = browser.script(PAGE_STATE);
        page["sequence"].as_str().is_some_and(|s| !s.is_empty()) && page["sequence"] != first
    });
    // The first subframe committed: the preview is a whole 1-sample image being refined, and
    // the page says which subframe of the seven is rendering.
    wait_until("a preview past the first subframe", TIMEOUT, || {
        page = browser.script(PAGE_STATE);
        page["note"]
            .as_str()
            .is_some_and(|n| (2..=7).any(|k| n.contains(&format!("subframe {k}/7"))))
    });
    assert!(
        page["progress"].as_array().is_some_and(|p| p
            .iter()
            .any(|c| c.as_str().is_some_and(|c| c.contains("/7")))),
        "{page}"
    );
    let now = job(&jobs(&cluster), &id)["state"].clone();
    assert_eq!(
        now, "running",
        "the frame ended before the page was checked: make it longer"
    );
    if let Some(path) = std::env::var_os("RAYFARM_DASHBOARD_SCREENSHOT") {
        std::fs::write(&path, browser.screenshot()).expect("screenshot written");
    }
    // A PNG, as WebDriver promises.
    assert_eq!(&browser.screenshot()[..8], b"\x89PNG\r\n\x1a\n");

    let button = format!("tr[data-job-id=\"{id}\"] button.cancel");
    wait_until("the cancel button clicked", TIMEOUT, || {
        browser.click(&button)
    });
    wait_until("the job cancelled, as the gRPC API says", TIMEOUT, || {
        job(&jobs(&cluster), &id)["state"] == "cancelled"
    });
    wait_until("the page shows it cancelled", TIMEOUT, || {
        let page = browser.script(PAGE_STATE);
        page["jobs"]
            .as_array()
            .is_some_and(|j| j.iter().any(|v| v == &json!(format!("{id}:cancelled"))))
    });
}

/// `(status, body)` of an HTTP request to the dashboard as the holder of `token`.
fn api(
    http: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    json_body: Option<&str>,
) -> (u16, String) {
    let bearer = token.map(|t| format!("Bearer {t}"));
    let mut headers = Vec::new();
    if let Some(b) = &bearer {
        headers.push(("Authorization", b.as_str()));
    }
    if json_body.is_some() {
        headers.push(("Content-Type", "application/json"));
    }
    rayfarm_tests::http_request(http, method, path, &headers, json_body.unwrap_or(""))
}

#[test]
fn with_user_tokens_the_dashboard_api_needs_a_token_json_posts_and_the_owner() {
    let root = tempfile::tempdir().expect("temp dir");
    prepare_nbody(root.path(), "nb", 2_000, 2);
    let tokens = root.path().join("tokens");
    std::fs::write(
        &tokens,
        "tok-alice alice\ntok-bob bob\ntok-root root admin\n",
    )
    .unwrap();
    let opts = ClusterOpts {
        coordinator_args: vec![
            "--http".into(),
            "127.0.0.1:0".into(),
            "--user-tokens-file".into(),
            tokens.display().to_string(),
        ],
        client_env: vec![("RAYFARM_TOKEN".into(), "tok-alice".into())],
        ..Default::default()
    };
    // No worker: the job stays queued.
    let cluster = Cluster::start_with(root.path(), Some("nb"), &opts, &[]);
    let http = cluster.coordinator_http().expect("http").to_string();
    let out = cluster.rayfarm_ok(&["submit", "--width", "16", "--height", "16", "--spp", "1"]);
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();

    // The page itself is open; its API is not.
    assert_eq!(api(&http, "GET", "/", None, None).0, 200);
    assert_eq!(api(&http, "GET", "/api/jobs", None, None).0, 401);
    assert_eq!(api(&http, "GET", "/api/jobs", Some("guess"), None).0, 401);
    let (status, body) = api(&http, "GET", "/api/jobs", Some("tok-bob"), None);
    assert_eq!(status, 200);
    assert!(body.contains(&id), "{body}");

    let cancel = format!("/api/jobs/{id}/cancel");
    let priority = format!("/api/jobs/{id}/priority");
    // Not without a token, not as another user, not without a JSON body.
    assert_eq!(api(&http, "POST", &cancel, None, Some("{}")).0, 401);
    let (status, body) = api(&http, "POST", &cancel, Some("tok-bob"), Some("{}"));
    assert_eq!(status, 403, "{body}");
    assert!(body.contains("only its owner or an admin"), "{body}");
    assert_eq!(api(&http, "POST", &cancel, Some("tok-alice"), None).0, 415);
    assert_eq!(api(&http, "GET", &cancel, Some("tok-alice"), None).0, 405);
    assert_eq!(job(&jobs(&cluster), &id)["state"], "queued");

    let (status, body) = api(
        &http,
        "POST",
        &priority,
        Some("tok-bob"),
        Some(r#"{"priority": 9}"#),
    );
    assert_eq!(status, 403, "{body}");
    let (status, body) = api(
        &http,
        "POST",
        &priority,
        Some("tok-alice"),
        Some(r#"{"priority": 7}"#),
    );
    assert_eq!(status, 200, "{body}");
    assert_eq!(job(&jobs(&cluster), &id)["priority"], 7);
    // A queued job has no preview yet.
    assert_eq!(
        api(
            &http,
            "GET",
            &format!("/api/jobs/{id}/preview"),
            Some("tok-alice"),
            None
        )
        .0,
        409
    );

    // An admin may cancel anyone's job; the gRPC API says so.
    let (status, body) = api(&http, "POST", &cancel, Some("tok-root"), Some("{}"));
    assert_eq!(status, 200, "{body}");
    assert_eq!(job(&jobs(&cluster), &id)["state"], "cancelled");
}
