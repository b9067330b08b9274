//! Build script: records the git commit the binary is built from as the compile-time
//! variable `TACTBENCH_GIT_COMMIT` (manifest.json `software_commit`, verdict.json
//! `provenance.git_commit`). Outside a git checkout (a crates.io tarball, no `git`
//! installed) it is `unknown`. Reruns when HEAD moves (checkout, commit, merge).

use std::path::PathBuf;
use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    if !out.status.success() {
        return None;
    }
    let s = String::from_utf8(out.stdout).ok()?.trim().to_string();
    (!s.is_empty()).then_some(s)
}

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    let commit = git(&["rev-parse", "HEAD"]);
    if let Some(git_dir) = git(&["rev-parse", "--git-dir"]) {
        // In a worktree `.git` is a file; ask git where HEAD and the refs live.
        let git_dir = PathBuf::from(git_dir);
        let common = git(&["rev-parse", "--git-common-dir"])
            .map(PathBuf::from)
            .unwrap_or_else(|| git_dir.clone());
        let mut watch = vec![git_dir.join("HEAD")];
        if let Some(r) = git(&["symbolic-ref", "-q", "HEAD"]) {
            watch.push(common.join(r));
        }
        watch.push(common.join("packed-refs"));
        for p in watch.into_iter().filter(|p| p.exists()) {
            println!("cargo:rerun-if-changed={}", p.display());
        }
    }
    let value = commit.unwrap_or_else(|| "unknown".to_string());
    println!("cargo:rustc-env=TACTBENCH_GIT_COMMIT={value}");
}
