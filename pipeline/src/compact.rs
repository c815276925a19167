//! Rewriting a dataset in the compact form the starters are committed in (`dsrl_suite::parquet_file`), row for
//! row: the starters cut before that form existed hold `next_observations` and list-form observations, about
//! twice the bytes. Ingest of the result gives the same canonical file, so the hosted version id does not move;
//! that is checked before anything is replaced, so a rewrite either keeps the version or writes nothing.

use std::path::{Path, PathBuf};

use anyhow::Context;
use dsrl_suite::convert::{import_file, join_compact_parts, parse_part_file_name, part_file_name, split_compact};
use dsrl_suite::{ObservationSpace, Task, VersionId};

/// What a rewrite produced.
#[derive(Debug, serde::Serialize)]
pub struct Compacted {
    /// The version id of the input, and of the output (checked equal).
    pub version: VersionId,
    pub episodes: usize,
    /// The input's files and their total size.
    pub replaced: Vec<PathBuf>,
    pub bytes_before: u64,
    /// The files written, in order, with their sizes.
    pub files: Vec<(PathBuf, u64)>,
    pub bytes_after: u64,
}

/// Rewrites the dataset `inputs` (one file, or a starter's parts in order) in the compact form as `parts` files
/// of whole episodes in `out_dir`. Where `out_dir` is the inputs' folder, the inputs are replaced (a part file
/// the new layout does not reuse is removed). The dataset keeps its name (`<stem>.parquet`, or its parts' names);
/// a `<name>.provenance.json` beside the inputs is copied along when `out_dir` is another folder.
pub fn rewrite(task: &Task, inputs: &[PathBuf], out_dir: &Path, parts: usize) -> anyhow::Result<Compacted> {
    anyhow::ensure!(!inputs.is_empty(), "no dataset file given");
    anyhow::ensure!(parts >= 1, "--parts must be at least 1");
    let name = dataset_name(inputs)?;
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    // Scratch beside the output, so the final renames stay on one file system.
    let scratch = tempfile::Builder::new()
        .prefix(".dsrl-compact-")
        .tempdir_in(out_dir)
        .with_context(|| format!("creating a scratch folder in {}", out_dir.display()))?;
    let space = ObservationSpace::Simulator;

    let canonical_of = |files: &[PathBuf], tag: &str| -> anyhow::Result<dsrl_suite::convert::Converted> {
        let source = match files {
            [one] => one.clone(),
            parts => {
                let joined = scratch.path().join(format!("{tag}-joined.parquet"));
                join_compact_parts(task, space, parts, &joined)
                    .with_context(|| format!("joining the parts of {name}"))?;
                joined
            }
        };
        let canonical = scratch.path().join(format!("{tag}-canonical.parquet"));
        let (_, converted) = import_file(&source, task, space, &canonical)
            .with_context(|| format!("reading {} as a dataset of {}", source.display(), task.id))?;
        Ok(converted)
    };

    let before = canonical_of(inputs, "before")?;
    let names: Vec<String> = if parts == 1 {
        vec![name.clone()]
    } else {
        (1..=parts).map(|i| part_file_name(&name, i, parts)).collect()
    };
    let written: Vec<PathBuf> = names.iter().map(|n| scratch.path().join(n)).collect();
    split_compact(
        task,
        space,
        &scratch.path().join("before-canonical.parquet"),
        &before.episode_index,
        &written,
    )
    .with_context(|| format!("writing {name} in the compact form"))?;
    let after = canonical_of(&written, "after")?;
    anyhow::ensure!(
        after.version == before.version,
        "the compact form of {name} would ingest as version {} where the input is {}; nothing was replaced",
        after.version,
        before.version
    );

    let bytes_before = total_size(inputs)?;
    let input_dir = inputs[0].parent().unwrap_or(Path::new("."));
    let in_place = same_dir(input_dir, out_dir)?;
    if !in_place {
        let provenance = input_dir.join(format!("{name}.provenance.json"));
        if provenance.is_file() {
            std::fs::copy(&provenance, out_dir.join(format!("{name}.provenance.json")))?;
        }
    }
    let mut files = Vec::with_capacity(written.len());
    for (from, file_name) in written.iter().zip(&names) {
        let to = out_dir.join(file_name);
        std::fs::rename(from, &to).with_context(|| format!("moving the result to {}", to.display()))?;
        files.push((to.clone(), std::fs::metadata(&to)?.len()));
    }
    if in_place {
        for input in inputs {
            if !names.iter().any(|n| input.file_name().is_some_and(|f| f == n.as_str())) {
                std::fs::remove_file(input).with_context(|| format!("removing {}", input.display()))?;
            }
        }
    }
    Ok(Compacted {
        version: before.version,
        episodes: before.episode_index.len(),
        replaced: inputs.to_vec(),
        bytes_before,
        bytes_after: files.iter().map(|(_, size)| size).sum(),
        files,
    })
}

/// The name the inputs are known by: the file's, or the name the parts share (each part named once, in order).
fn dataset_name(inputs: &[PathBuf]) -> anyhow::Result<String> {
    let file_name = |p: &PathBuf| {
        p.file_name()
            .and_then(|n| n.to_str())
            .map(str::to_owned)
            .with_context(|| format!("{} is not a file name", p.display()))
    };
    if let [one] = inputs {
        let name = file_name(one)?;
        return Ok(match parse_part_file_name(&name) {
            Some((whole, 1, 1)) => whole,
            _ => name,
        });
    }
    let mut whole_name = None;
    for (i, input) in inputs.iter().enumerate() {
        let name = file_name(input)?;
        let (whole, index, count) = parse_part_file_name(&name)
            .with_context(|| format!("{name}: several files are joined only as parts, <stem>.part-I-of-N.parquet"))?;
        anyhow::ensure!(
            index == i + 1 && count == inputs.len() && whole_name.as_ref().is_none_or(|w| *w == whole),
            "{name}: give the {} parts of one dataset, in order",
            inputs.len()
        );
        whole_name = Some(whole);
    }
    Ok(whole_name.expect("at least two inputs"))
}

fn total_size(files: &[PathBuf]) -> std::io::Result<u64> {
    files.iter().try_fold(0, |sum, f| Ok(sum + std::fs::metadata(f)?.len()))
}

fn same_dir(a: &Path, b: &Path) -> std::io::Result<bool> {
    let canonical = |p: &Path| std::fs::canonicalize(if p.as_os_str().is_empty() { Path::new(".") } else { p });
    Ok(canonical(a)? == canonical(b)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paths(names: &[&str]) -> Vec<PathBuf> {
        names.iter().map(|n| PathBuf::from("starter/T").join(n)).collect()
    }

    #[test]
    fn a_dataset_is_named_by_its_file_or_by_the_name_its_parts_share() {
        assert_eq!(dataset_name(&paths(&["a-80-5.parquet"])).unwrap(), "a-80-5.parquet");
        assert_eq!(
            dataset_name(&paths(&["a-80-5.part-1-of-1.parquet"])).unwrap(),
            "a-80-5.parquet"
        );
        assert_eq!(
            dataset_name(&paths(&["a-80-5.part-1-of-2.parquet", "a-80-5.part-2-of-2.parquet"])).unwrap(),
            "a-80-5.parquet"
        );
        for wrong in [
            &["a-80-5.part-2-of-2.parquet", "a-80-5.part-1-of-2.parquet"][..],
            &["a-80-5.part-1-of-3.parquet", "a-80-5.part-2-of-3.parquet"],
            &["a-80-5.part-1-of-2.parquet", "b-80-5.part-2-of-2.parquet"],
            &["a-80-5.parquet", "b-80-5.parquet"],
        ] {
            let err = dataset_name(&paths(wrong)).unwrap_err().to_string();
            assert!(err.contains("parts"), "{wrong:?}: {err}");
        }
    }
}
