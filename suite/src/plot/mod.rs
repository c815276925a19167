//! The cost–reward return scatter of a dataset, like the DSRL paper's figures: one point per trajectory, the
//! task's benchmark cost thresholds as dashed vertical lines. For a filtered dataset, the points removed by the
//! filter stay visible in gray and relabelled outliers are drawn in red, as in DSRL's own filter plot.
//!
//! The leaderboard's picture of entries on the normalized cost–reward plane is in `entries`, the placement of its
//! point keys in `keys`.

mod entries;
mod keys;

use plotters::prelude::*;

pub use entries::{EntryPoint, entries_svg};

use crate::catalog::Task;
use crate::episode::Fate;

/// One trajectory on the plot.
#[derive(Debug, Clone, Copy)]
pub struct Point {
    pub cost_return: f32,
    pub reward_return: f32,
    pub fate: Fate,
}

/// Renders the scatter as an SVG document; `subtitle` (e.g. the filter) goes on a second, smaller line.
pub fn cost_reward_svg(task: &Task, title: &str, subtitle: Option<&str>, points: &[Point]) -> Result<String, String> {
    let (mut xmax, mut ymin, mut ymax) = (1.0f32, f32::INFINITY, f32::NEG_INFINITY);
    for p in points {
        xmax = xmax.max(p.cost_return);
        ymin = ymin.min(p.reward_return);
        ymax = ymax.max(p.reward_return);
    }
    for &k in &task.cost_thresholds {
        xmax = xmax.max(k as f32);
    }
    if !ymin.is_finite() {
        (ymin, ymax) = (task.min_episode_reward as f32, task.max_episode_reward as f32);
    }
    let pad = ((ymax - ymin) * 0.05).max(1.0);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (800, 560)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let root = match subtitle {
            Some(text) => {
                let (top, rest) = root.split_vertically(24);
                top.draw_text(text, &("sans-serif", 13).into_text_style(&top), (16, 8))
                    .map_err(|e| e.to_string())?;
                rest
            }
            None => root,
        };
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(16)
            .x_label_area_size(44)
            .y_label_area_size(64)
            .build_cartesian_2d(0f32..xmax * 1.05, (ymin - pad)..(ymax + pad))
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("cost return")
            .y_desc("reward return")
            .draw()
            .map_err(|e| e.to_string())?;
        let groups = [
            (Fate::RemovedByDensity, RGBColor(190, 190, 190), "removed by density"),
            (Fate::RemovedByInpaint, RGBColor(150, 150, 150), "removed by inpainting"),
            (Fate::RemovedByEpsilon, RGBColor(110, 110, 110), "removed by epsilon"),
            (Fate::Kept, RGBColor(30, 144, 255), "trajectories"),
            (Fate::Relabelled, RGBColor(255, 99, 71), "relabelled outliers"),
        ];
        for (fate, color, label) in groups {
            let series: Vec<(f32, f32)> = points
                .iter()
                .filter(|p| p.fate == fate)
                .map(|p| (p.cost_return, p.reward_return))
                .collect();
            if series.is_empty() {
                continue;
            }
            chart
                .draw_series(series.into_iter().map(move |xy| Circle::new(xy, 3, color.filled())))
                .map_err(|e| e.to_string())?
                .label(label)
                .legend(move |(x, y)| Circle::new((x, y), 4, color.filled()));
        }
        for &k in &task.cost_thresholds {
            let k = k as f32;
            let dashes = DashedLineSeries::new([(k, ymin - pad), (k, ymax + pad)], 6, 4, BLACK.stroke_width(1));
            chart.draw_series(dashes).map_err(|e| e.to_string())?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(svg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::catalog::Catalog;

    #[test]
    fn draws_points_thresholds_and_legend() {
        let catalog = Catalog::embedded().unwrap();
        let task = catalog.get("OfflineCarCircle-v0").unwrap();
        let points = [
            Point {
                cost_return: 5.0,
                reward_return: 100.0,
                fate: Fate::Kept,
            },
            Point {
                cost_return: 60.0,
                reward_return: 400.0,
                fate: Fate::Relabelled,
            },
            Point {
                cost_return: 90.0,
                reward_return: 500.0,
                fate: Fate::RemovedByDensity,
            },
        ];
        let svg = cost_reward_svg(task, "OfflineCarCircle-v0", Some("density=0.5"), &points).unwrap();
        assert!(svg.contains("density=0.5"));
        assert!(svg.starts_with("<svg"));
        assert_eq!(svg.matches("<circle").count(), 3 + 3, "points plus legend markers");
        assert!(svg.contains("relabelled outliers") && svg.contains("cost return"));
        // Three thresholds (10, 20, 40), each a dashed series of several segments.
        assert!(svg.matches("<polyline").count() >= 3 || svg.matches("<line").count() > 10);
    }
}
