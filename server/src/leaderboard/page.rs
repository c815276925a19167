//! The leaderboard as an HTML page: each family's aggregate table, then each task's table with its entries on the
//! normalized cost–reward plane (an inline SVG drawn on the server, so the page needs no script).

use std::fmt::Write;

use dsrl_suite::plot::{EntryPoint, entries_svg};

use super::{Board, TaskTable};

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn number(x: f64) -> String {
    if x.is_finite() { format!("{x:.3}") } else { "–".into() }
}

pub fn render(board: &Board) -> String {
    let mut html = String::from(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>dsrl leaderboard</title>\n<style>\
         body{font-family:sans-serif;margin:2em;max-width:70em}table{border-collapse:collapse;margin:1em 0}\
         td,th{border:1px solid #ccc;padding:.3em .6em;text-align:right}td.name,th.name{text-align:left}\
         tr.unsafe td{color:#a33}</style></head><body>\n<h1>dsrl leaderboard</h1>\n<p>Entries are scored by the \
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
    html.push_str("</body></html>\n");
    html
}

fn task_section(html: &mut String, table: &TaskTable) {
    let thresholds: Vec<String> = table.cost_thresholds.iter().map(|t| t.to_string()).collect();
    let _ = write!(
        html,
        "<h2 id=\"{0}\">{0}</h2>\n<p>{1}; cost thresholds {2}.</p>\n<table class=\"task\"><tr><th>rank</th>\
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
             <td>{}</td><td>{}</td><td><a href=\"/v1/submissions/{}\">{}</a></td></tr>",
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
