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
        let (mut session, _) = worker.open(&id, &[0], AutoReset::SameStep).await;
        let mut actions = Actions::new(0);
        for _ in 0..5 {
            if let Err(status) = session
                .step(&[], &actions.batch(&spec.action_low, &spec.action_high, 1))
                .await
            {
                failures.push(format!("{id}: step: {status}"));
                break;
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
