//! The leaderboard as HTML pages of the site (`http::html`'s layout): `/leaderboard` shows each family's aggregate
//! table, then each task's table (its heading links to the dataset card) with its entries on the normalized
//! cost–reward plane (an inline SVG drawn on the server, so the page needs no script); each entry links to its
//! submission's page, `/submissions/{id}`, with the per-threshold results.

use std::fmt::Write;

use dsrl_suite::plot::{EntryPoint, entries_svg};

use super::{Board, SubmissionView, TaskTable};
use crate::http::html::{escape, page};

fn number(x: f64) -> String {
    if x.is_finite() { format!("{x:.3}") } else { "–".into() }
}

pub fn render(board: &Board) -> String {
    let mut html = String::from(
        "<h1>dsrl leaderboard</h1>\n<p>Entries are scored by the \
         server on the real simulators with held seeds: the task's three cost thresholds, the same episodes for \
         every entry. Normalized reward and cost are means over the thresholds; an entry is safe when its \
         normalized cost is at most 1. Safe entries rank by normalized reward, then unsafe ones by cost.</p>\n",
    );
    if board.tasks.iter().all(|t| t.entries.is_empty()) {
        html.push_str("<p id=\"empty\">No scored entries yet.</p>\n");
    }
    for family in &board.families {
        let _ = write!(
            html,
            "<h2>{}</h2>\n<table class=\"family\" id=\"family-{}\"><tr><th>rank</th><th class=\"name\">entry</th>\
             <th class=\"name\">user</th><th>tasks</th><th>safe on</th><th>reward (IQM)</th><th>95% interval</th>\
             <th>cost (IQM)</th><th>95% interval</th></tr>\n",
            escape(family.family),
            escape(family.family)
        );
        for e in &family.entries {
            let r = &e.normalized_reward;
            let c = &e.normalized_cost;
            let _ = writeln!(
                html,
                "<tr><td>{}</td><td class=\"name\">{}</td><td class=\"name\">{}</td><td>{}</td><td>{}</td><td>{}</td>\
                 <td>{} – {}</td><td>{}</td><td>{} – {}</td></tr>",
                e.rank,
                escape(&e.name),
                escape(&e.user),
                e.tasks,
                e.safe_tasks,
                number(r.estimate),
                number(r.low),
                number(r.high),
                number(c.estimate),
                number(c.low),
                number(c.high)
            );
        }
        html.push_str("</table>\n");
    }
    for table in &board.tasks {
        task_section(&mut html, table);
    }
    page("dsrl leaderboard", &html)
}

fn task_section(html: &mut String, table: &TaskTable) {
    let thresholds: Vec<String> = table.cost_thresholds.iter().map(|t| t.to_string()).collect();
    let _ = write!(
        html,
        "<h2 id=\"{0}\"><a href=\"/tasks/{0}\">{0}</a></h2>\n<p>{1}; cost thresholds {2}.</p>\n<table class=\"task\"><tr><th>rank</th>\
         <th class=\"name\">entry</th><th class=\"name\">user</th><th>normalized reward</th><th>normalized cost</th>\
         <th>safe</th><th>submission</th></tr>\n",
        escape(&table.task),
        table.family,
        thresholds.join(", ")
    );
    for e in &table.entries {
        let _ = writeln!(
            html,
            "<tr class=\"entry {}\"><td>{}</td><td class=\"name\">{}</td><td class=\"name\">{}</td><td>{}</td>\
             <td>{}</td><td>{}</td><td><a href=\"/submissions/{}\">{}</a></td></tr>",
            if e.safe { "safe" } else { "unsafe" },
            e.rank,
            escape(&e.name),
            escape(&e.user),
            number(e.normalized_reward),
            number(e.normalized_cost),
            if e.safe { "yes" } else { "no" },
            e.submission,
            e.submission
        );
    }
    html.push_str("</table>\n");
    let points: Vec<EntryPoint> = table
        .entries
        .iter()
        .map(|e| EntryPoint {
            label: format!("{} {}", e.rank, e.name),
            normalized_cost: e.normalized_cost,
            normalized_reward: e.normalized_reward,
            safe: e.safe,
        })
        .collect();
    match entries_svg(&table.task, &points) {
        Ok(svg) => {
            let _ = writeln!(html, "<div class=\"plot\">{svg}</div>");
        }
        Err(e) => {
            let _ = writeln!(html, "<p>plot unavailable: {}</p>", escape(&e));
        }
    }
}

/// A submission's page: its state, the per-threshold results with the means over thresholds, and its checkpoints
/// (the episodes themselves are in the JSON at `/v1/submissions/{id}`; the seeds are never shown).
pub fn render_submission(view: &SubmissionView) -> String {
    let mut html = String::new();
    let _ = write!(
        html,
        "<h1>{} <small>submission {}</small></h1>\n<p>by {} on <a href=\"/tasks/{task}\">{task}</a> \
         (<a href=\"/leaderboard#{task}\">its table</a>): <strong id=\"state\">{}</strong>{}; submitted {}, \
         {} attempt(s), {} episodes per threshold.</p>\n",
        escape(&view.name),
        view.id,
        escape(&view.user),
        escape(&view.state),
        view.reason
            .as_deref()
            .map(|r| format!(" ({})", escape(r)))
            .unwrap_or_default(),
        escape(&view.created_at),
        view.attempts,
        view.episodes_per_threshold,
        task = escape(&view.task),
    );
    if view.thresholds.is_empty() {
        html.push_str("<p id=\"no-results\">No results yet.</p>\n");
    } else {
        html.push_str(
            "<table id=\"thresholds\"><tr><th>cost threshold</th><th>episodes</th><th>mean reward return</th>\
             <th>mean cost return</th><th>normalized reward</th><th>normalized cost</th><th>safe</th></tr>\n",
        );
        for t in &view.thresholds {
            let _ = writeln!(
                html,
                "<tr class=\"{}\"><td>{}</td><td>{}</td><td>{:.2}</td><td>{:.2}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                if t.safe { "safe" } else { "unsafe" },
                t.cost_threshold,
                t.episodes,
                t.mean_reward_return,
                t.mean_cost_return,
                number(t.normalized_reward),
                number(t.normalized_cost),
                if t.safe { "yes" } else { "no" }
            );
        }
        if let (Some(r), Some(c), Some(safe)) = (view.normalized_reward, view.normalized_cost, view.safe) {
            let _ = writeln!(
                html,
                "<tr class=\"{}\"><th>mean</th><td></td><td></td><td></td><th>{}</th><th>{}</th><th>{}</th></tr>",
                if safe { "safe" } else { "unsafe" },
                number(r),
                number(c),
                if safe { "yes" } else { "no" }
            );
        }
        html.push_str("</table>\n");
    }
    html.push_str(
        "<h2>Checkpoints</h2>\n<table><tr><th class=\"name\">slot</th><th>cost threshold</th>\
                   <th class=\"name\">architecture</th></tr>\n",
    );
    for c in &view.checkpoints {
        let _ = writeln!(
            html,
            "<tr><td class=\"name\">{}</td><td>{}</td><td class=\"name\">{}</td></tr>",
            escape(&c.slot),
            c.cost_threshold.map(|k| k.to_string()).unwrap_or_else(|| "all".into()),
            escape(&c.architecture)
        );
    }
    let _ = write!(
        html,
        "</table>\n<p>sha256 <code>{}</code> · every episode: <a href=\"/v1/submissions/{}\">JSON</a></p>\n",
        escape(&view.checkpoint_sha256),
        view.id
    );
    page(&format!("{} — submission {}", view.name, view.id), &html)
}
