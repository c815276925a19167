//! Records the git commit this crate is built from, for the provenance of every dataset it makes: a recipe and its
//! seed rebuild a dataset exactly only with the same expert code (BallRun rebuilt from its recipe after the expert
//! code had changed gave another build), so the provenance names the code as well as the recipe.
//!
//! `DSRL_BUILD_COMMIT` is the commit (12 hex digits), with `-modified` when the sources that shape the data differ
//! from it, or `unknown` outside a git checkout. It is computed again whenever the commit moves or one of those
//! sources changes, so a modified build is never labelled as the commit's.

use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_owned())
}

/// What shapes the data this crate makes: its source, the sources of the crates it builds on, the locked
/// dependencies. Relative to this crate's folder, where cargo runs the script.
const SOURCES: [&str; 7] = [
    "src",
    "../suite/src",
    "../policy/src",
    "../sim/src",
    "../evaluation/src",
    "../proto/src",
    "../Cargo.lock",
];

fn main() {
    for source in SOURCES {
        println!("cargo:rerun-if-changed={source}");
    }
    let commit = match git(&["rev-parse", "--short=12", "HEAD"]) {
        Some(commit) => {
            // The commit moves with HEAD (a checkout) or with the branch it names (a commit): watch the files that
            // hold them, where they exist (a path that does not exist would rerun this on every build).
            let mut watched = vec!["HEAD".to_owned(), "packed-refs".to_owned()];
            watched.extend(git(&["symbolic-ref", "-q", "HEAD"]));
            for path in watched {
                if let Some(file) = git(&["rev-parse", "--path-format=absolute", "--git-path", &path])
                    .filter(|f| std::path::Path::new(f).exists())
                {
                    println!("cargo:rerun-if-changed={file}");
                }
            }
            let status = [&["status", "--porcelain", "--untracked-files=no", "--"][..], &SOURCES].concat();
            let modified = git(&status).is_some_and(|s| !s.is_empty());
            format!("{commit}{}", if modified { "-modified" } else { "" })
        }
        None => "unknown".to_owned(),
    };
    println!("cargo:rustc-env=DSRL_BUILD_COMMIT={commit}");
}
