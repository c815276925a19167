//! Every one of the 38 catalog tasks opens, resets and steps through the protocol, with the catalog's dimensions
//! and horizon. Two workers share the tasks (the CI machine has two cores).

use dsrl_proto::simulator::v1::{AutoReset, DescribeRequest};
use dsrl_suite::catalog::Catalog;

use crate::support::{Actions, Worker};

async fn run_tasks(tasks: Vec<dsrl_suite::catalog::Task>) -> Vec<String> {
    let worker = Worker::start(&[]).await;
    let mut failures = Vec::new();
    for task in tasks {
        let id = task.id.as_str().to_owned();
        let spec = match worker
            .client()
            .await
            .describe(DescribeRequest { task: id.clone() })
            .await
        {
            Ok(spec) => spec.into_inner(),
            Err(status) => {
                failures.push(format!("{id}: describe: {status}"));
                continue;
            }
        };
        if (spec.obs_dim, spec.act_dim, spec.max_episode_steps) != (task.obs_dim, task.act_dim, task.max_episode_steps)
        {
            failures.push(format!("{id}: spec {spec:?} disagrees with the catalog"));
            continue;
        }
        let (mut session, first) = worker.open(&id, &[0], AutoReset::SameStep).await;
        if first.len() != task.obs_dim as usize || first.iter().any(|x| !x.is_finite()) {
            failures.push(format!(
                "{id}: reset gave {} values, not {} finite ones",
                first.len(),
                task.obs_dim
            ));
        }
        let mut actions = Actions::new(0);
        for step in 0..5 {
            match session
                .step(&[], &actions.batch(&spec.action_low, &spec.action_high, 1))
                .await
            {
                // One environment: one row of the catalog's dimensions, finite, answered for environment 0.
                Ok(r) => {
                    let shapes = (r.envs.len(), r.observations.len(), r.rewards.len(), r.costs.len());
                    let flags = (r.terminated.len(), r.truncated.len(), r.applied_actions.len());
                    if shapes != (1, task.obs_dim as usize, 1, 1)
                        || flags != (1, 1, task.act_dim as usize)
                        || r.envs != [0]
                    {
                        failures.push(format!("{id}: step {step} answered shapes {shapes:?} {flags:?}"));
                        break;
                    }
                    let finite = r.observations.iter().all(|x| x.is_finite())
                        && r.rewards[0].is_finite()
                        && r.costs[0].is_finite()
                        && r.costs[0] >= 0.0;
                    if !finite {
                        failures.push(format!(
                            "{id}: step {step} answered a non-finite value or a negative cost"
                        ));
                        break;
                    }
                }
                Err(status) => {
                    failures.push(format!("{id}: step: {status}"));
                    break;
                }
            }
        }
        session.close().await.ok();
    }
    failures
}

#[tokio::test]
async fn all_38_tasks_step_through_the_protocol() {
    let catalog = Catalog::embedded().unwrap();
    assert_eq!(catalog.tasks().len(), 38);
    let (even, odd): (Vec<_>, Vec<_>) = catalog
        .tasks()
        .iter()
        .cloned()
        .enumerate()
        .partition(|(i, _)| i % 2 == 0);
    let strip = |v: Vec<(usize, dsrl_suite::catalog::Task)>| v.into_iter().map(|(_, t)| t).collect::<Vec<_>>();
    let (a, b) = tokio::join!(run_tasks(strip(even)), run_tasks(strip(odd)));
    let failures: Vec<String> = a.into_iter().chain(b).collect();
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
