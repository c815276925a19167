//! The dataset browser as a person sees it, in headless Chromium: `/` lists the 38 tasks by family with what is
//! hosted and a plot thumbnail for each hosted one; a task's card shows the paper's numbers beside ours, and its
//! filter form plans a DSRL filter from the episode index, says what each step did and redraws the plot (the
//! relabelled outliers in their own colour in the screenshot); a filter that does not apply shows the reason on the
//! page.

use crate::dsrl_download::starters;
use crate::leaderboard::{chromium, pixels_of_colour};
use crate::{Env, block_on, s};

fn dom(url: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    String::from_utf8(chromium(&dir.path().join("profile"), &["--dump-dom", url]).stdout).unwrap()
}

#[test]
fn the_dataset_browser_lists_every_task_and_its_card_plans_filters() {
    let dir = tempfile::tempdir().unwrap();
    let root = starters(dir.path(), &["OfflineBallRun-v0"]);
    let env = Env::with(&["--starter-datasets", s(&root)], &[]);
    let url = env.server.url.clone();

    let index = dom(&format!("{url}/"));
    assert_eq!(index.matches("<tr class=\"task").count(), 38, "{index}");
    assert_eq!(index.matches("<tr class=\"task hosted\"").count(), 1, "{index}");
    let ballrun = &index[index.find("id=\"OfflineBallRun-v0\"").unwrap()..];
    let ballrun = &ballrun[..ballrun.find("</tr>").unwrap()];
    assert!(
        ballrun.contains("/v1/datasets/OfflineBallRun-v0/versions/latest/plot.svg"),
        "{ballrun}"
    );
    assert!(index.contains("not hosted yet"));
    assert!(index.contains("href=\"/leaderboard\""));
    assert!(index.contains("Safety-Gymnasium navigation") && index.contains("MetaDrive"));

    // The card, with the paper's outlier filter at 5%.
    let card_url = format!("{url}/tasks/OfflineBallRun-v0?filter=noise%3D0.05");
    let card = dom(&card_url);
    assert!(card.contains("SafetyBallRun-v0-80-940.hdf5"), "the paper's file name");
    let counts = &card[card.find("id=\"filter-counts\"").expect("the plan's counts")..];
    let relabelled: u64 = counts
        .split("relabelled as tempting outliers</td><td>")
        .nth(1)
        .and_then(|rest| rest.split('<').next())
        .unwrap()
        .parse()
        .unwrap();
    assert!(relabelled > 0, "{counts}");
    assert!(
        card.contains("plot.svg?filter=noise%3D0.05"),
        "the plot is redrawn for the filter"
    );
    assert!(card.contains("id=\"download-parquet\"") && card.contains("id=\"download-hdf5\""));
    assert!(card.contains("id=\"provenance\""));
    // The corner count is the noise filter's own predicate on the served index.
    let manifest = crate::get_json(&format!("{url}/v1/datasets/OfflineBallRun-v0/versions/latest"));
    let catalog = dsrl_suite::Catalog::embedded().unwrap();
    let task = catalog.get("OfflineBallRun-v0").unwrap();
    let index: Vec<dsrl_suite::EpisodeSummary> = serde_json::from_value(manifest["episode_index"].clone()).unwrap();
    let corner = index
        .iter()
        .filter(|e| dsrl_filters::plan::in_tempting_corner(task, e.cost_return, e.reward_return))
        .count();
    assert!(
        card.contains(&format!("reward ≥ max reward/2)</td><td>{corner}</td>")),
        "the card's corner count is not {corner}"
    );

    // The screenshot shows the redrawn plot: kept trajectories in blue and the relabelled ones in tomato red.
    let shot = dir.path().join("card.png");
    chromium(
        &dir.path().join("profile-shot"),
        &[
            &format!("--screenshot={}", shot.display()),
            "--window-size=1280,2000",
            &card_url,
        ],
    );
    let (kept, outliers) = (
        pixels_of_colour(&shot, [30, 144, 255]),
        pixels_of_colour(&shot, [255, 99, 71]),
    );
    assert!(
        kept > 100 && outliers > 10,
        "the plot did not render: {kept} blue, {outliers} red pixels"
    );

    // A filter that does not apply: the page says why.
    let bad = format!("{url}/tasks/OfflineBallRun-v0?filter=noise%3D7");
    let (status, text) = block_on(async move {
        let r = reqwest::get(&bad).await.unwrap();
        (r.status().as_u16(), r.text().await.unwrap())
    });
    assert_eq!(status, 200);
    assert!(text.contains("id=\"filter-error\"") && text.contains("noise"), "{text}");
}
