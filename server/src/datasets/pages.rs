//! The dataset browser: HTML pages rendered by the server (no front-end build, no script), beside the JSON API.
//!
//! - `/`: the 38 tasks by family — what is hosted, each dataset's size and return ranges, a thumbnail of its
//!   cost–reward plot — with links to each task's card and to the leaderboard.
//! - `/tasks/{task}`: a dataset card — the task's facts and the paper's numbers beside ours, versions and tags,
//!   provenance and license, the plot with the benchmark thresholds, a filter form that redraws the plot for what
//!   a DSRL filter keeps and says how many trajectories each step removed or relabelled (the filter is planned
//!   from the episode index alone, so the page answers at once), download links and copy-paste snippets.

use std::fmt::Write;

use axum::extract::{Path, Query, State};
use axum::http::{StatusCode, header};
use axum::response::{Html, IntoResponse, Response};
use dsrl_filters::plan::plan;
use dsrl_filters::spec::FilterSpec;
use dsrl_suite::catalog::Family;
use dsrl_suite::{Manifest, Task};
use serde::Deserialize;

use crate::AppState;
use crate::datasets::dsrl_download::dsrl_file_name;
use crate::error::ApiError;
use crate::http::html::{escape, page};

/// `a` encoded for a URL query value.
fn query_value(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect()
}

fn family_title(family: Family) -> &'static str {
    match family {
        Family::Bullet => "Bullet-Safety-Gym",
        Family::SafetyGymNavigation => "Safety-Gymnasium navigation",
        Family::SafetyGymVelocity => "Safety-Gymnasium velocity",
        Family::MetaDrive => "MetaDrive",
    }
}

fn megabytes(bytes: u64) -> String {
    format!("{:.1} MB", bytes as f64 / 1e6)
}

/// `/`: every task of the catalog by family.
#[utoipa::path(get, path = "/", tag = "pages",
    responses((status = 200, content_type = "text/html", body = String, description = "The dataset browser")))]
pub async fn index(State(state): State<AppState>) -> Result<Response, ApiError> {
    let tasks = state.datasets.catalog_with_versions().await?;
    let hosted = tasks.iter().filter(|(_, v)| !v.is_empty()).count();
    let mut body = format!(
        "<h1>dsrl datasets</h1>\n<p>{hosted} of {} tasks hosted. Each dataset was built by this project's pipeline \
         on the real simulators (data/README.md says how it departs from the paper's files); fetch one with \
         <code>dsrl-client fetch TASK</code>, apply DSRL's filters on request, and compare methods on the \
         <a href=\"/leaderboard\">leaderboard</a>.</p>\n",
        tasks.len()
    );
    for family in [
        Family::Bullet,
        Family::SafetyGymNavigation,
        Family::SafetyGymVelocity,
        Family::MetaDrive,
    ] {
        let _ = write!(
            body,
            "<h2>{}</h2>\n<table class=\"tasks\"><tr><th class=\"name\">task</th><th>trajectories</th>\
             <th>transitions</th><th>size</th><th>reward return</th><th>cost return</th><th>plot</th></tr>\n",
            family_title(family)
        );
        for (task, versions) in tasks.iter().filter(|(t, _)| t.family == family) {
            let id = escape(task.id.as_str());
            let latest = versions.iter().find(|v| v.tags.iter().any(|t| t == "latest"));
            match latest {
                Some(v) => {
                    let manifest = state.datasets.manifest(v).await?;
                    // A starter says so beside its count, with the paper's.
                    let kind = match dsrl_suite::Hosting::of(task, manifest.episodes, &v.tags) {
                        Some(h) => format!(
                            " <span class=\"kind\">({}; the paper's: {})</span>",
                            h.kind, h.paper_trajectories
                        ),
                        None => String::new(),
                    };
                    let _ = writeln!(
                        body,
                        "<tr class=\"task hosted\" id=\"{id}\"><td class=\"name\"><a href=\"/tasks/{id}\">{id}</a>\
                         </td><td>{}{kind}</td><td>{}</td><td>{}</td><td>{:.1} – {:.1}</td><td>{:.1} – {:.1}</td><td>\
                         <img src=\"/v1/datasets/{id}/versions/latest/plot.svg\" width=\"120\" alt=\"cost–reward \
                         plot of {id}\" loading=\"lazy\"></td></tr>",
                        manifest.episodes,
                        manifest.transitions,
                        megabytes(manifest.byte_size),
                        manifest.reward_return.min,
                        manifest.reward_return.max,
                        manifest.cost_return.min,
                        manifest.cost_return.max
                    );
                }
                None => {
                    let _ = writeln!(
                        body,
                        "<tr class=\"task missing\" id=\"{id}\"><td class=\"name\"><a href=\"/tasks/{id}\">{id}</a>\
                         </td><td colspan=\"6\">not hosted yet</td></tr>"
                    );
                }
            }
        }
        body.push_str("</table>\n");
    }
    Ok((
        [(header::CACHE_CONTROL, "no-cache")],
        Html(page("dsrl datasets", &body)),
    )
        .into_response())
}

#[derive(Debug, Deserialize)]
pub struct CardQuery {
    pub filter: Option<String>,
}

/// The filter section: the plan's counts for `filter` (or the reason it does not apply) and the redrawn plot. A
/// filter that does not apply is a form error shown on the page (the page itself is fine: 200); the JSON API
/// answers it with 400.
fn filter_section(task: &Task, manifest: &Manifest, filter: Option<&str>) -> String {
    let id = escape(task.id.as_str());
    let value = filter.unwrap_or_default();
    let mut html = format!(
        "<h2>Filters</h2>\n<form method=\"get\" action=\"/tasks/{id}\"><label>DSRL post-process filter \
         <input name=\"filter\" size=\"60\" value=\"{}\" placeholder=\"noise=0.05,density=0.5\"></label> \
         <button type=\"submit\">apply</button></form>\n<p>Keys: <code>noise</code> (outlier share), \
         <code>density</code>, <code>inpaint</code>, <code>epsilon</code>, <code>target_cost</code>, \
         <code>obs_noise</code>, <code>seed</code> — DSRL's <code>pre_process_data</code>, bit for bit.</p>\n",
        escape(value)
    );
    let plot = format!("/v1/datasets/{id}/versions/{}/plot.svg", manifest.version);
    match (!value.is_empty()).then(|| FilterSpec::parse(value, task)) {
        None => {
            let _ = writeln!(html, "<img id=\"plot\" src=\"{plot}\" alt=\"cost–reward plot\">");
        }
        Some(Ok(spec)) => match spec.map(|s| plan(&s, task, &manifest.episode_index)).transpose() {
            Ok(planned) => {
                if let Some(p) = planned {
                    let c = p.counts;
                    let _ = writeln!(
                        html,
                        "<table id=\"filter-counts\"><tr><th class=\"name\">step</th><th>trajectories</th></tr>\
                         <tr><td class=\"name\">input</td><td>{}</td></tr><tr><td class=\"name\">removed by the \
                         density grid</td><td>{}</td></tr><tr><td class=\"name\">relabelled as tempting outliers\
                         </td><td>{}</td></tr><tr><td class=\"name\">removed by inpainting</td><td>{}</td></tr>\
                         <tr><td class=\"name\">removed by the epsilon rule</td><td>{}</td></tr><tr><td \
                         class=\"name\">kept</td><td>{}</td></tr></table>",
                        c.input_episodes,
                        c.removed_by_density,
                        c.relabelled_outliers,
                        c.removed_by_inpaint,
                        c.removed_by_epsilon,
                        c.output_episodes
                    );
                }
                let _ = writeln!(
                    html,
                    "<img id=\"plot\" src=\"{plot}?filter={}\" alt=\"cost–reward plot after the filter\">",
                    query_value(value)
                );
            }
            Err(e) => {
                let _ = writeln!(
                    html,
                    "<p class=\"error\" id=\"filter-error\">{}</p>",
                    escape(&e.to_string())
                );
            }
        },
        Some(Err(e)) => {
            let _ = writeln!(
                html,
                "<p class=\"error\" id=\"filter-error\">{}</p>",
                escape(&e.to_string())
            );
        }
    }
    html
}

/// `/tasks/{task}`: the dataset card.
#[utoipa::path(get, path = "/tasks/{task}", tag = "pages",
    params(("task" = String, Path, pattern = r"^[A-Za-z0-9_.-]+$", example = "OfflineBallRun-v0"),
        ("filter" = Option<String>, Query, description = "A DSRL post-process filter to plan and plot")),
    responses((status = 200, content_type = "text/html", body = String,
            description = "The dataset card (with the reason, when the filter does not apply)"),
        (status = 404, description = "Unknown task")))]
pub async fn card(
    State(state): State<AppState>,
    Path(task_id): Path<String>,
    Query(query): Query<CardQuery>,
) -> Result<Response, ApiError> {
    let (task, versions) = state.datasets.versions(&task_id).await?;
    let id = escape(task.id.as_str());
    let thresholds: Vec<String> = task.cost_thresholds.iter().map(|k| k.to_string()).collect();
    let mut body = format!(
        "<h1>{id}</h1>\n<table id=\"facts\"><tr><th class=\"name\">family</th><td class=\"name\">{}</td></tr>\
         <tr><th class=\"name\">simulator</th><td class=\"name\">{}</td></tr><tr><th class=\"name\">episode \
         horizon</th><td>{}</td></tr><tr><th class=\"name\">observation / action dims</th><td>{} / {}</td></tr>\
         <tr><th class=\"name\">cost thresholds (leaderboard)</th><td>{}</td></tr><tr><th class=\"name\">\
         normalization: reward</th><td>{:.1} – {:.1}</td></tr><tr><th class=\"name\">paper's file</th>\
         <td class=\"name\">{} trajectories, cost returns capped at {} (<code>{}</code>)</td></tr></table>\n",
        family_title(task.family),
        escape(&task.simulator_env_id),
        task.max_episode_steps,
        task.obs_dim,
        task.act_dim,
        thresholds.join(", "),
        task.min_episode_reward,
        task.max_episode_reward,
        task.paper_trajectories,
        task.paper_cost_cap,
        escape(&dsrl_file_name(task)),
    );
    let latest = versions.iter().find(|v| v.tags.iter().any(|t| t == "latest"));
    let Some(latest) = latest else {
        body.push_str("<p id=\"not-hosted\">No version of this task is hosted yet.</p>\n");
        return Ok((StatusCode::OK, Html(page(task.id.as_str(), &body))).into_response());
    };
    let manifest = state.datasets.manifest(latest).await?;
    // The noise filter's own corner (one predicate for the filter, the hosted bar and this page).
    let corner = manifest
        .episode_index
        .iter()
        .filter(|e| dsrl_filters::plan::in_tempting_corner(task, e.cost_return, e.reward_return))
        .count();
    let version = escape(manifest.version.as_str());
    let _ = write!(
        body,
        "<h2>Latest version</h2>\n<table id=\"latest\"><tr><th class=\"name\"></th><th>this server</th><th>paper\
         </th></tr><tr><td class=\"name\">trajectories</td><td>{}</td><td>{}</td></tr><tr><td class=\"name\">\
         reward return</td><td>{:.1} – {:.1}</td><td>{:.1} – {:.1}</td></tr><tr><td class=\"name\">cost return\
         </td><td>{:.1} – {:.1}</td><td>0 – {}</td></tr><tr><td class=\"name\">in the tempting corner (cost ≥ \
         max cost/2, reward ≥ max reward/2)</td><td>{corner}</td><td></td></tr></table>\n<p>Version <code id=\"version\">\
         {version}</code>, {} transitions, {}, license {}, created {}.</p>\n",
        manifest.episodes,
        task.paper_trajectories,
        manifest.reward_return.min,
        manifest.reward_return.max,
        task.min_episode_reward,
        task.max_episode_reward,
        manifest.cost_return.min,
        manifest.cost_return.max,
        task.paper_cost_cap,
        manifest.transitions,
        megabytes(manifest.byte_size),
        escape(&manifest.license),
        escape(&manifest.created_at),
    );
    // What the latest version is: the committed starter (said plainly, with the command that builds the full
    // dataset) or a full build.
    if let Some(hosting) = dsrl_suite::Hosting::of(task, manifest.episodes, &latest.tags) {
        match &hosting.notice {
            Some(notice) => {
                let _ = writeln!(body, "<p id=\"hosting\" class=\"notice\">{}</p>", escape(notice));
            }
            None => {
                let _ = writeln!(
                    body,
                    "<p id=\"hosting\">A full build: {} trajectories (the paper's: {}).</p>",
                    hosting.trajectories, hosting.paper_trajectories
                );
            }
        }
    }
    body.push_str(&filter_section(task, &manifest, query.filter.as_deref()));
    let parquet = format!("/v1/datasets/{id}/versions/{version}/download");
    let hdf5 = format!("/download/{}", escape(&dsrl_file_name(task)));
    let hdf5_link = if task.family == Family::MetaDrive && !state.dsrl_download_metadrive {
        String::new()
    } else {
        format!(" · <a id=\"download-hdf5\" href=\"{hdf5}\">HDF5 (DSRL's layout and file name)</a>")
    };
    let _ = write!(
        body,
        "<h2>Download</h2>\n<p><a id=\"download-parquet\" href=\"{parquet}\">Parquet</a>{hdf5_link} · <a \
         id=\"croissant\" href=\"/v1/datasets/{id}/versions/{version}/croissant.json\">Croissant metadata</a></p>\n\
         <pre>dsrl-client fetch {id}                      # verified, resumable, into ~/.dsrl/datasets\n\
         dsrl-client fetch {id} --format hdf5        # DSRL's HDF5 layout\n\
         dsrl-client fetch {id} --filter noise=0.05  # a DSRL filter, computed by the server</pre>\n\
         <pre>import pyarrow.parquet as pq               # or pandas.read_parquet\n\
         table = pq.read_table(\"{}.parquet\")</pre>\n\
         <pre>import dsrl, gymnasium as gym               # DSRL's own loader on the HDF5\n\
         env = gym.make(\"{id}\")\n\
         data = env.get_dataset(h5path=\"{}.hdf5\")</pre>\n",
        escape(&task.dataset_file_stem(manifest.episodes)),
        escape(&task.dataset_file_stem(manifest.episodes)),
    );
    let _ = write!(
        body,
        "<h2>Versions</h2>\n<table id=\"versions\"><tr><th class=\"name\">version</th><th class=\"name\">tags\
         </th><th>trajectories</th><th>transitions</th><th>size</th><th class=\"name\">created</th></tr>\n"
    );
    for v in &versions {
        let _ = writeln!(
            body,
            "<tr><td class=\"name\"><code>{}</code></td><td class=\"name\">{}</td><td>{}</td><td>{}</td><td>{}</td>\
             <td class=\"name\">{}</td></tr>",
            escape(&v.version[..16.min(v.version.len())]),
            escape(&v.tags.join(", ")),
            v.episodes,
            v.transitions,
            megabytes(v.byte_size),
            escape(&v.created_at)
        );
    }
    body.push_str("</table>\n");
    let provenance = serde_json::to_string_pretty(&manifest.provenance).map_err(ApiError::internal)?;
    let _ = writeln!(
        body,
        "<h2>Provenance</h2>\n<pre id=\"provenance\">{}</pre>",
        escape(&provenance)
    );
    Ok((
        [(header::CACHE_CONTROL, "no-cache")],
        Html(page(task.id.as_str(), &body)),
    )
        .into_response())
}
