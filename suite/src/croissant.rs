//! A hosted version described in Croissant (MLCommons' JSON-LD metadata format for ML datasets, which dataset
//! catalogs read and the NeurIPS datasets track asks for): the dataset, its one Parquet file (URL, sha256, size),
//! the columns as one record set of typed fields, the license, and how it was built (its provenance). Served beside
//! the manifest (`.../versions/{version}/croissant.json`); an end-to-end test validates it with `mlcroissant`.

use serde_json::{Value, json};

use crate::catalog::Task;
use crate::manifest::{Manifest, Provenance};

/// The Croissant version this describes to.
pub const CONFORMS_TO: &str = "http://mlcommons.org/croissant/1.0";

/// The JSON-LD context Croissant 1.0 documents use.
fn context() -> Value {
    json!({
        "@language": "en",
        "@vocab": "https://schema.org/",
        "sc": "https://schema.org/",
        "cr": "http://mlcommons.org/croissant/",
        "rai": "http://mlcommons.org/croissant/RAI/",
        "dct": "http://purl.org/dc/terms/",
        "citeAs": "cr:citeAs",
        "column": "cr:column",
        "conformsTo": "dct:conformsTo",
        "data": {"@id": "cr:data", "@type": "@json"},
        "dataType": {"@id": "cr:dataType", "@type": "@vocab"},
        "examples": {"@id": "cr:examples", "@type": "@json"},
        "extract": "cr:extract",
        "field": "cr:field",
        "fileObject": "cr:fileObject",
        "fileProperty": "cr:fileProperty",
        "fileSet": "cr:fileSet",
        "format": "cr:format",
        "includes": "cr:includes",
        "isLiveDataset": "cr:isLiveDataset",
        "jsonPath": "cr:jsonPath",
        "key": "cr:key",
        "md5": "cr:md5",
        "parentField": "cr:parentField",
        "path": "cr:path",
        "recordSet": "cr:recordSet",
        "references": "cr:references",
        "regex": "cr:regex",
        "repeated": "cr:repeated",
        "replace": "cr:replace",
        "separator": "cr:separator",
        "source": "cr:source",
        "subField": "cr:subField",
        "transform": "cr:transform"
    })
}

/// The Parquet columns: name, Croissant type, whether each value is a list (of the width given), what it holds.
fn columns(task: &Task) -> Vec<(&'static str, &'static str, Option<u32>, String)> {
    let obs = task.obs_dim;
    let act = task.act_dim;
    vec![
        (
            "episode",
            "sc:Integer",
            None,
            "the trajectory's number, from 0 in file order".into(),
        ),
        (
            "step",
            "sc:Integer",
            None,
            "the transition's step within its trajectory, from 0".into(),
        ),
        (
            "observations",
            "sc:Float",
            Some(obs),
            format!("the observation ({obs} float32 features)"),
        ),
        (
            "next_observations",
            "sc:Float",
            Some(obs),
            format!("the next observation ({obs} float32 features)"),
        ),
        (
            "actions",
            "sc:Float",
            Some(act),
            format!("the action the simulator applied ({act} float32)"),
        ),
        ("rewards", "sc:Float", None, "the step's reward (float32)".into()),
        ("costs", "sc:Float", None, "the step's cost (float32)".into()),
        (
            "terminals",
            "sc:Boolean",
            None,
            "the episode ended in a terminal state".into(),
        ),
        (
            "timeouts",
            "sc:Boolean",
            None,
            "the episode ended at the horizon".into(),
        ),
    ]
}

/// How the version was built, in a sentence and as the provenance record itself.
fn collection(provenance: &Provenance) -> String {
    let record = serde_json::to_string(provenance).unwrap_or_default();
    match provenance {
        Provenance::Recipe {
            recipe, code_version, ..
        } => format!(
            "Built on the real simulators by the dsrl data recipe {recipe} ({code_version}): a PPO-Lagrangian \
             expert trained under a moving cost limit (Bullet-Safety-Gym, Safety-Gymnasium) or a noisy IDM driver \
             sweep (MetaDrive), every episode offered to FSRL's trajectory buffer and DSRL's final grid filter, as \
             DSRL collected its datasets. Provenance: {record}"
        ),
        Provenance::Import { .. } => format!("Converted from an uploaded file. Provenance: {record}"),
        Provenance::Filter { .. } => {
            format!("Derived from another hosted version by DSRL's post-process filters. Provenance: {record}")
        }
    }
}

/// The Croissant document of a hosted version, whose files are served under `base` (the server's URL, no trailing
/// slash).
pub fn describe(manifest: &Manifest, task: &Task, base: &str) -> Value {
    let id = manifest.task.as_str();
    let version = manifest.version.as_str();
    let file_id = "parquet-file";
    let fields: Vec<Value> = columns(task)
        .into_iter()
        .map(|(name, data_type, width, description)| {
            let mut field = json!({
                "@type": "cr:Field",
                "@id": format!("transitions/{name}"),
                "name": name,
                "description": description,
                "dataType": data_type,
                "source": {"fileObject": {"@id": file_id}, "extract": {"column": name}},
            });
            if width.is_some() {
                field["repeated"] = Value::Bool(true);
            }
            field
        })
        .collect();
    json!({
        "@context": context(),
        "@type": "sc:Dataset",
        "conformsTo": CONFORMS_TO,
        "name": id,
        "description": format!(
            "{id}: an offline safe reinforcement learning dataset of the DSRL benchmark ({}), {} trajectories and {} \
             transitions of the simulator {} (horizon {} steps), with a reward and a cost per step. Reward returns \
             {} to {}, cost returns {} to {}. One row per transition, DSRL's key names. Version {version} (the \
             sha256 of the Parquet file).",
            task.family.as_str(),
            manifest.episodes,
            manifest.transitions,
            task.simulator_env_id,
            task.max_episode_steps,
            manifest.reward_return.min,
            manifest.reward_return.max,
            manifest.cost_return.min,
            manifest.cost_return.max,
        ),
        "url": format!("{base}/tasks/{id}"),
        "license": manifest.license,
        "datePublished": manifest.created_at,
        "citeAs": "@article{liu2023datasets, title={Datasets and Benchmarks for Offline Safe Reinforcement \
            Learning}, author={Liu, Zuxin and Guo, Zijian and Lin, Haohong and Yao, Yihang and Zhu, Jiacheng and \
            Cen, Zhepeng and Hu, Hanjiang and Yu, Wenhao and Zhang, Tingnan and Tan, Jie and Zhao, Ding}, \
            journal={arXiv preprint arXiv:2306.09303}, year={2023}}",
        "keywords": ["offline reinforcement learning", "safe reinforcement learning", "DSRL", task.family.as_str()],
        "rai:dataCollection": collection(&manifest.provenance),
        "distribution": [{
            "@type": "cr:FileObject",
            "@id": file_id,
            "name": manifest.file_name,
            "description": "The dataset's one Parquet file (zstd; float columns BYTE_STREAM_SPLIT).",
            "contentUrl": format!("{base}/v1/datasets/{id}/versions/{version}/download"),
            "contentSize": format!("{} B", manifest.byte_size),
            "encodingFormat": "application/x-parquet",
            "sha256": version,
        }],
        "recordSet": [{
            "@type": "cr:RecordSet",
            "@id": "transitions",
            "name": "transitions",
            "description": "One record per transition, in file order (episode, then step).",
            "field": fields,
        }],
    })
}
