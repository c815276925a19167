//! The leaderboard's picture: entries (and a task's reported rows) on the normalized cost–reward plane.
//!
//! Each point carries a short key (an entry's rank, a letter for the rest) placed beside its marker clear of the
//! others (see `keys`), and a legend to the right of the plot says what each key is. Full names beside the markers
//! would overlap wherever entries score alike, which on this board is most of the time.

use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::keys::{PixelBox, place_keys};

/// One point of the picture: a leaderboard entry or one of a task's reported rows.
#[derive(Debug, Clone)]
pub struct EntryPoint {
    /// Drawn beside the marker and at the head of its legend line: short (an entry's rank, a letter), so that the
    /// keys of points scored alike find room around them.
    pub key: String,
    /// The legend's words for the point.
    pub label: String,
    pub normalized_cost: f64,
    pub normalized_reward: f64,
    pub safe: bool,
    /// The 95% intervals, drawn as whiskers; `None` for a point without one (the reported rows).
    pub reward_interval: Option<(f64, f64)>,
    pub cost_interval: Option<(f64, f64)>,
    /// One of the reported rows (the paper's, or a later method's published numbers): a hollow square, not a
    /// filled circle.
    pub paper: bool,
}

const SAFE: RGBColor = RGBColor(30, 144, 255);
const UNSAFE: RGBColor = RGBColor(220, 60, 40);
/// The plot's own size; the legend is as wide as its longest line needs, and the picture as tall as its lines.
const PLOT_WIDTH: u32 = 560;
const PLOT_HEIGHT: u32 = 400;
const MARKER_RADIUS: i32 = 5;
/// Font sizes as plotters takes them (it writes them into the SVG as 1/1.24 of this: about 10.5 px for keys, 11.3 px
/// for the legend). The widths are estimates for a sans-serif face at those sizes (SVG text is laid out by the
/// viewer, so the exact width is not known here), erring wide.
const KEY_FONT: u32 = 13;
const KEY_CHAR_WIDTH: i32 = 7;
const KEY_HEIGHT: i32 = 12;
const LEGEND_FONT: u32 = 14;
const LEGEND_CHAR_WIDTH: u32 = 7;
const LEGEND_LINE: u32 = 16;
/// Where a legend line's key and words start, from the legend's left edge (after the marker).
const LEGEND_KEY_X: i32 = 22;
const LEGEND_TEXT_X: i32 = 50;

/// The entries of a leaderboard table on the normalized cost–reward plane, safe ones in blue, unsafe in red, with
/// their intervals as whiskers, reported rows as hollow squares, and the safety boundary (normalized cost 1) dashed.
pub fn entries_svg(title: &str, entries: &[EntryPoint]) -> Result<String, String> {
    let finite = |x: f64| if x.is_finite() { x } else { 0.0 };
    // Every value the picture shows, whiskers included, sets the axes.
    let costs = entries.iter().flat_map(|e| {
        [
            Some(e.normalized_cost),
            e.cost_interval.map(|i| i.0),
            e.cost_interval.map(|i| i.1),
        ]
        .into_iter()
        .flatten()
    });
    let rewards = || {
        entries.iter().flat_map(|e| {
            [
                Some(e.normalized_reward),
                e.reward_interval.map(|i| i.0),
                e.reward_interval.map(|i| i.1),
            ]
            .into_iter()
            .flatten()
        })
    };
    let xmax = costs.map(finite).fold(2.0f64, f64::max) * 1.1;
    let ymin = rewards().map(finite).fold(0.0f64, f64::min) - 0.05;
    let ymax = rewards().map(finite).fold(1.0f64, f64::max) + 0.05;

    let longest = entries.iter().map(|e| e.label.chars().count()).max().unwrap_or(0) as u32;
    let legend_width = if entries.is_empty() {
        0
    } else {
        (LEGEND_TEXT_X as u32 + LEGEND_CHAR_WIDTH * longest + 12).clamp(160, 420)
    };
    let height = PLOT_HEIGHT.max(44 + LEGEND_LINE * entries.len() as u32);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (PLOT_WIDTH + legend_width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let (plot, legend) = root.split_horizontally(PLOT_WIDTH);
        let mut chart = ChartBuilder::on(&plot)
            .caption(title, ("sans-serif", 16))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(52)
            .build_cartesian_2d(0f64..xmax, ymin..ymax)
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("normalized cost")
            .y_desc("normalized reward")
            .draw()
            .map_err(|e| e.to_string())?;
        let boundary = DashedLineSeries::new([(1.0, ymin), (1.0, ymax)], 6, 4, BLACK.stroke_width(1));
        chart.draw_series(boundary).map_err(|e| e.to_string())?;
        let color = |e: &EntryPoint| if e.safe { SAFE } else { UNSAFE };
        // Whiskers first, so that no marker is hidden under another point's whisker.
        for e in entries {
            let xy = (finite(e.normalized_cost), finite(e.normalized_reward));
            if let Some((low, high)) = e.cost_interval {
                chart
                    .draw_series(LineSeries::new(
                        [(finite(low), xy.1), (finite(high), xy.1)],
                        color(e).mix(0.6).stroke_width(1),
                    ))
                    .map_err(|e| e.to_string())?;
            }
            if let Some((low, high)) = e.reward_interval {
                chart
                    .draw_series(LineSeries::new(
                        [(xy.0, finite(low)), (xy.0, finite(high))],
                        color(e).mix(0.6).stroke_width(1),
                    ))
                    .map_err(|e| e.to_string())?;
            }
        }
        let mut markers = Vec::with_capacity(entries.len());
        for e in entries {
            let xy = (finite(e.normalized_cost), finite(e.normalized_reward));
            let at = chart.backend_coord(&xy);
            markers.push(at);
            draw_marker(&plot, at, e.paper, color(e))?;
        }

        // The keys, placed clear of each other inside the plotting area.
        let (xs, ys) = chart.plotting_area().get_pixel_range();
        let area = PixelBox {
            left: xs.start,
            top: ys.start,
            right: xs.end,
            bottom: ys.end,
        };
        let sizes: Vec<(i32, i32)> = entries
            .iter()
            .map(|e| (KEY_CHAR_WIDTH * e.key.chars().count() as i32 + 2, KEY_HEIGHT))
            .collect();
        let key_style = ("sans-serif", KEY_FONT)
            .into_text_style(&plot)
            .pos(Pos::new(HPos::Center, VPos::Center));
        for ((e, &marker), placed) in
            entries
                .iter()
                .zip(&markers)
                .zip(place_keys(&markers, &sizes, area, MARKER_RADIUS))
        {
            let b = placed.at;
            if placed.leader {
                plot.draw(&PathElement::new(
                    [marker, b.nearest(marker)],
                    RGBColor(120, 120, 120).stroke_width(1),
                ))
                .map_err(|e| e.to_string())?;
            }
            let centre = ((b.left + b.right) / 2, (b.top + b.bottom) / 2);
            plot.draw(&Text::new(e.key.clone(), centre, key_style.clone().color(&color(e))))
                .map_err(|e| e.to_string())?;
        }

        // The legend: each point's marker, key and words, in the order given (ranked entries first).
        if !entries.is_empty() {
            let head = ("sans-serif", LEGEND_FONT)
                .into_text_style(&legend)
                .color(&RGBColor(90, 90, 90));
            legend
                .draw(&Text::new("blue: safe · red: unsafe", (8, 14), head))
                .map_err(|e| e.to_string())?;
            let style = ("sans-serif", LEGEND_FONT)
                .into_text_style(&legend)
                .pos(Pos::new(HPos::Left, VPos::Center));
            for (i, e) in entries.iter().enumerate() {
                let y = 44 + (LEGEND_LINE as i32) * i as i32;
                draw_marker(&legend, (14, y), e.paper, color(e))?;
                legend
                    .draw(&Text::new(
                        e.key.clone(),
                        (LEGEND_KEY_X, y),
                        style.clone().color(&color(e)),
                    ))
                    .map_err(|e| e.to_string())?;
                legend
                    .draw(&Text::new(e.label.clone(), (LEGEND_TEXT_X, y), style.clone()))
                    .map_err(|e| e.to_string())?;
            }
        }
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(svg)
}

/// A point's marker at a pixel position of `area`: a filled circle for an entry, a hollow square for a reported row.
fn draw_marker<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    at: (i32, i32),
    paper: bool,
    color: RGBColor,
) -> Result<(), String> {
    let r = MARKER_RADIUS;
    let drawn = if paper {
        area.draw(&Rectangle::new(
            [(at.0 - r + 1, at.1 - r + 1), (at.0 + r - 1, at.1 + r - 1)],
            color.stroke_width(2),
        ))
    } else {
        area.draw(&Circle::new(at, r, color.filled()))
    };
    drawn.map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(key: &str, label: &str, cost: f64, reward: f64, paper: bool) -> EntryPoint {
        EntryPoint {
            key: key.into(),
            label: label.into(),
            normalized_cost: cost,
            normalized_reward: reward,
            safe: cost <= 1.0,
            reward_interval: (!paper).then_some((reward - 0.1, reward + 0.1)),
            cost_interval: (!paper).then_some((cost - 0.2, cost + 0.2)),
            paper,
        }
    }

    #[test]
    fn every_point_has_its_marker_its_key_and_a_legend_line() {
        let points = [
            point("1", "BC-Safe [full build] (seeds 0, 1, 2)", 0.5, 0.3, false),
            point("2", "CPQ (seed 0)", 1.50, 0.6, false),
            point("3", "CDT (seed 0)", 1.51, 0.61, false),
            point("a", "paper CPQ", 0.35, 0.57, true),
        ];
        let svg = entries_svg("OfflinePointGoal1Gymnasium-v0", &points).unwrap();
        assert!(svg.starts_with("<svg"));
        // Three entries' circles, in the plot and again in the legend; the reported row's square likewise.
        assert_eq!(svg.matches("<circle").count(), 3 * 2, "{svg}");
        for p in &points {
            assert_eq!(
                svg.matches(&format!(">\n{}\n</text>", p.label)).count(),
                1,
                "{}",
                p.label
            );
            assert_eq!(
                svg.matches(&format!(">\n{}\n</text>", p.key)).count(),
                2,
                "key {}",
                p.key
            );
        }
        // The legend widens the picture beyond the plot.
        let width: u32 = svg
            .split("width=\"")
            .nth(1)
            .unwrap()
            .split('"')
            .next()
            .unwrap()
            .parse()
            .unwrap();
        assert!(width > PLOT_WIDTH, "{width}");
    }

    #[test]
    fn an_empty_table_draws_the_bare_plane() {
        let svg = entries_svg("bullet (IQM over tasks)", &[]).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("normalized cost"));
        assert_eq!(svg.matches("<circle").count(), 0);
    }
}
