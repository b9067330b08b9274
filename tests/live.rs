//! The live view (`run --serve`, `serve`): the state API follows a simulated run
//! in-process and from another process, the Stop button interrupts like Ctrl-C and
//! the run resumes, access rules (token, path traversal, symlinks, read-only), bad
//! input, many and hung viewers, and the page in headless Chromium.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::util;

/// A response: status, head, body.
struct Resp {
    status: u16,
    head: String,
    body: Vec<u8>,
}

impl Resp {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&self.body)))
    }
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// One HTTP/1.0 request with the path sent exactly as given (no normalisation).
fn request(addr: &str, method: &str, path: &str, headers: &[(&str, &str)]) -> Resp {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    let mut req = format!("{method} {path} HTTP/1.0\r\nHost: {addr}\r\n");
    for (k, v) in headers {
        req += &format!("{k}: {v}\r\n");
    }
    req += "Content-Length: 0\r\n\r\n";
    s.write_all(req.as_bytes()).unwrap();
    let mut all = Vec::new();
    s.read_to_end(&mut all).unwrap();
    let split = all
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a response head");
    let head = String::from_utf8_lossy(&all[..split]).into_owned();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    Resp {
        status,
        head,
        body: all[split + 4..].to_vec(),
    }
}

fn get(addr: &str, path: &str) -> Resp {
    request(addr, "GET", path, &[])
}

/// `http://HOST:PORT/...` -> (`HOST:PORT` to connect to, the token if any).
fn parse_url(url: &str) -> (String, Option<String>) {
    let rest = url.strip_prefix("http://").unwrap();
    let (hostport, tail) = rest.split_once('/').unwrap();
    let port = hostport.rsplit(':').next().unwrap();
    let token = tail.strip_prefix("?token=").map(str::to_string);
    (format!("127.0.0.1:{port}"), token)
}

/// A `tactbench` child whose stderr is collected; the live view's URL, once printed.
struct Served {
    child: Child,
    url: String,
    addr: String,
    lines: mpsc::Receiver<String>,
}

fn spawn_collecting(args: &[&str], url_prefix: &'static str) -> Served {
    let mut child = Command::new(util::bin())
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let t0 = Instant::now();
    let mut seen = Vec::new();
    let url = loop {
        match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(line) => {
                if let Some(i) = line.find(url_prefix) {
                    let rest = &line[i + url_prefix.len()..];
                    break rest.split_whitespace().next().unwrap().to_string();
                }
                seen.push(line);
            }
            Err(_) => {
                let _ = child.kill();
                panic!("no URL after {:?}: {seen:?}", t0.elapsed());
            }
        }
    };
    let (addr, _) = parse_url(&url);
    Served {
        child,
        url,
        addr,
        lines: rx,
    }
}

fn spawn_run(out: &Path, limit: usize, extra: &[&str]) -> Served {
    let out = out.to_str().unwrap();
    let limit = limit.to_string();
    let mut args = util::FIG7_SIM_RUN.to_vec();
    args.extend(["--limit", &limit, "--no-progress", "--out", out]);
    args.extend_from_slice(extra);
    spawn_collecting(&args, "live view: ")
}

fn spawn_serve(dirs: &[&Path], extra: &[&str]) -> Served {
    let mut args: Vec<String> = vec!["serve".into()];
    args.extend(dirs.iter().map(|d| d.display().to_string()));
    args.extend(extra.iter().map(|s| s.to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    spawn_collecting(&args, "run(s): ")
}

/// The view's token as its page carries it (`None` when the page is refused).
fn page_token(addr: &str) -> Option<String> {
    let page = get(addr, "/");
    if page.status != 200 {
        return None;
    }
    let text = page.text();
    let key = r#"<meta name="tactbench-token" content=""#;
    let at = text.find(key)? + key.len();
    Some(text[at..].split('"').next()?.to_string())
}

/// The page's Stop button: `POST /api/stop` with the confirmation header and the
/// token the page carries.
fn confirmed_stop(addr: &str) -> Resp {
    let token = page_token(addr).unwrap_or_default();
    request(
        addr,
        "POST",
        "/api/stop",
        &[
            ("X-Tactbench-Stop", "confirm"),
            ("X-Tactbench-Token", &token),
        ],
    )
}

/// One request with the `Host` line given (and any other headers).
fn request_as(addr: &str, host: &str, method: &str, path: &str, headers: &[(&str, &str)]) -> Resp {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n");
    for (k, v) in headers {
        req += &format!("{k}: {v}\r\n");
    }
    req += "Content-Length: 0\r\n\r\n";
    s.write_all(req.as_bytes()).unwrap();
    let mut all = Vec::new();
    s.read_to_end(&mut all).unwrap();
    let split = all
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a response head");
    let head = String::from_utf8_lossy(&all[..split]).into_owned();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    Resp {
        status,
        head,
        body: all[split + 4..].to_vec(),
    }
}

fn state(addr: &str) -> Value {
    let r = get(addr, "/api/state");
    assert_eq!(r.status, 200, "{}", r.text());
    r.json()
}

/// Polls until `f` holds (or panics after `secs`).
fn wait_for(secs: u64, what: &str, mut f: impl FnMut() -> bool) {
    let t0 = Instant::now();
    while !f() {
        assert!(
            t0.elapsed() < Duration::from_secs(secs),
            "timed out: {what}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn wait_exit(child: &mut Child, secs: u64) -> i32 {
    let t0 = Instant::now();
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s.code().unwrap_or(-1);
        }
        if t0.elapsed() > Duration::from_secs(secs) {
            let _ = child.kill();
            panic!("did not exit in {secs} s");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Reads server-sent events for `dur` (or until `n` events), returning (name, data).
fn read_events(addr: &str, path: &str, n: usize, dur: Duration) -> Vec<(String, String)> {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    let mut buf = Vec::new();
    let t0 = Instant::now();
    let mut chunk = [0u8; 65536];
    let mut events = Vec::new();
    while t0.elapsed() < dur && events.len() < n {
        match s.read(&mut chunk) {
            Ok(0) => break,
            Ok(k) => buf.extend_from_slice(&chunk[..k]),
            Err(_) => {}
        }
        let text = String::from_utf8_lossy(&buf).into_owned();
        events = text
            .split("\n\n")
            .filter_map(|block| {
                let name = block
                    .lines()
                    .find_map(|l| l.strip_prefix("event: "))?
                    .to_string();
                let data = block
                    .lines()
                    .find_map(|l| l.strip_prefix("data: "))?
                    .to_string();
                Some((name, data))
            })
            .collect();
    }
    events
}

#[test]
fn run_serve_follows_a_simulated_run_and_serves_its_state_journal_frame_and_events() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let n = 6;
    let mut s = spawn_run(&out, n, &["--serve", "127.0.0.1:0"]);
    assert!(s.url.starts_with("http://127.0.0.1:"), "{}", s.url);
    assert!(!s.url.contains("token"), "loopback: no token");

    // The page itself.
    let page = get(&s.addr, "/");
    assert_eq!(page.status, 200);
    assert!(page.text().contains("tactbench live view"));
    assert!(page
        .head
        .to_ascii_lowercase()
        .contains("content-type: text/html"));

    // The numbers advance while the run runs.
    let mut done_seen = Vec::new();
    let mut phases = std::collections::BTreeSet::new();
    wait_for(240, "two setpoints measured while running", || {
        let st = state(&s.addr);
        if st["state"] == "running" {
            let d = st["setpoints_done"].as_u64().unwrap();
            if done_seen.last() != Some(&d) {
                done_seen.push(d);
            }
            phases.insert(st["phase"].as_str().unwrap().to_string());
            assert_eq!(st["setpoints_total"], n);
        }
        done_seen.iter().filter(|d| **d > 0).count() >= 2
    });
    assert!(
        phases.iter().all(|p| [
            "home",
            "tare",
            "reference",
            "approach",
            "force_control",
            "settle",
            "acquire",
            "solve",
            "retract",
            "idle"
        ]
        .contains(&p.as_str())),
        "{phases:?}"
    );
    let st = state(&s.addr);
    assert!(st["elapsed_s"].as_f64().unwrap() > 0.0, "{st}");
    assert!(st["simulated"].as_bool().unwrap());

    // Journal rows so far, the latest frame, pushed events.
    let j = get(&s.addr, "/api/journal").json();
    let rows = j["rows"].as_array().unwrap();
    assert!(!rows.is_empty(), "{j}");
    assert!(rows[0]["fz_n"].is_number() && rows[0]["index"] == 0);
    let from1 = get(&s.addr, "/api/journal?from=1").json();
    assert!(from1["rows"]
        .as_array()
        .unwrap()
        .iter()
        .all(|r| r["index"].as_u64().unwrap() >= 1));
    wait_for(30, "a frame", || {
        get(&s.addr, "/api/frame.png").status == 200
    });
    let png = get(&s.addr, "/api/frame.png");
    assert!(png.body.starts_with(b"\x89PNG\r\n\x1a\n"));
    assert!(png.head.to_ascii_lowercase().contains("image/png"));
    let ev = read_events(&s.addr, "/api/events", 3, Duration::from_secs(10));
    let names: Vec<&str> = ev.iter().map(|(n, _)| n.as_str()).collect();
    assert!(
        names.contains(&"state") && names.contains(&"series"),
        "{names:?}"
    );
    let pushed: Value =
        serde_json::from_str(&ev.iter().find(|e| e.0 == "state").unwrap().1).unwrap();
    assert_eq!(pushed["run"], 0);

    // Read-only: nothing but the stop accepts another method.
    assert_eq!(request(&s.addr, "PUT", "/api/state", &[]).status, 405);
    assert_eq!(
        request(&s.addr, "DELETE", "/runs/0/report.html", &[]).status,
        405
    );
    assert_eq!(get(&s.addr, "/api/stop").status, 405);

    // The final state, then the process ends as without --serve.
    assert_eq!(wait_exit(&mut s.child, 300), 0);
    let lines: Vec<String> = s.lines.try_iter().collect();
    assert!(
        lines.iter().any(|l| l.contains("run completed")),
        "{lines:?}"
    );
    let live: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("live.json")).unwrap()).unwrap();
    assert_eq!(live["schema"], "tactbench-live/1");
    assert_eq!(live["state"], "completed");
    assert_eq!(live["phase"], "idle");
    assert_eq!(live["setpoints_done"], n);
    assert!(!out.join(".live.json.tmp").exists());
}

/// A small finished run, shared by the tests that only read one.
fn finished_run(tmp: &Path, n: usize) -> PathBuf {
    let out = tmp.join("done");
    let o = util::run_fig7_sim(&[
        "--limit",
        &n.to_string(),
        "--no-progress",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    out
}

#[test]
fn serve_reads_only_inside_the_run_directories_and_never_writes_to_them() {
    let tmp = tempfile::tempdir().unwrap();
    let run = finished_run(tmp.path(), 2);
    std::fs::write(tmp.path().join("secret.png"), b"secret").unwrap();
    std::os::unix::fs::symlink(
        tmp.path().join("secret.png"),
        run.join("frames/zz_link.png"),
    )
    .unwrap();
    std::fs::write(run.join("report.html"), "<html>report</html>").unwrap();
    let before = listing(&run);
    let mut s = spawn_serve(&[&run], &["--addr", "127.0.0.1:0"]);
    wait_for(30, "the finished state", || {
        state(&s.addr)["state"] == "completed"
    });
    let st = state(&s.addr);
    assert_eq!(st["setpoints_done"], 2);
    assert_eq!(st["setpoints_total"], 2);
    assert_eq!(st["report"], "report.html");
    assert_eq!(
        get(&s.addr, "/runs/0/report.html").text(),
        "<html>report</html>"
    );
    assert_eq!(get(&s.addr, "/runs/0/frames/00000_0.png").status, 200);
    for bad in [
        "/runs/0/../../../../etc/passwd",
        "/runs/0/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
        "/runs/0/frames/%2e%2e%2f%2e%2e%2fsecret.png",
        "/runs/0/frames/..%2f..%2fsecret.png",
        "/runs/0/frames/zz_link.png",
        "/runs/0/manifest.json",
        "/runs/0/run.lock",
        "/runs/0//etc/passwd",
        "/runs/0/frames/%00.png",
        "/runs/1/report.html",
        "/runs/0/frames/..\\..\\secret.png",
        "/../../etc/passwd",
        "/api/runs/0/../../secret.png",
    ] {
        let r = get(&s.addr, bad);
        assert!(
            [400, 404].contains(&r.status),
            "{bad}: {} {}",
            r.status,
            r.text()
        );
        assert!(!r.body.windows(6).any(|w| w == b"secret"), "{bad}");
        assert!(!r.text().contains("root:"), "{bad}");
    }
    // A stop on a finished run is refused; nothing was written.
    let r = confirmed_stop(&s.addr);
    assert_eq!(r.status, 409, "{}", r.text());
    let _ = s.child.kill();
    let _ = s.child.wait();
    assert_eq!(listing(&run), before, "serve wrote into the run directory");
}

/// Every file under `dir` with its length and modification time.
fn listing(dir: &Path) -> Vec<(PathBuf, u64, std::time::SystemTime)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let e = e.unwrap();
            let m = std::fs::symlink_metadata(e.path()).unwrap();
            if m.is_dir() {
                stack.push(e.path());
            } else {
                out.push((e.path(), m.len(), m.modified().unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn a_non_loopback_address_needs_the_token_printed_in_the_url() {
    let tmp = tempfile::tempdir().unwrap();
    let run = finished_run(tmp.path(), 1);
    let mut s = spawn_serve(&[&run], &["--addr", "0.0.0.0:0"]);
    let (addr, token) = parse_url(&s.url);
    let token = token.expect("a token in the URL");
    assert_eq!(token.len(), 32);
    for path in [
        "/",
        "/api/state",
        "/api/events",
        "/runs/0/frames/00000_0.png",
        "/api/state?token=wrong",
    ] {
        assert_eq!(get(&addr, path).status, 401, "{path}");
    }
    assert_eq!(get(&addr, &format!("/api/state?token={token}")).status, 200);
    let bearer = format!("Bearer {token}");
    assert_eq!(
        request(&addr, "GET", "/api/state", &[("Authorization", &bearer)]).status,
        200
    );
    assert_eq!(confirmed_stop(&addr).status, 401);
    let _ = s.child.kill();
    let _ = s.child.wait();
}

#[test]
fn bad_addresses_and_directories_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let run = finished_run(tmp.path(), 1);
    let busy = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let busy_addr = busy.local_addr().unwrap().to_string();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "serve".into(),
                run.display().to_string(),
                "--addr".into(),
                busy_addr.clone(),
            ],
            "in use",
        ),
        (
            // TEST-NET-1 (RFC 5737): never an address of this machine.
            vec![
                "serve".into(),
                run.display().to_string(),
                "--addr".into(),
                "192.0.2.1:0".into(),
            ],
            "not an address of this machine",
        ),
        (
            vec![
                "serve".into(),
                run.display().to_string(),
                "--addr".into(),
                "nonsense".into(),
            ],
            "not an address",
        ),
        (
            vec![
                "serve".into(),
                tmp.path().display().to_string(),
                "--addr".into(),
                "127.0.0.1:0".into(),
            ],
            "not a run directory",
        ),
        (
            vec![
                "serve".into(),
                tmp.path().join("nope").display().to_string(),
            ],
            "not a run directory",
        ),
    ];
    for (args, want) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = util::run(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", util::stderr(&o));
        assert!(
            util::stderr(&o).contains(want),
            "{args:?}: {}",
            util::stderr(&o)
        );
    }
    // `run --serve` on a busy port fails before creating or moving anything.
    let out = tmp.path().join("never");
    let o = util::run_fig7_sim(&["--out", out.to_str().unwrap(), "--serve", &busy_addr]);
    assert_eq!(o.status.code(), Some(2), "{}", util::stderr(&o));
    assert!(util::stderr(&o).contains("in use"), "{}", util::stderr(&o));
    assert!(!out.exists(), "nothing created");
    drop(busy);
}

#[test]
fn a_run_directory_that_disappears_while_served_is_reported_as_missing() {
    let tmp = tempfile::tempdir().unwrap();
    let run = finished_run(tmp.path(), 1);
    let copy = tmp.path().join("copy");
    std::fs::create_dir_all(copy.join("frames")).unwrap();
    for f in ["manifest.json", "journal.csv"] {
        std::fs::copy(run.join(f), copy.join(f)).unwrap();
    }
    let mut s = spawn_serve(&[&run, &copy], &["--addr", "127.0.0.1:0"]);
    wait_for(30, "both runs", || {
        get(&s.addr, "/api/runs/1/state").json()["state"] == "completed"
    });
    std::fs::remove_dir_all(&copy).unwrap();
    wait_for(30, "the missing run", || {
        get(&s.addr, "/api/runs/1/state").json()["state"] == "missing"
    });
    let st = get(&s.addr, "/api/runs/1/state").json();
    assert!(
        st["error"].as_str().unwrap().contains("disappeared"),
        "{st}"
    );
    // The other run is still served.
    assert_eq!(state(&s.addr)["state"], "completed");
    assert_eq!(
        get(&s.addr, "/api/runs").json().as_array().unwrap().len(),
        2
    );
    let _ = s.child.kill();
    let _ = s.child.wait();
}

#[test]
fn serve_follows_a_run_of_another_process_and_its_stop_button_interrupts_it_like_ctrl_c() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let n = 12;
    let mut child = Command::new(util::bin())
        .args(util::FIG7_SIM_RUN)
        .args(["--limit", &n.to_string(), "--no-progress", "--out"])
        .arg(&out)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    wait_for(60, "the manifest", || out.join("manifest.json").exists());
    let mut s = spawn_serve(&[&out], &["--addr", "127.0.0.1:0"]);
    wait_for(120, "a running state with a measured setpoint", || {
        let st = state(&s.addr);
        st["state"] == "running" && st["setpoints_done"].as_u64().unwrap() >= 1
    });
    let st = state(&s.addr);
    assert_eq!(st["writer_pid"], child.id());
    assert_eq!(st["setpoints_total"], n);
    // Without the confirmation header nothing happens.
    assert_eq!(request(&s.addr, "POST", "/api/stop", &[]).status, 400);
    assert!(child.try_wait().unwrap().is_none());
    let r = confirmed_stop(&s.addr);
    assert_eq!(r.status, 202, "{}", r.text());
    // What Ctrl-C does: exit 4, interrupted, stage retracted, resumable.
    assert_eq!(wait_exit(&mut child, 120), 4);
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["status"], "interrupted");
    assert_eq!(m["stop_signal"], "SIGINT");
    assert!(
        m["end_reason"]
            .as_str()
            .unwrap()
            .contains("stage retracted"),
        "{m}"
    );
    wait_for(30, "the interrupted state", || {
        state(&s.addr)["state"] == "interrupted"
    });
    let _ = s.child.kill();
    let _ = s.child.wait();
    let resumed = util::run(&["run", "--resume", out.to_str().unwrap(), "--no-progress"]);
    assert!(resumed.status.success(), "{}", util::stderr(&resumed));
}

#[test]
fn the_stop_button_of_run_serve_interrupts_the_run_it_serves() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let mut s = spawn_run(&out, 40, &["--serve", "127.0.0.1:0"]);
    wait_for(120, "a measured setpoint", || {
        state(&s.addr)["setpoints_done"].as_u64().unwrap_or(0) >= 1
    });
    let r = confirmed_stop(&s.addr);
    assert_eq!(r.status, 202, "{}", r.text());
    assert_eq!(wait_exit(&mut s.child, 120), 4);
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["status"], "interrupted");
    assert!(
        m["end_reason"]
            .as_str()
            .unwrap()
            .contains("stage retracted"),
        "{m}"
    );
}

#[test]
fn twenty_viewers_and_a_hung_one_leave_the_run_and_its_journal_intact() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let n = 4;
    let mut s = spawn_run(&out, n, &["--serve", "127.0.0.1:0"]);
    // A hung browser: connects to the event stream and never reads.
    let mut hung = TcpStream::connect(&s.addr).unwrap();
    write!(hung, "GET /api/events HTTP/1.1\r\nHost: {}\r\n\r\n", s.addr).unwrap();
    let viewers: Vec<_> = (0..20)
        .map(|_| {
            let addr = s.addr.clone();
            std::thread::spawn(move || viewer(&addr))
        })
        .collect();
    assert_eq!(wait_exit(&mut s.child, 300), 0);
    drop(hung);
    for v in viewers {
        let seen = v.join().unwrap();
        let last = seen.last_state.expect("a state event");
        assert_eq!(last["state"], "completed", "{last}");
        assert!(seen.ended, "the stream ended with `end`");
        assert!(seen.frames >= 1, "a frame was fetched");
    }
    let rows = tactbench::bench::journal::read_rows(&out).unwrap();
    assert_eq!(
        rows.iter().map(|r| r.index).collect::<Vec<_>>(),
        (0..n).collect::<Vec<_>>()
    );
}

/// Debian's Chromium (`.ci/run` installs it), or `TACTBENCH_CHROMIUM`.
fn chromium() -> Option<PathBuf> {
    std::env::var_os("TACTBENCH_CHROMIUM")
        .map(PathBuf::from)
        .into_iter()
        .chain(["/usr/bin/chromium", "/usr/bin/chromium-browser"].map(PathBuf::from))
        .find(|p| p.is_file())
}

/// Headless Chromium driven over the DevTools protocol on a pipe
/// (`--remote-debugging-pipe`: commands on fd 3, answers on fd 4, NUL-terminated
/// JSON), so one page stays open while the run advances and the test reads its DOM.
struct Browser {
    child: Child,
    tx: std::fs::File,
    rx: BufReader<std::fs::File>,
    next: u64,
    session: Option<String>,
    _profile: tempfile::TempDir,
}

impl Browser {
    fn launch(path: &Path) -> Browser {
        Browser::launch_with(path, &[])
    }

    /// [`Browser::launch`] with more command-line switches.
    fn launch_with(path: &Path, extra: &[&str]) -> Browser {
        use std::os::fd::FromRawFd;
        use std::os::unix::process::CommandExt;
        let pipe = || {
            let mut fds = [0i32; 2];
            // SAFETY: pipe2 fills two descriptors; close-on-exec keeps them out of the
            // child except where dup2 places them.
            assert_eq!(unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) }, 0);
            fds
        };
        let (to_browser, from_browser) = (pipe(), pipe());
        let profile = tempfile::tempdir().unwrap();
        let mut cmd = Command::new(path);
        cmd.args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--remote-debugging-pipe",
        ])
        .args(extra)
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg("about:blank")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
        let (r3, w4) = (to_browser[0], from_browser[1]);
        // SAFETY: only async-signal-safe dup2 between fork and exec.
        unsafe {
            cmd.pre_exec(move || {
                // Out of the way first: either end may itself be fd 3 or 4.
                let a = libc::fcntl(r3, libc::F_DUPFD, 10);
                let b = libc::fcntl(w4, libc::F_DUPFD, 10);
                if a < 0 || b < 0 || libc::dup2(a, 3) < 0 || libc::dup2(b, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = cmd.spawn().expect("start chromium");
        // SAFETY: our ends of the pipes, owned from here on; the child's are closed.
        let (tx, rx) = unsafe {
            libc::close(r3);
            libc::close(w4);
            (
                std::fs::File::from_raw_fd(to_browser[1]),
                std::fs::File::from_raw_fd(from_browser[0]),
            )
        };
        Browser {
            child,
            tx,
            rx: BufReader::new(rx),
            next: 1,
            session: None,
            _profile: profile,
        }
    }

    /// One command; returns its `result` (events in between are skipped).
    fn call(&mut self, method: &str, params: Value) -> Value {
        let id = self.next;
        self.next += 1;
        let mut msg = serde_json::json!({ "id": id, "method": method, "params": params });
        if let Some(s) = &self.session {
            msg["sessionId"] = Value::String(s.clone());
        }
        let mut bytes = msg.to_string().into_bytes();
        bytes.push(0);
        self.tx.write_all(&bytes).unwrap();
        loop {
            let mut buf = Vec::new();
            let k = self.rx.read_until(0, &mut buf).unwrap();
            assert!(k > 0, "chromium closed the DevTools pipe");
            buf.pop();
            let v: Value = serde_json::from_slice(&buf).unwrap();
            if v["id"] == id {
                assert!(v.get("error").is_none(), "{method}: {v}");
                return v["result"].clone();
            }
        }
    }

    /// Opens `url` in a new page of 1400x1500 px and attaches to it.
    fn open(&mut self, url: &str) {
        self.session = None;
        let t = self.call(
            "Target.createTarget",
            serde_json::json!({ "url": "about:blank" }),
        );
        let a = self.call(
            "Target.attachToTarget",
            serde_json::json!({ "targetId": t["targetId"], "flatten": true }),
        );
        self.session = Some(a["sessionId"].as_str().unwrap().to_string());
        self.call(
            "Emulation.setDeviceMetricsOverride",
            serde_json::json!({ "width": 1400, "height": 1500, "deviceScaleFactor": 1, "mobile": false }),
        );
        self.call("Page.enable", serde_json::json!({}));
        self.call("Page.navigate", serde_json::json!({ "url": url }));
    }

    /// The text of the element `id` (`None` when there is none).
    fn text(&mut self, id: &str) -> Option<String> {
        let r = self.call(
            "Runtime.evaluate",
            serde_json::json!({
                "expression": format!("(e => e ? e.textContent : null)(document.getElementById({id:?}))"),
                "returnByValue": true
            }),
        );
        r["result"]["value"].as_str().map(str::to_string)
    }

    /// The value of a script in the page (a promise is awaited).
    fn eval(&mut self, expr: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            serde_json::json!({ "expression": expr, "returnByValue": true, "awaitPromise": true }),
        );
        r["result"]["value"].clone()
    }

    fn exists(&mut self, id: &str) -> bool {
        let r = self.call(
            "Runtime.evaluate",
            serde_json::json!({ "expression": format!("!!document.getElementById({id:?})"), "returnByValue": true }),
        );
        r["result"]["value"] == true
    }

    /// A PNG of the page.
    fn screenshot(&mut self, to: &Path) {
        use base64::Engine as _;
        let r = self.call(
            "Page.captureScreenshot",
            serde_json::json!({ "format": "png", "captureBeyondViewport": true }),
        );
        let png = base64::engine::general_purpose::STANDARD
            .decode(r["data"].as_str().unwrap())
            .unwrap();
        std::fs::write(to, png).unwrap();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Where screenshots go: `TACTBENCH_SCREENSHOTS` (to look at them), else a temporary
/// directory.
fn screenshot_dir(tmp: &Path) -> PathBuf {
    std::env::var_os("TACTBENCH_SCREENSHOTS")
        .map(PathBuf::from)
        .unwrap_or_else(|| tmp.join("shots"))
}

#[test]
fn headless_chromium_sees_the_numbers_advance_and_the_final_state() {
    let Some(path) = chromium() else {
        eprintln!("SKIPPED: no /usr/bin/chromium (apt-get install chromium; .ci/run installs it)");
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let shots = screenshot_dir(tmp.path());
    std::fs::create_dir_all(&shots).unwrap();
    let out = tmp.path().join("run");
    let n = 12;
    let mut s = spawn_run(&out, n, &["--serve", "127.0.0.1:0"]);
    let mut b = Browser::launch(&path);
    b.open(&s.url);
    // One page, never reloaded: its numbers advance by push.
    let num = |b: &mut Browser| -> Option<u64> { b.text("r0-done")?.parse().ok() };
    let mut seen: Vec<u64> = Vec::new();
    let mut shot = false;
    let t0 = Instant::now();
    while s.child.try_wait().unwrap().is_none() {
        assert!(t0.elapsed() < Duration::from_secs(300), "run too slow");
        if let Some(d) = num(&mut b) {
            if seen.last() != Some(&d) {
                seen.push(d);
            }
            if !shot && d >= 3 && b.text("r0-state").as_deref() == Some("running") {
                assert_eq!(b.text("r0-total").as_deref(), Some("12"));
                b.screenshot(&shots.join("live_running.png"));
                shot = true;
            }
        }
        std::thread::sleep(Duration::from_millis(150));
    }
    assert_eq!(wait_exit(&mut s.child, 10), 0);
    assert!(
        seen.iter().filter(|d| **d > 0 && **d < n as u64).count() >= 2,
        "the page's setpoint count advanced while running: {seen:?}"
    );
    assert!(seen.windows(2).all(|w| w[0] < w[1]), "{seen:?}");
    // The final state reached the same page before the view closed.
    assert_eq!(b.text("r0-state").as_deref(), Some("completed"));
    assert_eq!(num(&mut b), Some(n as u64));
    // The finished run, served by `serve`, with its report link.
    let o = util::run(&["report", out.to_str().unwrap()]);
    assert!(out.join("report.html").exists(), "{}", util::stderr(&o));
    let mut v = spawn_serve(&[&out], &["--addr", "127.0.0.1:0"]);
    b.open(&v.url);
    wait_for(30, "the finished page", || {
        b.text("r0-state").as_deref() == Some("completed") && b.exists("r0-reportlink")
    });
    assert_eq!(b.text("r0-done").as_deref(), Some("12"));
    std::thread::sleep(Duration::from_millis(1500));
    b.screenshot(&shots.join("live_finished.png"));
    if !shot {
        panic!("no screenshot of the running page: {seen:?}");
    }
    let _ = v.child.kill();
    let _ = v.child.wait();
}

/// `--timings`' summary line: (setpoints, wall s, controller overhead mean ms).
fn timings_of(lines: &[String]) -> (f64, f64, f64) {
    let l = lines
        .iter()
        .find(|l| l.starts_with("timings over "))
        .unwrap_or_else(|| panic!("no timings line in {lines:?}"));
    let num_after = |key: &str| -> f64 {
        let i = l.find(key).unwrap() + key.len();
        l[i..]
            .split_whitespace()
            .next()
            .unwrap()
            .trim_end_matches(';')
            .parse()
            .unwrap()
    };
    (
        num_after("timings over "),
        num_after("wall "),
        num_after("controller overhead "),
    )
}

/// The overhead measurement quoted in docs/live-view.md: the same simulated run
/// without and with `--serve` and 20 viewers (each reading the event stream and
/// fetching every pushed frame), alternated so the machine's load hits both alike.
/// Run it with `cargo test --test integration live_view_overhead -- --ignored
/// --nocapture` (`TACTBENCH_OVERHEAD_PAIRS`, `TACTBENCH_OVERHEAD_SETPOINTS`).
#[test]
#[ignore]
fn live_view_overhead_per_setpoint_with_twenty_viewers() {
    let env = |k: &str, d: usize| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    };
    let pairs = env("TACTBENCH_OVERHEAD_PAIRS", 3);
    let n = env("TACTBENCH_OVERHEAD_SETPOINTS", 32);
    let tmp = tempfile::tempdir().unwrap();
    let mut rows = Vec::new();
    for p in 0..pairs {
        for serve in [false, true] {
            let out = tmp.path().join(format!("run{p}_{serve}"));
            let limit = n.to_string();
            let mut args = util::FIG7_SIM_RUN.to_vec();
            args.extend(["--limit", &limit, "--no-progress", "--timings", "--out"]);
            let out_s = out.display().to_string();
            args.push(&out_s);
            let (lines, code) = if serve {
                args.extend(["--serve", "127.0.0.1:0"]);
                let mut s = spawn_collecting(&args, "live view: ");
                let viewers: Vec<_> = (0..20)
                    .map(|_| {
                        let addr = s.addr.clone();
                        std::thread::spawn(move || viewer(&addr))
                    })
                    .collect();
                let code = wait_exit(&mut s.child, 3600);
                let frames: usize = viewers.into_iter().map(|v| v.join().unwrap().frames).sum();
                eprintln!("  20 viewers fetched {frames} frames");
                (s.lines.try_iter().collect::<Vec<_>>(), code)
            } else {
                let o = util::run(&args);
                (
                    util::stderr(&o).lines().map(str::to_string).collect(),
                    o.status.code().unwrap_or(-1),
                )
            };
            assert_eq!(code, 0, "{lines:?}");
            let (k, wall, overhead_ms) = timings_of(&lines);
            let per = wall / k;
            eprintln!(
                "pair {p} {}: {k} setpoints, {per:.4} s per setpoint, controller overhead {overhead_ms:.3} ms",
                if serve { "--serve + 20 viewers" } else { "without --serve" }
            );
            rows.push((serve, per, overhead_ms));
        }
    }
    let mean = |serve: bool, f: fn(&(bool, f64, f64)) -> f64| {
        let v: Vec<f64> = rows.iter().filter(|r| r.0 == serve).map(f).collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    let (a, b) = (mean(false, |r| r.1), mean(true, |r| r.1));
    let (oa, ob) = (mean(false, |r| r.2), mean(true, |r| r.2));
    eprintln!(
        "mean over {pairs} pairs of {n} setpoints: {a:.4} s per setpoint without, {b:.4} s with --serve and 20 viewers ({:+.2} %); controller overhead {oa:.3} ms vs {ob:.3} ms",
        100.0 * (b - a) / a
    );
}

/// What a viewer saw.
#[derive(Default)]
struct Seen {
    frames: usize,
    last_state: Option<Value>,
    ended: bool,
}

/// A viewer: reads the event stream until it ends, fetching each pushed frame as the
/// page does.
fn viewer(addr: &str) -> Seen {
    let mut seen = Seen::default();
    let Ok(mut s) = TcpStream::connect(addr) else {
        return seen;
    };
    let _ = s.set_read_timeout(Some(Duration::from_secs(120)));
    let _ = write!(s, "GET /api/events HTTP/1.1\r\nHost: {addr}\r\n\r\n");
    let mut buf = Vec::new();
    let mut chunk = [0u8; 65536];
    let mut last_index = None;
    loop {
        match s.read(&mut chunk) {
            Ok(0) | Err(_) => return seen,
            Ok(k) => buf.extend_from_slice(&chunk[..k]),
        }
        while let Some(end) = buf.windows(2).position(|w| w == b"\n\n") {
            let block = String::from_utf8_lossy(&buf[..end]).into_owned();
            buf.drain(..end + 2);
            if block.contains("event: end") {
                seen.ended = true;
                return seen;
            }
            if let Some(data) = block.strip_prefix("event: state\ndata: ") {
                seen.last_state = serde_json::from_str(data).ok();
            }
            if let Some(data) = block.strip_prefix("event: evidence\ndata: ") {
                if let Ok(v) = serde_json::from_str::<Value>(data) {
                    let idx = v["evidence"]["index"].as_u64();
                    if idx.is_some() && idx != last_index {
                        last_index = idx;
                        if get(addr, "/api/frame.png").status == 200 {
                            seen.frames += 1;
                        }
                    }
                }
            }
        }
    }
}

/// The provisional verdict the live view shows (`serve --acceptance`) judges the run as
/// `report --acceptance` does: the same criteria, the same outcomes, the same values.
#[test]
fn provisional_verdict_matches_what_report_judges() {
    let tmp = tempfile::tempdir().unwrap();
    let run = finished_run(tmp.path(), 6);
    let criteria = util::root("experiments/acceptance_example.toml");
    let mut s = spawn_serve(
        &[&run],
        &[
            "--addr",
            "127.0.0.1:0",
            "--acceptance",
            criteria.to_str().unwrap(),
        ],
    );
    let mut live = Value::Null;
    wait_for(60, "the provisional verdict", || {
        live = state(&s.addr)["verdict"].clone();
        live["rows"].as_array().is_some_and(|r| !r.is_empty())
    });
    let _ = s.child.kill();
    let _ = s.child.wait();
    let report_dir = tmp.path().join("report");
    let o = util::run(&[
        "report",
        run.to_str().unwrap(),
        "--acceptance",
        criteria.to_str().unwrap(),
        "--allow-partial",
        "--out",
        report_dir.to_str().unwrap(),
    ]);
    assert!(
        o.status.code().is_some_and(|c| c == 0 || c == 1),
        "{}",
        util::stderr(&o)
    );
    let verdict: Value =
        serde_json::from_str(&std::fs::read_to_string(report_dir.join("verdict.json")).unwrap())
            .unwrap();
    let rows = live["rows"].as_array().unwrap();
    let judged = verdict["criteria"].as_array().unwrap();
    assert_eq!(rows.len(), judged.len(), "live {live}\nreport {verdict}");
    for row in rows {
        let metric = row["metric"].as_str().unwrap();
        let r = judged
            .iter()
            .find(|c| c["metric"] == metric)
            .unwrap_or_else(|| panic!("{metric} judged live but not by report"));
        assert_eq!(
            row["outcome"], r["outcome"],
            "{metric}: live {row}, report {r}"
        );
        if row["unit"] == r["unit"] {
            let (a, b) = (row["value"].as_f64(), r["value"].as_f64());
            if let (Some(a), Some(b)) = (a, b) {
                assert!(
                    (a - b).abs() <= 1e-9 * b.abs().max(1.0),
                    "{metric}: {a} vs {b}"
                );
            }
        }
    }
    assert!(live["overall"].is_string(), "{live}");
}

/// Issue 33, case 6: the loopback view answered any `Host` and `Origin`, so a page of
/// another site whose name was rebound to 127.0.0.1 (DNS rebinding) could read the
/// run and press Stop (the issue's curl got 202). Now: a foreign `Host` gets 421, a
/// foreign `Origin` 403, a Stop without the page's token 403, no answer carries CORS
/// headers, and the page's own Stop still stops the run.
#[test]
fn case6_a_foreign_host_or_origin_cannot_read_or_stop_a_loopback_view_and_the_stop_needs_its_token()
{
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let mut s = spawn_run(&out, 40, &["--serve", "127.0.0.1:0"]);
    wait_for(120, "a measured setpoint", || {
        state(&s.addr)["setpoints_done"].as_u64().unwrap_or(0) >= 1
    });
    let port = s.addr.rsplit(':').next().unwrap().to_string();
    let evil_host = format!("attacker.example:{port}");
    // The issue's curl.
    let r = request_as(
        &s.addr,
        &evil_host,
        "POST",
        "/api/stop",
        &[
            ("Origin", "http://attacker.example"),
            ("X-Tactbench-Stop", "confirm"),
        ],
    );
    assert_eq!(r.status, 421, "{}", r.text());
    assert!(
        r.text().contains("attacker.example") && r.text().contains("localhost"),
        "the refusal says what was asked and what is answered: {}",
        r.text()
    );
    // Nothing is readable under the rebound name (or another port).
    for host in [evil_host.as_str(), "127.0.0.1:1", "localhost"] {
        for path in [
            "/",
            "/api/state",
            "/api/runs",
            "/api/journal",
            "/api/events",
            "/api/frame.png",
            "/runs/0/frames/00000_0.png",
        ] {
            let r = request_as(&s.addr, host, "GET", path, &[]);
            assert_eq!(r.status, 421, "{host} {path}: {}", r.text());
            assert!(
                !r.text().contains("setpoints") && !r.text().contains("tactbench-token"),
                "{host} {path}"
            );
        }
    }
    // Another origin may neither read nor stop, even with the token.
    let token = page_token(&s.addr).expect("the page carries the view's token");
    assert_eq!(token.len(), 32);
    assert!(token.bytes().all(|b| b.is_ascii_hexdigit()));
    let other_port = format!("http://127.0.0.1:{}", port.parse::<u32>().unwrap() + 1);
    for origin in ["http://attacker.example", other_port.as_str(), "null"] {
        let r = request_as(
            &s.addr,
            &s.addr,
            "POST",
            "/api/stop",
            &[
                ("Origin", origin),
                ("X-Tactbench-Stop", "confirm"),
                ("X-Tactbench-Token", &token),
            ],
        );
        assert_eq!(r.status, 403, "{origin}: {}", r.text());
        let r = request_as(&s.addr, &s.addr, "GET", "/api/state", &[("Origin", origin)]);
        assert_eq!(r.status, 403, "{origin}: {}", r.text());
    }
    // The Stop needs the token, right.
    let wrong = "0".repeat(32);
    for extra in [vec![], vec![("X-Tactbench-Token", wrong.as_str())]] {
        let mut h = vec![("X-Tactbench-Stop", "confirm")];
        h.extend(extra);
        let r = request_as(&s.addr, &s.addr, "POST", "/api/stop", &h);
        assert_eq!(r.status, 403, "{h:?}: {}", r.text());
        assert!(r.text().contains("token"), "{}", r.text());
    }
    // No CORS: a preflight is refused and no answer allows another origin.
    let pre = request_as(
        &s.addr,
        &s.addr,
        "OPTIONS",
        "/api/stop",
        &[
            ("Access-Control-Request-Method", "POST"),
            ("Access-Control-Request-Headers", "x-tactbench-stop"),
        ],
    );
    assert!(pre.status >= 400, "{}", pre.status);
    for r in [pre, get(&s.addr, "/api/state"), get(&s.addr, "/")] {
        let head = r.head.to_ascii_lowercase();
        assert!(!head.contains("access-control-allow"), "{head}");
        assert!(
            head.contains("cross-origin-resource-policy: same-origin"),
            "{head}"
        );
    }
    // The loopback names are answered.
    for host in [
        format!("localhost:{port}"),
        format!("LocalHost:{port}"),
        format!("[::1]:{port}"),
        format!("127.0.0.1:{port}"),
    ] {
        assert_eq!(
            request_as(&s.addr, &host, "GET", "/api/state", &[]).status,
            200,
            "{host}"
        );
    }
    // None of it stopped the run; the page's own Stop (its origin, its token) does.
    assert!(s.child.try_wait().unwrap().is_none(), "the run was stopped");
    assert_eq!(state(&s.addr)["state"], "running");
    let own = format!("http://127.0.0.1:{port}");
    let r = request_as(
        &s.addr,
        &s.addr,
        "POST",
        "/api/stop",
        &[
            ("Origin", own.as_str()),
            ("X-Tactbench-Stop", "confirm"),
            ("X-Tactbench-Token", &token),
        ],
    );
    assert_eq!(r.status, 202, "{}", r.text());
    assert_eq!(wait_exit(&mut s.child, 120), 4);
}

/// Sets SO_LINGER 0: dropping the stream then resets the connection (RST).
fn reset_on_drop(s: &TcpStream) {
    use std::os::fd::AsRawFd;
    let l = libc::linger {
        l_onoff: 1,
        l_linger: 0,
    };
    // SAFETY: a valid socket and a `linger` of the size given.
    let rc = unsafe {
        libc::setsockopt(
            s.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_LINGER,
            (&l as *const libc::linger).cast(),
            std::mem::size_of::<libc::linger>() as libc::socklen_t,
        )
    };
    assert_eq!(rc, 0);
}

/// Issue 33, case 10: a client that reset its connection left a web-server thread's
/// panic and backtrace in the operator's terminal (`tiny_http` unwrapping the peer's
/// address of a connection already reset). Now it is a quiet close.
#[test]
fn case10_a_client_that_resets_its_connection_leaves_no_panic_in_the_log() {
    let tmp = tempfile::tempdir().unwrap();
    let run = finished_run(tmp.path(), 1);
    let s = spawn_serve(&[&run], &["--addr", "127.0.0.1:0"]);
    let Served {
        mut child,
        addr,
        lines,
        ..
    } = s;
    // Reset at once, after a moment, and after the first bytes of the answer.
    for mode in 0..3 {
        for path in [
            "/api/events",
            "/",
            "/api/state",
            "/api/frame.png",
            "/api/journal",
        ] {
            for _ in 0..10 {
                let mut c = TcpStream::connect(&addr).unwrap();
                reset_on_drop(&c);
                let _ = write!(c, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n");
                match mode {
                    1 => std::thread::sleep(Duration::from_millis(20)),
                    2 => {
                        let _ = c.set_read_timeout(Some(Duration::from_secs(5)));
                        let _ = c.read(&mut [0u8; 16]);
                    }
                    _ => {}
                }
                drop(c);
            }
        }
    }
    // Still serving.
    assert_eq!(get(&addr, "/api/state").status, 200);
    std::thread::sleep(Duration::from_millis(500));
    let _ = child.kill();
    let _ = child.wait();
    let log: Vec<String> = lines.iter().collect();
    assert!(
        !log.iter()
            .any(|l| l.contains("panicked") || l.contains("backtrace")),
        "{log:#?}"
    );
}

/// Issue 33, case 10: a journal row without finite force sums (a failed
/// reconstruction: NaN before issue 33, empty columns after) was plotted at 0 (its
/// NaN became `null`). Now it is left out of the plotted series, and counted.
#[test]
fn case10_the_live_plot_leaves_out_a_row_without_finite_force_sums() {
    let tmp = tempfile::tempdir().unwrap();
    let run = finished_run(tmp.path(), 3);
    let path = run.join("journal.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    let header: Vec<String> = lines[0].split(',').map(str::to_string).collect();
    let cols: Vec<usize> = ["fsum_x_n", "fsum_y_n", "fsum_z_n"]
        .iter()
        .map(|c| header.iter().position(|h| h == c).unwrap())
        .collect();
    for (line, value) in [(2, "NaN"), (3, "")] {
        let mut f: Vec<String> = lines[line].split(',').map(str::to_string).collect();
        assert_eq!(f.len(), header.len(), "a plain row: {}", lines[line]);
        for &c in &cols {
            f[c] = value.to_string();
        }
        lines[line] = f.join(",");
    }
    std::fs::write(&path, lines.join("\n") + "\n").unwrap();
    let mut v = tactbench::live::view::RunView::open(&run, None).unwrap();
    v.refresh();
    let series = v.series_json(0);
    let points = series["points"].as_array().unwrap();
    assert!(
        points.iter().all(|p| p
            .as_array()
            .unwrap()
            .iter()
            .all(|x| x.as_f64().is_some_and(f64::is_finite))),
        "every plotted value a finite number: {series}"
    );
    let indices: Vec<u64> = points
        .iter()
        .map(|p| p[0].as_f64().unwrap() as u64)
        .collect();
    assert_eq!(indices, vec![0], "{series}");
    // The NaN row is read and counted as not plotted (the empty one too, once the
    // journal reads empty force columns).
    let unplotted = series["unplotted"].as_u64().unwrap();
    assert!(unplotted >= 1, "{series}");
    assert_eq!(series["rows"].as_u64().unwrap(), 1 + unplotted, "{series}");
}

/// A page of another site for the browser test: tries to stop the run and read it.
const ATTACK_PAGE: &str = r#"<!doctype html><html><body><p>another site</p><script>
const T = "TARGET", out = {};
const attempt = async (name, f) => { try { out[name] = await f(); } catch (e) { out[name] = "blocked"; } };
(async () => {
  await attempt("stop_with_header", async () => (await fetch(T + "/api/stop", { method: "POST", headers: { "X-Tactbench-Stop": "confirm" } })).status);
  await attempt("stop_simple", async () => (await fetch(T + "/api/stop", { method: "POST", mode: "no-cors" })).type);
  await attempt("state", async () => await (await fetch(T + "/api/state")).text());
  await attempt("journal", async () => await (await fetch(T + "/api/journal")).text());
  await attempt("page", async () => await (await fetch(T + "/")).text());
  window.RESULT = JSON.stringify(out);
})();
</script></body></html>"#;

/// What a script of a rebound name (its origin `http://attacker.example:PORT`, the
/// name resolving to 127.0.0.1) tries: read the page for its token, read the state,
/// press Stop.
const REBOUND_SCRIPT: &str = r#"(async () => {
  const out = { origin: location.origin };
  const page = await fetch("/").then(r => r.text()).catch(() => "");
  const m = page.match(/name="tactbench-token" content="([0-9a-f]+)"/);
  out.token = m ? m[1] : null;
  out.state = await fetch("/api/state").then(r => r.status + " " + r.headers.get("content-type")).catch(e => "blocked");
  const h = { "X-Tactbench-Stop": "confirm" };
  if (out.token) h["X-Tactbench-Token"] = out.token;
  out.stop = await fetch("/api/stop", { method: "POST", headers: h }).then(r => r.status).catch(e => "blocked");
  return JSON.stringify(out);
})()"#;

/// Issue 33, case 6 in a browser: a page served from another origin (another port of
/// 127.0.0.1) and a page under a rebound name (`attacker.example`, resolved to
/// 127.0.0.1 by Chromium's `--host-resolver-rules`: what DNS rebinding achieves) can
/// neither stop the run nor read it; the view's own page still stops it.
#[test]
fn case6_headless_chromium_a_page_of_another_origin_or_a_rebound_name_cannot_stop_or_read_the_run()
{
    let Some(path) = chromium() else {
        eprintln!("SKIPPED: no /usr/bin/chromium (apt-get install chromium; .ci/run installs it)");
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let shots = screenshot_dir(tmp.path());
    std::fs::create_dir_all(&shots).unwrap();
    let out = tmp.path().join("run");
    let mut s = spawn_run(&out, 40, &["--serve", "127.0.0.1:0"]);
    wait_for(120, "a measured setpoint", || {
        state(&s.addr)["setpoints_done"].as_u64().unwrap_or(0) >= 1
    });
    let port = s.addr.rsplit(':').next().unwrap().to_string();
    // The other site: another port of 127.0.0.1, so another origin.
    let evil = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let evil_addr = evil.local_addr().unwrap();
    let html = ATTACK_PAGE.replace("TARGET", &format!("http://127.0.0.1:{port}"));
    std::thread::spawn(move || {
        for c in evil.incoming() {
            let Ok(mut c) = c else { break };
            let _ = c.set_read_timeout(Some(Duration::from_secs(5)));
            let mut head = Vec::new();
            let mut b = [0u8; 1024];
            while !head.windows(4).any(|w| w == b"\r\n\r\n") {
                match c.read(&mut b) {
                    Ok(0) | Err(_) => break,
                    Ok(k) => head.extend_from_slice(&b[..k]),
                }
            }
            let _ = write!(
                c,
                "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{html}",
                html.len()
            );
        }
    });
    // No automatic https:// attempt first for the made-up name (plain http, as a real
    // rebinding page would be served).
    let mut b = Browser::launch_with(
        &path,
        &[
            "--host-resolver-rules=MAP attacker.example 127.0.0.1",
            "--disable-features=HttpsUpgrades",
        ],
    );
    b.open(&format!("http://{evil_addr}/"));
    wait_for(60, "the other site's attempts", || {
        b.eval("window.RESULT || null").is_string()
    });
    let tried: Value = serde_json::from_str(b.eval("window.RESULT").as_str().unwrap()).unwrap();
    for k in ["stop_with_header", "state", "journal", "page"] {
        assert_eq!(tried[k], "blocked", "{k}: {tried}");
    }
    assert!(
        s.child.try_wait().unwrap().is_none(),
        "stopped by another site: {tried}"
    );
    assert_eq!(state(&s.addr)["state"], "running", "{tried}");

    // A rebound name: a page whose origin is attacker.example:PORT reaches the view.
    b.open(&format!("http://attacker.example:{port}/"));
    wait_for(30, "the rebound page", || {
        b.eval("document.readyState") == "complete"
    });
    let shown = b.eval("document.body ? document.body.innerText : ''");
    assert!(
        !shown.as_str().unwrap_or("").contains("tactbench live view"),
        "the live view's page was served under a rebound name"
    );
    let tried: Value = serde_json::from_str(b.eval(REBOUND_SCRIPT).as_str().unwrap()).unwrap();
    assert_eq!(
        tried["origin"],
        format!("http://attacker.example:{port}"),
        "{tried}"
    );
    assert_eq!(tried["token"], Value::Null, "{tried}");
    assert!(
        tried["state"].as_str().unwrap().starts_with("421"),
        "{tried}"
    );
    assert_eq!(tried["stop"], 421, "{tried}");
    assert!(
        s.child.try_wait().unwrap().is_none(),
        "stopped under a rebound name: {tried}"
    );
    assert_eq!(state(&s.addr)["state"], "running", "{tried}");

    // The view's own page: its Stop button stops the run.
    b.open(&s.url);
    wait_for(60, "the page's Stop enabled", || {
        b.eval("(e => !!e && !e.disabled)(document.getElementById('r0-stop'))") == true
    });
    b.screenshot(&shots.join("live_before_stop.png"));
    b.eval("window.confirm = () => true; document.getElementById('r0-stop').click(); true");
    wait_for(30, "the button to say Stopping", || {
        b.text("r0-stop").as_deref() == Some("Stopping…")
    });
    b.screenshot(&shots.join("live_stopping.png"));
    assert_eq!(wait_exit(&mut s.child, 120), 4);
    let m: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["status"], "interrupted");
}
