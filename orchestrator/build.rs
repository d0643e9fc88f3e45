//! Records the git revision the binary was built from, for run manifests.
use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok().filter(|o| o.status.success())?;
    String::from_utf8(out.stdout).ok().map(|s| s.trim().to_string())
}

fn main() {
    let rev = git(&["rev-parse", "--short=12", "HEAD"]).unwrap_or_else(|| "unknown".into());
    println!("cargo:rustc-env=GEESE_GIT_REV={rev}");
    // Rebuild when HEAD moves; only name files that exist, or cargo reruns every time.
    if let Some(dir) = git(&["rev-parse", "--absolute-git-dir"]) {
        let head = std::path::Path::new(&dir).join("HEAD");
        if head.exists() {
            println!("cargo:rerun-if-changed={}", head.display());
        }
        if let Some(r) = git(&["symbolic-ref", "-q", "HEAD"]) {
            let reff = std::path::Path::new(&dir).join(&r);
            if reff.exists() {
                println!("cargo:rerun-if-changed={}", reff.display());
            }
        }
    }
    println!("cargo:rerun-if-changed=build.rs");
}
