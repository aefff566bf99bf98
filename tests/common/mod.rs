//! Helpers shared by the command-line integration tests: run `rtvtk`, record a trace, read a
//! query's single value. Each test binary uses some of them.
#![allow(dead_code, clippy::unwrap_used)]

use std::path::Path;
use std::process::{Command, Output};

pub mod snapshot;

/// Starts `rtvtk ARGS` as a child process (its stderr shown with a failing test's output); the
/// child and the first line it prints (a server's address).
pub fn start_with_first_line(args: &[&str]) -> (std::process::Child, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_rtvtk"));
    cmd.args(args);
    spawn_with_first_line(&mut cmd)
}

/// Starts `cmd` with its stdout piped (its stderr shown with a failing test's output); the child
/// and the first line it prints. A child that prints nothing within 60 s is killed and the test
/// fails naming it (a hung server or display never hangs the test).
pub fn spawn_with_first_line(cmd: &mut Command) -> (std::process::Child, String) {
    use std::io::BufRead;
    let name = cmd.get_program().to_string_lossy().to_string();
    let mut child = cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::inherit()).spawn().unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = std::io::BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    match rx.recv_timeout(std::time::Duration::from_secs(60)) {
        Ok(line) => (child, line),
        Err(_) => {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{name} printed nothing within 60 s (killed)");
        }
    }
}

/// Waits for `child` at most `limit`; kills it and fails the test naming `what` past that.
pub fn wait_at_most(
    child: &mut std::process::Child,
    limit: std::time::Duration,
    what: &str,
) -> std::process::ExitStatus {
    let t0 = std::time::Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{what} did not finish within {} s (killed)", limit.as_secs());
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// Runs `rtvtk ARGS`.
pub fn rtvtk(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rtvtk")).args(args).output().unwrap()
}

/// Runs `rtvtk ARGS`, asserting success; its stdout.
pub fn ok(args: &[&str]) -> String {
    let out = rtvtk(args);
    assert!(out.status.success(), "rtvtk {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).to_string()
}

/// `rtvtk record ARGS --out DIR`, asserting success.
pub fn record(dir: &Path, args: &[&str]) {
    ok(&[&["record"], args, &["--out", dir.to_str().unwrap()]].concat());
}

/// The single value `rtvtk sql DATASETS QUERY` prints (CSV, header skipped).
pub fn scalar(datasets: &[&str], query: &str) -> String {
    let out = ok(&[&["sql"], datasets, &[query, "--format", "csv"]].concat());
    out.lines().nth(1).unwrap_or_default().trim().to_string()
}

/// The paper's bug as a query: shadow rays that point at no emitter.
pub const WRONG_SHADOWS: &str = "SELECT count(*) FROM rays WHERE kind = 'shadow' \
     AND NOT aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)";

/// Records `DIR/good` (a correct trace) and `DIR/bad` (with `--inject-bug shadow-dir`), both with
/// `settings`; their paths.
pub fn record_good_and_bad(dir: &Path, settings: &[&str]) -> (std::path::PathBuf, std::path::PathBuf) {
    let (good, bad) = (dir.join("good"), dir.join("bad"));
    record(&good, settings);
    record(&bad, &[settings, &["--inject-bug", "shadow-dir"]].concat());
    (good, bad)
}

/// Rust source `text` without its test-only items: each `#[cfg(test)]` item (a `mod tests { .. }`,
/// a helper function, a `use`) is cut out, from the attribute to the item's end (its closing
/// brace, or its `;`), and the code after it is kept. Braces inside string and char literals and
/// comments are not counted.
pub fn without_test_items(text: &str) -> String {
    const ATTR: &str = "#[cfg(test)]";
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(at) = rest.find(ATTR) {
        out.push_str(&rest[..at]);
        let item = &rest[at + ATTR.len()..];
        rest = &item[item_end(item)..];
    }
    out.push_str(rest);
    out
}

/// The byte length of the item at the start of `s` (after an attribute): up to its first `;` at
/// brace depth 0, or the brace that closes its first `{`.
fn item_end(s: &str) -> usize {
    let b = s.as_bytes();
    let (mut depth, mut i) = (0usize, 0usize);
    while i < b.len() {
        match b[i] {
            b'/' if b.get(i + 1) == Some(&b'/') => {
                while i < b.len() && b[i] != b'\n' {
                    i += 1;
                }
            }
            b'/' if b.get(i + 1) == Some(&b'*') => {
                i += 2;
                while i + 1 < b.len() && !(b[i] == b'*' && b[i + 1] == b'/') {
                    i += 1;
                }
                i += 1;
            }
            b'"' => {
                i += 1;
                while i < b.len() && b[i] != b'"' {
                    i += if b[i] == b'\\' { 2 } else { 1 };
                }
            }
            // A char literal ('{', '\''), not a lifetime ('a).
            b'\'' if b.get(i + 2) == Some(&b'\'') => i += 2,
            b'\'' if b.get(i + 1) == Some(&b'\\') => {
                i += 2;
                while i < b.len() && b[i] != b'\'' {
                    i += 1;
                }
            }
            b'{' => depth += 1,
            b'}' => {
                depth = depth.saturating_sub(1);
                if depth == 0 {
                    return i + 1;
                }
            }
            b';' if depth == 0 => return i + 1,
            _ => {}
        }
        i += 1;
    }
    b.len()
}
