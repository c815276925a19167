//! Where uploads are parsed. Uploads are untrusted and HDF5 is parsed by libhdf5, a C library: a hostile file
//! could crash it or make it allocate without bound. The `dsrl-server` binary therefore converts every upload in
//! a child process (`dsrl-server convert`, hidden) under an address-space limit, so the worst a file can do is
//! fail its own request. In-process conversion exists for tests that run the server inside the test binary.

use std::path::{Path, PathBuf};

use dsrl_suite::convert::{Converted, ImportError, SourceFormat, import_file};
use dsrl_suite::{ObservationSpace, Task};
use serde::{Deserialize, Serialize};

use crate::error::ApiError;

#[derive(Debug, Clone)]
pub enum Converter {
    InProcess,
    /// `program convert --task T --observation-space S --memory-limit N IN OUT`, answering one JSON line.
    Subprocess {
        program: PathBuf,
        memory_limit_bytes: u64,
    },
}

/// The child's answer on stdout.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ConvertReply {
    Converted {
        format: SourceFormat,
        converted: Converted,
    },
    /// The upload is not a valid dataset: the message names the problem.
    Rejected {
        message: String,
    },
    /// A local I/O failure: not the uploader's fault.
    Failed {
        message: String,
    },
}

impl ConvertReply {
    /// Runs the conversion here; what the child process does.
    pub fn run(source: &Path, task: &Task, space: ObservationSpace, out: &Path) -> ConvertReply {
        match import_file(source, task, space, out) {
            Ok((format, converted)) => ConvertReply::Converted { format, converted },
            Err(ImportError::Io(e)) => ConvertReply::Failed { message: e.to_string() },
            Err(invalid) => ConvertReply::Rejected {
                message: invalid.to_string(),
            },
        }
    }

    fn into_result(self) -> Result<(SourceFormat, Converted), ApiError> {
        match self {
            ConvertReply::Converted { format, converted } => Ok((format, converted)),
            ConvertReply::Rejected { message } => Err(ApiError::InvalidUpload(message)),
            ConvertReply::Failed { message } => Err(ApiError::Internal(format!("converting the upload: {message}"))),
        }
    }
}

impl Converter {
    pub async fn convert(
        &self,
        source: &Path,
        task: &Task,
        space: ObservationSpace,
        out: &Path,
    ) -> Result<(SourceFormat, Converted), ApiError> {
        match self {
            Converter::InProcess => {
                let (source, out, task) = (source.to_owned(), out.to_owned(), task.clone());
                tokio::task::spawn_blocking(move || ConvertReply::run(&source, &task, space, &out))
                    .await
                    .map_err(ApiError::internal)?
                    .into_result()
            }
            Converter::Subprocess {
                program,
                memory_limit_bytes,
            } => {
                // The child exits when its standard input closes (`exit_when_stdin_closes`): the pipe's write end
                // is held here until the answer is read, and the kernel closes it when this process dies, even by
                // SIGKILL, so no converter outlives the server.
                let mut child = tokio::process::Command::new(program)
                    .arg("convert")
                    .args(["--task", task.id.as_str(), "--observation-space", space.as_str()])
                    .args(["--memory-limit", &memory_limit_bytes.to_string()])
                    .arg(source)
                    .arg(out)
                    .stdin(std::process::Stdio::piped())
                    .stdout(std::process::Stdio::piped())
                    .stderr(std::process::Stdio::piped())
                    .kill_on_drop(true)
                    .spawn()
                    .map_err(|e| ApiError::Internal(format!("starting the converter {}: {e}", program.display())))?;
                let lifeline = child.stdin.take();
                let output = child
                    .wait_with_output()
                    .await
                    .map_err(|e| ApiError::Internal(format!("waiting for the converter: {e}")))?;
                drop(lifeline);
                if !output.status.success() {
                    let stderr = String::from_utf8_lossy(&output.stderr);
                    tracing::warn!(status = %output.status, stderr = %stderr.trim(), "converter process died");
                    return Err(ApiError::InvalidUpload(format!(
                        "the file could not be read safely: the converter process died ({})",
                        output.status
                    )));
                }
                let reply: ConvertReply = serde_json::from_slice(&output.stdout)
                    .map_err(|e| ApiError::Internal(format!("unreadable converter reply: {e}")))?;
                reply.into_result()
            }
        }
    }
}

/// In a child process: exits as soon as standard input reaches end of file, which happens when the parent closes
/// its end of the pipe or dies (the kernel closes a killed process's descriptors). A watcher thread does it, so
/// the exit happens even while the main thread is blocked in a read of the upload.
pub fn exit_when_stdin_closes() {
    std::thread::spawn(|| {
        let _ = std::io::copy(&mut std::io::stdin().lock(), &mut std::io::sink());
        std::process::exit(3);
    });
}
