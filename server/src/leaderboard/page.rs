//! The leaderboard as HTML pages of the site (`http::html`'s layout): `/leaderboard` shows each family's aggregate
//! table, then each task's table (its heading links to the dataset card) with its entries on the normalized
//! cost–reward plane (an inline SVG drawn on the server, so the page needs no script); each entry links to its
//! submission's page, `/submissions/{id}`, with the per-threshold results.

use std::fmt::Write;

use dsrl_suite::plot::{EntryPoint, entries_svg};

use super::reference::{ReferenceRecord, TrainingData, method_label};
use super::renders::{EpisodeReplay, ReplayState};
use super::{Board, FamilyEntry, FamilyTable, QueuedJob, SubmissionView, TaskEntry, TaskTable, UserSubmission};
use crate::http::html::{escape, page};

fn number(x: f64) -> String {
    if x.is_finite() { format!("{x:.3}") } else { "–".into() }
}

/// `estimate [low, high]`.
fn with_interval(i: &dsrl_scoring::leaderboard::Interval) -> String {
    format!(
        "{} <small>[{}, {}]</small>",
        number(i.estimate),
        number(i.low),
        number(i.high)
    )
}

/// A reference entry's budget: steps (× models) at a batch size, as a fraction of the method's own budget's samples
/// (OSRL's for the paper's seven methods; CAPS's, FISOR's and LSPC's code's for theirs).
fn budget(record: &ReferenceRecord, seeds: &str) -> String {
    let t = &record.training;
    let models = if t.models > 1 {
        format!(" × {} models", t.models)
    } else {
        String::new()
    };
    format!(
        "reference: {} steps{models} at batch {} (1/{:.0} of the method's samples), seed {seeds}, trained on the {}",
        t.steps,
        t.batch_size,
        1.0 / t.fraction_of_osrl(),
        record.dataset.as_str(),
    )
}

fn percent(share: Option<f64>) -> String {
    share.map_or_else(|| "–".into(), |s| format!("{:.0}%", 100.0 * s))
}

/// The agreement table's header cells after the scope, and one summary's cells: the agreement, then what chance and
/// the two trivial rules agree on over the same cells, then the mean differences.
const AGREEMENT_HEADER: &str = "<th>verdicts that agree</th><th>chance (from the safe rates)</th><th>\"every method \
     unsafe\"</th><th>\"BC-Safe safe, the rest unsafe\"</th><th>mean |Δ reward|</th><th>mean |Δ cost|</th>";

fn agreement_cells(s: &dsrl_scoring::reference::AgreementSummary) -> String {
    format!(
        "<td>{}</td><td class=\"baseline\">{}</td><td class=\"baseline\">{}</td><td class=\"baseline\">{}</td><td>{}</td><td>{}</td>",
        share(s),
        percent(s.chance_share),
        percent(s.all_unsafe_share),
        percent(s.bc_safe_rule_share),
        s.mean_abs_reward_difference.map(number).unwrap_or_else(|| "–".into()),
        s.mean_abs_cost_difference.map(number).unwrap_or_else(|| "–".into())
    )
}

fn share(summary: &dsrl_scoring::reference::AgreementSummary) -> String {
    match summary.share {
        Some(share) => format!("{} of {} ({:.0}%)", summary.agreeing, summary.cells, 100.0 * share),
        None => "no cells yet".into(),
    }
}

/// The queue: jobs being scored with their progress, then the waiting ones in claim order.
fn queue_section(html: &mut String, queue: &[QueuedJob]) {
    html.push_str("<h2>Queue</h2>\n");
    if queue.is_empty() {
        html.push_str("<p id=\"queue-empty\">Nothing is waiting or being scored.</p>\n");
        return;
    }
    html.push_str(
        "<table id=\"queue\"><tr><th>submission</th><th class=\"name\">task</th><th class=\"name\">entry</th>\
         <th class=\"name\">user</th><th class=\"name\">state</th></tr>\n",
    );
    for j in queue {
        let state = match j.position {
            Some(p) => format!("queued, position {p}"),
            None => format!("scoring: {} of {} episodes", j.episodes_done, j.episodes_total),
        };
        let _ = writeln!(
            html,
            "<tr class=\"job {}\"><td><a href=\"/submissions/{id}\">{id}</a></td><td class=\"name\">{}</td>\
             <td class=\"name\">{}</td><td class=\"name\"><a href=\"/users/{user}\">{user}</a></td><td class=\"name\">{}</td></tr>",
            escape(&j.state),
            escape(&j.task),
            escape(&j.name),
            escape(&state),
            id = j.id,
            user = escape(&j.user),
        );
    }
    html.push_str("</table>\n");
}

/// A user's page: every submission, newest first.
pub fn render_user(name: &str, submissions: &[UserSubmission]) -> String {
    let mut html = format!(
        "<h1>{}</h1>\n<p>{} submissions, newest first (every one is kept: the leaderboard shows each entry's count \
         beside its score). <a href=\"/v1/users/{}/submissions\">JSON</a></p>\n<table id=\"submissions\"><tr>\
         <th>submission</th><th class=\"name\">task</th><th class=\"name\">entry</th><th class=\"name\">state</th>\
         <th>normalized reward</th><th>normalized cost</th><th class=\"name\">protocol</th><th class=\"name\">submitted</th></tr>\n",
        escape(name),
        submissions.len(),
        escape(name)
    );
    for s in submissions {
        let _ = writeln!(
            html,
            "<tr><td><a href=\"/submissions/{id}\">{id}</a></td><td class=\"name\">{}</td><td class=\"name\">{}</td>\
             <td class=\"name\">{}</td><td>{}</td><td>{}</td><td class=\"name\">{}</td><td class=\"name\">{}</td></tr>",
            escape(&s.task),
            escape(&s.name),
            escape(&s.state),
            s.normalized_reward.map(number).unwrap_or_else(|| "–".into()),
            s.normalized_cost.map(number).unwrap_or_else(|| "–".into()),
            escape(s.protocol_version.as_deref().unwrap_or("–")),
            escape(&s.created_at),
            id = s.id,
        );
    }
    html.push_str("</table>\n");
    page(&format!("{name}: submissions"), &html)
}

pub fn render(board: &Board, queue: &[QueuedJob]) -> String {
    let p = &board.protocol;
    let mut html = String::new();
    let _ = write!(
        html,
        "<h1>dsrl leaderboard</h1>\n<p>Entries are scored by the server on the real simulators with held seeds: the \
         task's three cost thresholds, the same episodes for every entry. Normalized reward and cost are means over \
         the thresholds, with a 95% bootstrap interval over the entry's episodes; an entry is safe when its \
         normalized cost is at most 1. Safe entries rank by normalized reward, then unsafe ones by cost. Reference \
         entries (user <em>{}</em>) are the paper's baselines trained by <code>dsrl-train</code> on the hosted \
         data at the budget shown; the paper's own rows are shown beside each task, unranked.</p>\n\
         <p id=\"protocol\">Protocol <strong>{}</strong>: {} tasks, {} episodes per threshold on {} environments, \
         held seeds <code>{}</code>, scorer revision {}, rules {}; catalog sha256 <code>{}</code>, simulator pins \
         sha256 <code>{}</code>. Only results scored under it are ranked.</p>\n",
        escape(crate::leaderboard::users::REFERENCE_USER),
        escape(&p.version),
        p.tasks,
        p.episodes_per_threshold,
        p.envs_per_session,
        escape(&p.held_seeds),
        p.scorer_revision,
        p.rules,
        escape(dsrl_suite::ids::short_hex(&p.catalog_sha256)),
        escape(dsrl_suite::ids::short_hex(&p.simulator_pins_sha256)),
    );
    let _ = write!(
        html,
        "<h2>Agreement with the paper</h2>\n<p>For every task and method with both a reference entry here and a \
         row in the paper: does the safe/unsafe verdict agree (<a href=\"/leaderboard/agreement\">every cell, and per \
         method</a>)? Beside it, what trivial rules would agree on over the same cells: chance, given how often each \
         table calls a method safe; calling every method unsafe; calling BC-Safe safe and every other method \
         unsafe.</p>\n<table id=\"agreement\"><tr><th class=\"name\">family</th>{AGREEMENT_HEADER}</tr>\n"
    );
    scope_rows(&mut html, &board.agreement);
    full_build_agreement(&mut html, board);
    html.push_str(
        "<p>The board as data: <a href=\"/v1/leaderboard.csv\">CSV</a>, <a href=\"/v1/leaderboard.parquet\">Parquet\
         </a>, <a href=\"/v1/leaderboard\">JSON</a>.</p>\n",
    );
    queue_section(&mut html, queue);
    if board.tasks.iter().all(|t| t.entries.is_empty()) {
        html.push_str("<p id=\"empty\">No scored entries yet.</p>\n");
    }
    for family in &board.families {
        family_section(&mut html, family);
    }
    for table in &board.tasks {
        task_section(&mut html, table, board.paper_label);
    }
    page("dsrl leaderboard", &html)
}

/// One family's table: the entries scored on all its tasks, ranked; then the partial ones with their coverage; then
/// the picture (also at `/leaderboard/plots/{family}.svg`).
fn family_section(html: &mut String, family: &FamilyTable) {
    let _ = write!(
        html,
        "<h2>{0}</h2>\n<p>Ranked: the entries scored on all {1} tasks of the family, by the interquartile mean over \
         tasks of each task's mean over training seeds, with a 95% bootstrap interval that resamples tasks and then \
         seeds.</p>\n<table class=\"family\" id=\"family-{0}\"><tr><th>rank</th><th class=\"name\">entry</th>\
         <th class=\"name\">user</th><th>tasks</th><th>training seeds</th><th>safe on</th><th>reward (IQM)</th>\
         <th>95% interval</th><th>cost (IQM)</th><th>95% interval</th></tr>\n",
        escape(family.family),
        family.tasks
    );
    let row = |html: &mut String, e: &FamilyEntry| {
        let (r, c) = (&e.normalized_reward, &e.normalized_cost);
        let _ = writeln!(
            html,
            "<tr class=\"{}\"><td>{}</td><td class=\"name\">{}</td><td class=\"name\">{}</td><td>{} of {}</td><td>{}</td>\
             <td>{}</td><td>{}</td><td>{} – {}</td><td>{}</td><td>{} – {}</td></tr>",
            if e.reference { "reference" } else { "user" },
            e.rank.map_or_else(|| "–".to_owned(), |r| r.to_string()),
            escape(&e.name),
            escape(&e.user),
            e.tasks,
            family.tasks,
            e.training_seeds,
            e.safe_tasks,
            number(r.estimate),
            number(r.low),
            number(r.high),
            number(c.estimate),
            number(c.low),
            number(c.high)
        );
    };
    for e in &family.entries {
        row(html, e);
    }
    html.push_str("</table>\n");
    if !family.partial.is_empty() {
        let _ = write!(
            html,
            "<p>Scored on some of the family's tasks (an aggregate over fewer tasks is not comparable: listed, not \
             ranked):</p>\n<table class=\"family partial\" id=\"family-{}-partial\"><tr><th>rank</th>\
             <th class=\"name\">entry</th><th class=\"name\">user</th><th>tasks</th><th>training seeds</th>\
             <th>safe on</th><th>reward (IQM)</th><th>95% interval</th><th>cost (IQM)</th><th>95% interval</th></tr>\n",
            escape(family.family)
        );
        for e in &family.partial {
            row(html, e);
        }
        html.push_str("</table>\n");
    }
    match family_svg(family) {
        Ok(svg) => {
            let _ = writeln!(html, "<div class=\"plot\">{svg}</div>");
        }
        Err(e) => {
            let _ = writeln!(html, "<p>plot unavailable: {}</p>", escape(&e));
        }
    }
}

/// A family's entries on the normalized cost–reward plane: ranked ones keyed by their rank, partial ones by a
/// letter, their coverage in the legend.
pub fn family_svg(family: &FamilyTable) -> Result<String, String> {
    let ranked = family
        .entries
        .iter()
        .map(|e| (e.rank.map_or_else(|| "–".to_owned(), |r| r.to_string()), e, None));
    let partial = family.partial.iter().enumerate().map(|(i, e)| {
        (
            letter_key(i),
            e,
            Some(format!(", {} of {} tasks", e.tasks, family.tasks)),
        )
    });
    let points: Vec<EntryPoint> = ranked
        .chain(partial)
        .map(|(key, e, coverage)| EntryPoint {
            key,
            label: format!(
                "{}{}",
                legend_name(&e.name, &e.user, e.reference),
                coverage.unwrap_or_default()
            ),
            normalized_cost: e.normalized_cost.estimate,
            normalized_reward: e.normalized_reward.estimate,
            safe: dsrl_suite::score::is_safe(e.normalized_cost.estimate),
            reward_interval: Some((e.normalized_reward.low, e.normalized_reward.high)),
            cost_interval: Some((e.normalized_cost.low, e.normalized_cost.high)),
            paper: false,
        })
        .collect();
    entries_svg(&format!("{} (IQM over tasks)", family.family), &points)
}

/// A point's name in a picture's legend: a reference entry's name alone (its user is the reference account), any
/// other's with its user, since two users may give an entry the same name.
fn legend_name(name: &str, user: &str, reference: bool) -> String {
    if reference {
        name.to_owned()
    } else {
        format!("{name} ({user})")
    }
}

/// The key of the `i`-th unranked point of a picture: a, b, …, z, then aa, ab, …
fn letter_key(i: usize) -> String {
    let letter = |n: usize| char::from(b'a' + (n % 26) as u8);
    if i < 26 {
        letter(i).to_string()
    } else {
        format!("{}{}", letter(i / 26 - 1), letter(i))
    }
}

/// A task's entries and the paper's rows on the normalized cost–reward plane, with the entries' intervals.
pub fn task_svg(table: &TaskTable) -> Result<String, String> {
    let entries = table.entries.iter().map(|e| EntryPoint {
        key: e.rank.to_string(),
        label: legend_name(&e.name, &e.user, e.reference.is_some()),
        normalized_cost: e.normalized_cost,
        normalized_reward: e.normalized_reward,
        safe: e.safe,
        reward_interval: Some((e.normalized_reward_interval.low, e.normalized_reward_interval.high)),
        cost_interval: Some((e.normalized_cost_interval.low, e.normalized_cost_interval.high)),
        paper: false,
    });
    // The self-reported rows, drawn as the paper's: the paper's own, then those of methods beyond it.
    let reported = table
        .paper
        .iter()
        .map(|p| ("paper", &p.method, p.normalized_cost, p.normalized_reward, p.safe))
        .chain(
            table
                .published
                .iter()
                .map(|p| ("published", &p.method, p.normalized_cost, p.normalized_reward, p.safe)),
        )
        .enumerate()
        .map(
            |(i, (source, method, normalized_cost, normalized_reward, safe))| EntryPoint {
                key: letter_key(i),
                label: format!("{source} {method}"),
                normalized_cost,
                normalized_reward,
                safe,
                reward_interval: None,
                cost_interval: None,
                paper: true,
            },
        );
    let points: Vec<EntryPoint> = entries.chain(reported).collect();
    entries_svg(&table.task, &points)
}

fn task_section(html: &mut String, table: &TaskTable, paper_label: &str) {
    let thresholds: Vec<String> = table.cost_thresholds.iter().map(|t| t.to_string()).collect();
    let _ = write!(
        html,
        "<h2 id=\"{0}\"><a href=\"/tasks/{0}\">{0}</a></h2>\n<p>{1}; cost thresholds {2}.</p>\n<table class=\"task\"><tr><th>rank</th>\
         <th class=\"name\">entry</th><th class=\"name\">user</th><th>normalized reward [95%]</th><th>normalized cost [95%]</th>\
         <th class=\"name\">interval over</th><th>safe</th><th>author's submissions to the task</th><th class=\"name\">trained</th>\
         <th>submission</th></tr>\n",
        escape(&table.task),
        table.family,
        thresholds.join(", ")
    );
    for e in &table.entries {
        let trained = match &e.reference {
            Some(record) if e.training_seeds.is_empty() => budget(record, &record.seed.to_string()),
            Some(record) => {
                let seeds: Vec<String> = e.training_seeds.iter().map(|s| s.seed.to_string()).collect();
                budget(record, &seeds.join(", "))
            }
            None => "submitted".into(),
        };
        // A method's several seeds: the mean's row links each seed's own entry, with its own score.
        let submissions = if e.training_seeds.is_empty() {
            format!("<a href=\"/submissions/{0}\">{0}</a>", e.submission)
        } else {
            e.training_seeds
                .iter()
                .map(|s| {
                    format!(
                        "<a class=\"seed\" href=\"/submissions/{0}\" title=\"seed {1}: reward {2}, cost {3}\">seed {1}: {0}</a>",
                        s.submission,
                        s.seed,
                        number(s.normalized_reward),
                        number(s.normalized_cost)
                    )
                })
                .collect::<Vec<_>>()
                .join("<br>")
        };
        let covers = if e.interval_covers == crate::leaderboard::EPISODES_ONLY {
            "episodes only (one training seed)".to_owned()
        } else {
            format!("{} training seeds and their episodes", e.training_seeds.len())
        };
        let _ = writeln!(
            html,
            "<tr class=\"entry {} {}\"><td>{}</td><td class=\"name\">{}</td><td class=\"name\"><a href=\"/users/{user}\">{user}</a></td><td>{}</td>\
             <td>{}</td><td class=\"name covers\">{}</td><td>{}</td><td class=\"count\">{}</td><td class=\"name\">{}</td><td>{}</td></tr>",
            if e.safe { "safe" } else { "unsafe" },
            if e.reference.is_some() { "reference" } else { "user" },
            e.rank,
            escape(&e.name),
            with_interval(&e.normalized_reward_interval),
            with_interval(&e.normalized_cost_interval),
            covers,
            if e.safe { "yes" } else { "no" },
            e.author_submissions_to_task,
            escape(&trained),
            submissions,
            user = escape(&e.user),
        );
    }
    html.push_str("</table>\n");
    if table.earlier_protocol_entries > 0 {
        let _ = writeln!(
            html,
            "<p class=\"earlier\">{} more scored under an earlier protocol (not ranked).</p>",
            table.earlier_protocol_entries
        );
    }
    if !table.paper.is_empty() {
        let _ = writeln!(
            html,
            "<table class=\"paper\"><caption>The paper's rows: {}. Beside them, our reference entries of the same \
             method (mean over training seeds).</caption><tr><th class=\"name\">method</th><th>paper reward</th>\
             <th>paper cost</th><th>paper safe</th><th>ours: reward</th><th>ours: cost</th><th>ours: safe</th>\
             <th>verdict agrees</th></tr>",
            escape(paper_label)
        );
        for row in &table.paper {
            let ours = table.agreement.iter().find(|a| a.method == row.method);
            let (reward, cost, safe, agrees) = match ours {
                Some(a) => (
                    number(a.normalized_reward),
                    number(a.normalized_cost),
                    if a.safe { "yes" } else { "no" }.to_owned(),
                    if a.verdict_agrees { "yes" } else { "no" }.to_owned(),
                ),
                None => ("–".into(), "–".into(), "–".into(), "–".into()),
            };
            let _ = writeln!(
                html,
                "<tr class=\"paper-row\"><td class=\"name\">{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td>\
                 <td>{}</td><td>{}</td><td>{}</td></tr>",
                escape(&row.method),
                number(row.normalized_reward),
                number(row.normalized_cost),
                if row.safe { "yes" } else { "no" },
                reward,
                cost,
                safe,
                agrees
            );
        }
        html.push_str("</table>\n");
    }
    if !table.published.is_empty() {
        html.push_str(
            "<table class=\"published\"><caption>Rows methods beyond the paper publish for this task, as their \
             authors report them under their own protocol (not ranked, not part of the agreement). Beside them, our \
             reference entries of the same method.</caption><tr><th class=\"name\">method</th><th>published \
             reward</th><th>published cost</th><th>source</th><th>ours: reward</th><th>ours: cost</th></tr>\n",
        );
        for row in &table.published {
            // Our starter-trained reference entries of the method (each training seed is its own entry): their mean.
            let ours: Vec<&TaskEntry> = table
                .entries
                .iter()
                .filter(|e| {
                    e.reference
                        .as_ref()
                        .is_some_and(|r| r.method == row.method && r.dataset == TrainingData::Starter)
                })
                .collect();
            let mean = |f: fn(&TaskEntry) -> f64| {
                if ours.is_empty() {
                    "–".to_owned()
                } else {
                    number(ours.iter().map(|e| f(e)).sum::<f64>() / ours.len() as f64)
                }
            };
            let _ = writeln!(
                html,
                "<tr class=\"published-row\"><td class=\"name\">{}</td><td>{}</td><td>{}</td><td>{}<br><small>{}\
                 </small></td><td>{}</td><td>{}</td></tr>",
                escape(&row.method),
                number(row.normalized_reward),
                number(row.normalized_cost),
                escape(&row.citation),
                escape(&row.protocol),
                mean(|e| e.normalized_reward),
                mean(|e| e.normalized_cost),
            );
        }
        html.push_str("</table>\n");
    }
    if table.entries.is_empty() && table.paper.is_empty() {
        return;
    }
    match task_svg(table) {
        Ok(svg) => {
            let _ = writeln!(html, "<div class=\"plot\">{svg}</div>");
        }
        Err(e) => {
            let _ = writeln!(html, "<p>plot unavailable: {}</p>", escape(&e));
        }
    }
}

/// The agreement of the entries trained on the full builds, apart from the starter-trained entries' (the figure
/// above it): over the cells they cover, with the same trivial rules beside it.
fn full_build_agreement(html: &mut String, board: &Board) {
    let Some(overall) = board.full_build_agreement.last().filter(|s| s.cells > 0) else {
        return;
    };
    let _ = write!(
        html,
        "<h3>Entries trained on the full builds</h3>\n<p>The same figure for the reference entries trained on the \
         tasks' paper-size full builds (named \"[full build]\" in the tables), over the {} cells they cover; never \
         mixed with the starter-trained entries above.</p>\n<table id=\"full-build-agreement\"><tr><th \
         class=\"name\">family</th>{AGREEMENT_HEADER}</tr>\n",
        overall.cells
    );
    scope_rows(html, board.full_build_agreement.iter().filter(|s| s.cells > 0));
}

/// An agreement table's rows, one per scope (family or overall), and its end.
fn scope_rows<'a>(
    html: &mut String,
    summaries: impl IntoIterator<Item = &'a dsrl_scoring::reference::AgreementSummary>,
) {
    for s in summaries {
        let _ = writeln!(
            html,
            "<tr><td class=\"name\">{}</td>{}</tr>",
            escape(&s.scope),
            agreement_cells(s)
        );
    }
    html.push_str("</table>\n");
}

/// `/leaderboard/agreement`: the fidelity figure. Per family and overall, the share of (task, method) cells whose
/// safe/unsafe verdict agrees with the paper's, then every cell.
pub fn render_agreement(board: &Board) -> String {
    let mut html = format!(
        "<h1>Agreement with the paper</h1>\n<p>Our reference entries (protocol <strong>{}</strong>; mean over \
         training seeds) against {}. A cell agrees when both call the method safe on the task, or both unsafe. Our \
         entries are trained at a fraction of OSRL's budgets on this service's rebuilt datasets, with fewer seeds; \
         the budgets are on each task's table. Beside each share, what trivial rules agree on over the same cells: \
         chance from the two tables' safe rates, every method unsafe, and BC-Safe safe with every other method \
         unsafe.</p>\n<table id=\"agreement\"><tr><th class=\"name\">family</th><th>cells</th>{AGREEMENT_HEADER}</tr>\n",
        escape(&board.protocol.version),
        escape(board.paper_label)
    );
    let rows = |html: &mut String, summaries: &[dsrl_scoring::reference::AgreementSummary]| {
        for s in summaries {
            let _ = writeln!(
                html,
                "<tr><td class=\"name\">{}</td><td>{}</td>{}</tr>",
                escape(&s.scope),
                s.cells,
                agreement_cells(s)
            );
        }
    };
    rows(&mut html, &board.agreement);
    let _ = write!(
        html,
        "</table>\n<h2>Per method</h2>\n<table id=\"agreement-by-method\"><tr><th class=\"name\">method</th>\
         <th>cells</th>{AGREEMENT_HEADER}</tr>\n"
    );
    rows(&mut html, &board.agreement_by_method);
    html.push_str("</table>\n");
    full_build_agreement(&mut html, board);
    html.push_str(
        "<table id=\"cells\"><tr><th class=\"name\">task</th><th class=\"name\">method</th><th>seeds</th>\
         <th>reward</th><th>paper</th><th>Δ</th><th>cost</th><th>paper</th><th>Δ</th><th>safe</th><th>paper</th>\
         <th>agrees</th></tr>\n",
    );
    for t in &board.tasks {
        let starter = t.agreement.iter().map(|a| (a, TrainingData::Starter));
        for (a, dataset) in starter.chain(t.full_build_agreement.iter().map(|a| (a, TrainingData::FullBuild))) {
            let _ = writeln!(
                html,
                "<tr class=\"{}\"><td class=\"name\"><a href=\"/leaderboard#{task}\">{task}</a></td><td class=\"name\">{}</td>\
                 <td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td>\
                 <td>{}</td></tr>",
                if a.verdict_agrees { "agrees" } else { "differs" },
                escape(&method_label(&a.method, dataset)),
                a.seeds,
                number(a.normalized_reward),
                number(a.paper_normalized_reward),
                number(a.reward_difference),
                number(a.normalized_cost),
                number(a.paper_normalized_cost),
                number(a.cost_difference),
                if a.safe { "yes" } else { "no" },
                if a.paper_safe { "yes" } else { "no" },
                if a.verdict_agrees { "yes" } else { "no" },
                task = escape(&a.task),
            );
        }
    }
    html.push_str("</table>\n");
    page("dsrl leaderboard: agreement with the paper", &html)
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
    let _ = writeln!(
        html,
        "<p id=\"provenance\">Protocol {}, scored by {}; trained on dataset version {}.{}</p>",
        view.protocol_version
            .as_deref()
            .map(|v| format!("<code>{}</code>", escape(v)))
            .unwrap_or_else(|| "not recorded".into()),
        view.scored_by
            .as_deref()
            .map(|v| format!("<code>{}</code>", escape(v)))
            .unwrap_or_else(|| "a build not recorded (scored before builds were)".into()),
        view.dataset_version
            .as_deref()
            .map(|v| format!("<code>{}</code>", escape(v)))
            .unwrap_or_else(|| "not stated by the checkpoint".into()),
        view.reference
            .as_ref()
            .map(|r| format!(
                " A {}; code commit <code>{}</code>, {:.0} s of training.",
                escape(&budget(r, &r.seed.to_string())),
                escape(&r.code_commit),
                r.training.seconds
            ))
            .unwrap_or_default()
    );
    if let Some(q) = &view.queue {
        let estimate = match (&q.estimated_start, &q.estimated_finish, &q.estimate_unknown) {
            (Some(start), Some(finish), _) => format!("estimated start {}, finish {}", escape(start), escape(finish)),
            (Some(start), None, Some(why)) => {
                format!("estimated start {}, finish unknown ({})", escape(start), escape(why))
            }
            (_, _, why) => format!(
                "start and finish unknown ({})",
                escape(why.as_deref().unwrap_or("no estimate"))
            ),
        };
        let recent = q.task_scoring_seconds.map_or_else(
            || "no job of this task has been scored yet".to_owned(),
            |s| format!("this task's jobs recently took {s:.0} s"),
        );
        let _ = writeln!(
            html,
            "<p id=\"queue-place\">Queued at position {} ({} jobs ahead, {} being scored, {} evaluators alive); \
             {estimate} ({recent}).</p>",
            q.position,
            q.jobs_ahead.len(),
            q.running,
            q.live_evaluators,
        );
    }
    if let Some(p) = &view.progress {
        let _ = writeln!(
            html,
            "<p id=\"progress\">Scoring: {} of {} episodes done; evaluator <code>{}</code>, last heartbeat {}{}.</p>",
            p.episodes_done,
            p.episodes_total,
            escape(p.evaluator.as_deref().unwrap_or("–")),
            escape(p.last_heartbeat.as_deref().unwrap_or("–")),
            if p.heartbeat_stale {
                " (stale: the evaluator has probably stopped; the job returns to the queue when its lease lapses)"
                    .to_owned()
            } else {
                p.estimated_finish
                    .as_deref()
                    .map_or_else(String::new, |f| format!("; estimated finish {}", escape(f)))
            }
        );
    }
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
    episodes_section(&mut html, view);
    page(&format!("{} — submission {}", view.name, view.id), &html)
}

/// A scored submission's episodes, each with a link to watch it played again (the first of each threshold is the
/// one the section names).
fn episodes_section(html: &mut String, view: &SubmissionView) {
    if view.state != "finished" || view.episodes.is_empty() {
        return;
    }
    html.push_str(
        "<h2>Episodes</h2>\n<p id=\"watch\">Watch an episode: it is played again on this server's simulators from its \
         held seed with this policy, drawn, and kept (the first request queues it; replays wait while submissions are \
         scored). ",
    );
    for t in &view.thresholds {
        let _ = write!(
            html,
            "<a class=\"watch-first\" href=\"/submissions/{}/episodes/{}/0\">threshold {}, episode 0</a> ",
            view.id, t.cost_threshold, t.cost_threshold
        );
    }
    html.push_str(
        "</p>\n<table id=\"episodes\"><tr><th>cost threshold</th><th>episode</th><th>reward return</th>\
         <th>cost return</th><th>length</th><th></th></tr>\n",
    );
    for e in &view.episodes {
        let _ = writeln!(
            html,
            "<tr><td>{}</td><td>{}</td><td>{:.2}</td><td>{:.2}</td><td>{}</td>\
             <td class=\"name\"><a href=\"/submissions/{}/episodes/{}/{}\">watch</a></td></tr>",
            e.cost_threshold, e.episode, e.reward_return, e.cost_return, e.length, view.id, e.cost_threshold, e.episode
        );
    }
    html.push_str("</table>\n");
}

/// An episode's page: its animation beside its step-by-step reward and cumulative cost; while its replay waits,
/// a note that reloads the page every five seconds (a `refresh` meta element: the pages run no script).
pub fn render_episode(submission: i64, threshold: f64, episode: u32, state: &ReplayState) -> String {
    let title = format!("submission {submission}, cost threshold {threshold}, episode {episode}");
    let mut html = format!(
        "<h1>Episode {episode} <small>cost threshold {threshold} · <a href=\"/submissions/{submission}\">submission \
         {submission}</a></small></h1>\n"
    );
    match state {
        ReplayState::Queued { ahead } => {
            let _ = writeln!(
                html,
                "<p id=\"replay-queued\">Being replayed ({ahead} replays ahead; replays wait while submissions are \
                 scored). This page reloads itself.</p>"
            );
            return page(&title, &html).replacen("<head>", "<head><meta http-equiv=\"refresh\" content=\"5\">", 1);
        }
        ReplayState::Failed(reason) => {
            let _ = writeln!(
                html,
                "<p id=\"replay-failed\" class=\"error\">The replay failed: {}</p>",
                escape(reason)
            );
        }
        ReplayState::Ready { replay, .. } => {
            let base = format!("/v1/submissions/{submission}/episodes/{threshold}/{episode}");
            let _ = writeln!(
                html,
                "<p id=\"replay-summary\">{}: reward return {:.2}, cost return {:.2}, {} steps, the scored \
                 episode's. Played again on protocol <code>{}</code> by <code>{}</code>, {}; one frame every {} \
                 step(s).</p>\n<div style=\"display:flex;gap:1em;align-items:flex-start\"><img id=\"replay\" \
                 src=\"{base}/replay.gif\" width=\"{}\" height=\"{}\" alt=\"the episode, drawn\">{}</div>\n\
                 <p><a href=\"{base}/replay.json\">every step's reward and cost (JSON)</a> · \
                 <a href=\"{base}/replay.gif\">the animation</a> (sha256 <code>{}</code>)</p>",
                escape(&replay.task),
                replay.reward_return,
                replay.cost_return,
                replay.length,
                escape(&replay.protocol_version),
                escape(&replay.rendered_by),
                escape(&replay.rendered_at),
                replay.frame_steps.first().copied().unwrap_or(1),
                replay.frame_width * 2,
                replay.frame_height * 2,
                replay_svg(replay),
                escape(&replay.gif_sha256),
            );
        }
    }
    page(&title, &html)
}

/// Each step's reward (above) and the cost accumulated so far against the threshold (below), as an inline SVG.
pub fn replay_svg(replay: &EpisodeReplay) -> String {
    const WIDTH: f64 = 480.0;
    const PANEL: f64 = 120.0;
    const MARGIN: f64 = 40.0;
    let steps = replay.rewards.len().max(1) as f64;
    let cumulative: Vec<f64> = replay
        .costs
        .iter()
        .scan(0.0, |sum, c| {
            *sum += c;
            Some(*sum)
        })
        .collect();
    let mut svg = format!(
        "<svg id=\"replay-plot\" xmlns=\"http://www.w3.org/2000/svg\" width=\"{}\" height=\"{}\" \
         font-family=\"sans-serif\" font-size=\"11\">",
        WIDTH + MARGIN,
        2.0 * PANEL + 3.0 * MARGIN
    );
    let panels = [
        ("reward per step", &replay.rewards[..], None, "#2a6"),
        ("cost so far", &cumulative[..], Some(replay.cost_threshold), "#a33"),
    ];
    for (k, (label, values, limit, colour)) in panels.into_iter().enumerate() {
        let top = MARGIN + k as f64 * (PANEL + MARGIN);
        let lowest = values.iter().copied().chain(limit).fold(0.0f64, f64::min);
        let highest = values.iter().copied().chain(limit).fold(lowest + 1e-9, f64::max);
        let y = |v: f64| top + PANEL * (1.0 - (v - lowest) / (highest - lowest));
        let x = |i: usize| MARGIN + WIDTH * (i as f64 + 1.0) / steps;
        let _ = write!(
            svg,
            "<text x=\"{MARGIN}\" y=\"{:.1}\">{label} (from {} to {})</text><rect x=\"{MARGIN}\" y=\"{top:.1}\" \
             width=\"{WIDTH}\" height=\"{PANEL}\" fill=\"none\" stroke=\"#ccc\"/>",
            top - 6.0,
            number(lowest),
            number(highest)
        );
        if let Some(limit) = limit {
            let _ = write!(
                svg,
                "<line x1=\"{MARGIN}\" x2=\"{:.1}\" y1=\"{:.1}\" y2=\"{:.1}\" stroke=\"#888\" \
                 stroke-dasharray=\"4 3\"/><text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">threshold {}</text>",
                MARGIN + WIDTH,
                y(limit),
                y(limit),
                MARGIN + WIDTH - 4.0,
                y(limit) - 3.0,
                number(limit)
            );
        }
        let points: Vec<String> = values
            .iter()
            .enumerate()
            .map(|(i, &v)| format!("{:.1},{:.1}", x(i), y(v)))
            .collect();
        let _ = write!(
            svg,
            "<polyline fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.2\" points=\"{}\"/>",
            points.join(" ")
        );
    }
    let _ = write!(
        svg,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">step (1 to {})</text></svg>",
        MARGIN + WIDTH / 2.0,
        2.0 * PANEL + 3.0 * MARGIN - 8.0,
        replay.rewards.len()
    );
    svg
}
