//! Which simulator Python a worker runs. The workers import the `dsrl_sim` package from a folder when they start
//! rather than compiling it in, so a binary built at one commit can play episodes with other Python. Each worker
//! reports the digest of the package it imported in Health's `version` (`dsrl-sim-worker 0.1.0 (dsrl_sim
//! 0123456789ab)`); what a binary built (its label: `<crate> <version> (git <commit>)`) bakes in is compared here.

use crate::WorkerStatus;

/// `label` (`<name> <version> (git <commit>)`, or the same with `-modified`), marked `-modified` when a healthy worker
/// of `workers` reports a `dsrl_sim` package other than `package` (the first 12 hex digits of the digest the build
/// baked) or does not say which it runs. Unhealthy workers play nothing and do not count.
pub fn label_with_workers_python(label: &str, workers: &[WorkerStatus], package: &str) -> String {
    let ours = format!("(dsrl_sim {package})");
    let other = workers
        .iter()
        .filter(|w| w.healthy)
        .any(|w| !w.version.as_deref().is_some_and(|v| v.ends_with(&ours)));
    mark_modified(label, other)
}

/// `label` with `-modified` before its closing parenthesis when `modified` (once).
pub fn mark_modified(label: &str, modified: bool) -> String {
    match label.strip_suffix(')') {
        Some(open) if modified && !open.ends_with("-modified") => format!("{open}-modified)"),
        _ => label.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn worker(healthy: bool, version: Option<&str>) -> WorkerStatus {
        WorkerStatus {
            name: "w".into(),
            kind: "local".into(),
            address: None,
            pid: None,
            healthy,
            sessions: 0,
            envs: 0,
            max_envs: 32,
            version: version.map(str::to_owned),
            restarts: 0,
            last_error: None,
        }
    }

    /// A result played where a worker's Python package differs from the build's (or a worker does not say which it
    /// has) is not the build's commit: it carries `-modified`, once; unhealthy workers do not count.
    #[test]
    fn a_worker_with_other_python_marks_the_label() {
        let (label, package) = ("dsrl-x 0.1.0 (git 0123456789ab)", "aaaaaaaaaaaa");
        let ours = "dsrl-sim-worker 0.1.0 (dsrl_sim aaaaaaaaaaaa)";
        let same = [worker(true, Some(ours)), worker(false, Some("dsrl-sim-worker 0.1.0"))];
        assert_eq!(label_with_workers_python(label, &same, package), label);
        assert_eq!(label_with_workers_python(label, &[], package), label);
        for other in ["dsrl-sim-worker 0.1.0 (dsrl_sim bbbbbbbbbbbb)", "dsrl-sim-worker 0.1.0"] {
            let workers = [worker(true, Some(ours)), worker(true, Some(other))];
            assert_eq!(
                label_with_workers_python(label, &workers, package),
                "dsrl-x 0.1.0 (git 0123456789ab-modified)",
                "{other}"
            );
        }
        assert_eq!(
            label_with_workers_python(label, &[worker(true, None)], package),
            "dsrl-x 0.1.0 (git 0123456789ab-modified)"
        );
        let modified = "dsrl-x 0.1.0 (git 0123456789ab-modified)";
        assert_eq!(
            label_with_workers_python(modified, &[worker(true, None)], package),
            modified
        );
        assert_eq!(mark_modified(label, false), label);
    }
}
