//! Every filter and combination against the outputs of DSRL's own `pre_process_data` (fixtures made by
//! tests/golden/make_golden.sh from the same synthetic datasets): bit for bit.

use std::collections::HashMap;

use dsrl_filters::apply::gather;
use dsrl_filters::plan::plan;
use dsrl_filters::spec::FilterSpec;
use dsrl_suite::catalog::{Catalog, ObservationSpace};
use dsrl_suite::convert::write_canonical;
use dsrl_suite::synthetic::{SyntheticSpec, transitions};
use sha2::{Digest, Sha256};

const GOLDEN: &str = include_str!("golden/filters.json");

fn digest_f32(values: &[f32]) -> String {
    let mut h = Sha256::new();
    for v in values {
        h.update(v.to_le_bytes());
    }
    hex::encode(h.finalize())
}

fn digest_bool(values: &[bool]) -> String {
    hex::encode(Sha256::digest(values.iter().map(|&b| b as u8).collect::<Vec<u8>>()))
}

#[test]
fn every_filter_matches_dsrls_reference_bit_for_bit() {
    let doc: serde_json::Value = serde_json::from_str(GOLDEN).unwrap();
    let catalog = Catalog::embedded().unwrap();
    let dir = tempfile::tempdir().unwrap();
    // Write each dataset once, the way dsrl-make-dataset did for the reference.
    let mut datasets = HashMap::new();
    for (name, d) in doc["datasets"].as_object().unwrap() {
        let task = catalog.get(d["task"].as_str().unwrap()).unwrap().clone();
        let spec = SyntheticSpec::for_task(
            &task,
            d["episodes"].as_u64().unwrap() as usize,
            d["seed"].as_u64().unwrap(),
        );
        let path = dir.path().join(format!("{name}.parquet"));
        let converted = write_canonical(
            &task,
            ObservationSpace::Simulator,
            transitions(spec).map(Ok),
            vec![],
            &path,
        )
        .unwrap();
        datasets.insert(name.clone(), (task, path, converted.episode_index));
    }
    let mut failures = Vec::new();
    let cases = doc["cases"].as_array().unwrap();
    for case in cases {
        let (task, path, episodes) = &datasets[case["dataset"].as_str().unwrap()];
        let text = case["filter"].as_str().unwrap();
        let label = format!("{} {text}", case["dataset"].as_str().unwrap());
        let spec = FilterSpec::parse(text, task)
            .unwrap_or_else(|e| panic!("{label}: {e}"))
            .unwrap();
        let expected = &case["expected"];
        let planned = plan(&spec, task, episodes);
        if let Some(error) = expected.get("error") {
            if planned.is_ok() {
                failures.push(format!("{label}: the reference fails ({error}) but we accepted it"));
            }
            continue;
        }
        let planned = match planned {
            Ok(p) => p,
            Err(e) => {
                failures.push(format!("{label}: rejected ({e}) but the reference succeeds"));
                continue;
            }
        };
        let out = gather(path, episodes, &planned, task.obs_dim as usize, task.act_dim as usize).unwrap();
        let rows = expected["rows"].as_u64().unwrap() as usize;
        if out.len() != rows {
            failures.push(format!("{label}: {} rows, expected {rows}", out.len()));
            continue;
        }
        let ours = [
            ("observations", digest_f32(&out.observations)),
            ("next_observations", digest_f32(&out.next_observations)),
            ("actions", digest_f32(&out.actions)),
            ("rewards", digest_f32(&out.rewards)),
            ("costs", digest_f32(&out.costs)),
            ("terminals", digest_bool(&out.terminals)),
            ("timeouts", digest_bool(&out.timeouts)),
        ];
        for (key, digest) in ours {
            if expected["sha256"][key] != digest.as_str() {
                failures.push(format!("{label}: {key} differs"));
            }
        }
        assert_eq!(
            planned.order.len() as u64,
            expected["episodes"].as_u64().unwrap(),
            "{label}"
        );
        // The server's streaming path (bounded memory) writes the same file, byte for byte: on every case that
        // reorders, relabels or adds noise (one density-only case of each dataset stands for the rest).
        let reorders_or_noise = ["noise", "outliers", "obs_noise", "noise_scale", "epsilon", "seed=0"]
            .iter()
            .any(|k| text.contains(k));
        if !reorders_or_noise {
            continue;
        }
        let (whole, streamed) = (dir.path().join("whole.parquet"), dir.path().join("streamed.parquet"));
        let written = dsrl_filters::apply::write(task, ObservationSpace::Simulator, &out, &whole).unwrap();
        let (o, a) = (task.obs_dim as usize, task.act_dim as usize);
        let spill = dir.path().join("spill");
        let streamed = dsrl_filters::apply::filter_to(
            path,
            episodes,
            &planned,
            task,
            ObservationSpace::Simulator,
            o,
            a,
            &streamed,
            &spill,
        )
        .unwrap();
        if streamed.version != written.version {
            failures.push(format!("{label}: the streamed output differs from the gathered one"));
        }
        assert!(!spill.exists(), "the spill file is removed");
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases differ:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
