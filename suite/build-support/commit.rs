// Shared by the build scripts that record the git commit their crate is built from (`include!`d: a build script
// cannot depend on a workspace crate without compiling it twice). Sets `DSRL_BUILD_COMMIT` to the commit (12 hex
// digits), with `-modified` when one of `sources` differs from it, or `unknown` outside a git checkout; computed
// again whenever the commit moves or one of those sources changes, so a modified build is never labelled as the
// commit's.

fn git(args: &[&str]) -> Option<String> {
    let out = std::process::Command::new("git").args(args).output().ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_owned())
}

/// `sources`: what shapes the crate's output, relative to the crate's folder (where cargo runs the script).
fn record_build_commit(sources: &[&str]) {
    for source in sources {
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
            let status = [&["status", "--porcelain", "--untracked-files=no", "--"][..], sources].concat();
            let modified = git(&status).is_some_and(|s| !s.is_empty());
            format!("{commit}{}", if modified { "-modified" } else { "" })
        }
        None => "unknown".to_owned(),
    };
    println!("cargo:rustc-env=DSRL_BUILD_COMMIT={commit}");
}
