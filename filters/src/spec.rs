//! What a user asks for, and its canonical form. Users type `noise=0.05` (the paper's "noise level", which is
//! DSRL's `outliers_percent`), DSRL's own names, or our aliases; all are checked against their ranges and reduced
//! to one canonical string that names the computation (it is the cache key and is shown in manifests).

use std::collections::BTreeMap;
use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use dsrl_suite::catalog::Task;

/// `data/density_presets.csv`, compiled in: the per-task grid parameters of DSRL's `DENSITY_CFG`.
pub const EMBEDDED_DENSITY_PRESETS_CSV: &str = include_str!("../../data/density_presets.csv");

/// Grid parameters of the density filter.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    pub cbins: u32,
    pub rbins: u32,
    pub max_npb: u32,
    pub min_npb: u32,
}

/// One relative rectangle of the inpaint filter: cost band `[pcmin, pcmax]` of the task's cost range, reward band
/// `[prmin, prmax]` of the rewards inside that cost band.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct InpaintRange {
    pub pcmin: f64,
    pub pcmax: f64,
    pub prmin: f64,
    pub prmax: f64,
}

/// A validated filter request in DSRL's terms. `None` means the filter is off.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FilterSpec {
    pub grid: Option<Grid>,
    pub outliers_percent: Option<f64>,
    pub inpaint: Option<InpaintRange>,
    pub epsilon: Option<f64>,
    pub noise_scale: Option<f64>,
    /// Used by outliers and epsilon; default: the task's lowest benchmark threshold.
    pub target_cost: f64,
    /// Seeds CPython's `random` for the density filter (the only filter it changes).
    pub seed: u64,
}

/// The paper's two partial-discarding presets, as inpaint rectangles.
pub fn discard_preset(name: &str) -> Option<InpaintRange> {
    match name {
        // High-reward trajectories in the upper half of the cost range: the ones that tempt a policy to
        // trade safety for reward.
        "tempting" => Some(InpaintRange {
            pcmin: 0.5,
            pcmax: 1.0,
            prmin: 0.5,
            prmax: 1.0,
        }),
        // Low-reward trajectories in the lower half of the cost range: the conservative, low-value data.
        "low-reward" => Some(InpaintRange {
            pcmin: 0.0,
            pcmax: 0.5,
            prmin: 0.0,
            prmax: 0.5,
        }),
        _ => None,
    }
}

/// The keys a filter string accepts, with what they take: shown whenever a request is rejected.
pub const VALID_KEYS: &str = "valid keys: noise|outliers_percent (0 < p <= 1), obs_noise|noise_scale (0 < s <= 100), \
density (0 < d < 1; the task's preset grid) with optional cbins|rbins (1..=1000), max_npb (>= 1), min_npb (>= 0), \
inpaint|inpaint_ranges (pcmin:pcmax:prmin:prmax, each in [0, 1], min <= max; one range), \
discard (tempting|low-reward), epsilon (finite, not 0, |e| <= 1e9), target_cost (0..=100000; >= 1 with outliers), seed (0..2^64)";

/// The largest `target_cost` accepted. An episode's cost return is at most its number of steps (unit costs; the
/// longest horizon is 1000) and relabelled outliers draw that many unit costs, so anything above this is a
/// mistake, and an unbounded value would saturate DSRL's `int(target_cost)`.
pub const MAX_TARGET_COST: f64 = 100_000.0;
/// The largest `|epsilon|` accepted: returns are at most a few thousand.
pub const MAX_EPSILON: f64 = 1e9;

/// A filter that cannot be applied: a malformed request (the message lists the valid keys), or a request that
/// this dataset cannot satisfy (for example too few outlier candidates), where DSRL's reference would fail.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}", self.render())]
pub struct FilterError {
    pub message: String,
    pub about_data: bool,
}

impl FilterError {
    /// A request this dataset cannot satisfy.
    pub fn data(message: impl Into<String>) -> Self {
        FilterError {
            message: message.into(),
            about_data: true,
        }
    }

    fn render(&self) -> String {
        if self.about_data {
            format!("filter not applicable to this dataset: {}", self.message)
        } else {
            format!("invalid filter: {}; {VALID_KEYS}", self.message)
        }
    }
}

fn err(message: impl Into<String>) -> FilterError {
    FilterError {
        message: message.into(),
        about_data: false,
    }
}

/// Density presets by (task id, density as written in the CSV).
pub fn density_presets() -> BTreeMap<(String, String), Grid> {
    let mut presets = BTreeMap::new();
    for line in EMBEDDED_DENSITY_PRESETS_CSV
        .lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
    {
        let f: Vec<&str> = line.split(',').collect();
        let num = |i: usize| {
            f[i].trim()
                .parse::<u32>()
                .expect("density_presets.csv is validated by a test")
        };
        presets.insert(
            (f[0].to_owned(), canonical_number(f[1].parse::<f64>().expect("density"))),
            Grid {
                cbins: num(2),
                rbins: num(3),
                max_npb: num(4),
                min_npb: num(5),
            },
        );
    }
    presets
}

/// Shortest decimal that reads back as the same f64 (as Python's `repr`).
pub fn canonical_number(v: f64) -> String {
    let s = format!("{v:?}");
    s.strip_suffix(".0").map(str::to_owned).unwrap_or(s)
}

fn number(key: &str, value: &str) -> Result<f64, FilterError> {
    match value.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(err(format!("{key}={value:?} is not a finite number"))),
    }
}

fn integer(key: &str, value: &str) -> Result<u64, FilterError> {
    value
        .trim()
        .parse::<u64>()
        .map_err(|_| err(format!("{key}={value:?} is not a non-negative integer")))
}

/// The `key=value` pairs of a filter text, keys under their canonical names (aliases folded), each key once.
fn key_values(text: &str) -> Result<BTreeMap<String, String>, FilterError> {
    let mut pairs: BTreeMap<String, String> = BTreeMap::new();
    for item in text.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (key, value) = item
            .split_once('=')
            .ok_or_else(|| err(format!("{item:?} is not key=value")))?;
        let key = match key.trim() {
            "noise" | "outliers" | "outliers_percent" => "outliers_percent",
            "obs_noise" | "noise_scale" => "noise_scale",
            "inpaint" | "inpaint_ranges" => "inpaint",
            k @ ("discard" | "epsilon" | "density" | "cbins" | "rbins" | "max_npb" | "min_npb" | "target_cost"
            | "seed") => k,
            other => return Err(err(format!("unknown key {other:?}"))),
        };
        if pairs.insert(key.to_owned(), value.trim().to_owned()).is_some() {
            return Err(err(format!("{key} is given twice (counting its aliases)")));
        }
    }
    Ok(pairs)
}

/// The range `inpaint` or `discard` (a preset) names; both at once is an error.
fn inpaint_range(inpaint: Option<&str>, discard: Option<&str>) -> Result<Option<InpaintRange>, FilterError> {
    Ok(match (inpaint, discard) {
        (Some(_), Some(_)) => return Err(err("give either inpaint or discard, not both")),
        (None, None) => None,
        (None, Some(name)) => Some(
            discard_preset(name)
                .ok_or_else(|| err(format!("discard={name:?} is not a preset (tempting, low-reward)")))?,
        ),
        (Some(v), None) => {
            if v.contains(';') {
                return Err(err(
                    "several inpaint ranges are not supported: DSRL stacks their results into one NumPy \
                     array, which fails (NumPy >= 1.24) or misbehaves when the ranges remove different numbers \
                     of trajectories",
                ));
            }
            let parts: Vec<&str> = v.split(':').collect();
            if parts.len() != 4 {
                return Err(err(format!("inpaint={v:?} needs four numbers pcmin:pcmax:prmin:prmax")));
            }
            let n = parts
                .iter()
                .map(|p| number("inpaint", p))
                .collect::<Result<Vec<_>, _>>()?;
            let r = InpaintRange {
                pcmin: n[0],
                pcmax: n[1],
                prmin: n[2],
                prmax: n[3],
            };
            if n.iter().any(|x| !(0.0..=1.0).contains(x)) || r.pcmin > r.pcmax || r.prmin > r.prmax {
                return Err(err(format!(
                    "inpaint={v:?}: each value in [0, 1] with pcmin <= pcmax, prmin <= prmax"
                )));
            }
            Some(r)
        }
    })
}

/// The density filter's grid: the task's preset for `density`, each of `cbins`, `rbins`, `max_npb` and `min_npb`
/// given over it; `None` when none of them is given.
fn density_grid(pairs: &BTreeMap<String, String>, task: &Task) -> Result<Option<Grid>, FilterError> {
    let get = |k: &str| pairs.get(k).map(String::as_str);
    let grid_keys = ["cbins", "rbins", "max_npb", "min_npb"];
    Ok(
        if get("density").is_some() || grid_keys.iter().any(|k| get(k).is_some()) {
            let preset = match get("density") {
                Some(v) => {
                    let d = number("density", v)?;
                    if !(d > 0.0 && d < 1.0) {
                        return Err(err(format!("density={d} is outside (0, 1); 1 means no density filter")));
                    }
                    density_presets()
                        .get(&(task.id.to_string(), canonical_number(d)))
                        .copied()
                }
                None => None,
            };
            let mut values = [0u64; 4];
            for (i, key) in grid_keys.iter().enumerate() {
                values[i] = match (get(key), preset) {
                    (Some(v), _) => integer(key, v)?,
                    (None, Some(p)) => [p.cbins, p.rbins, p.max_npb, p.min_npb][i] as u64,
                    (None, None) => {
                        let known: Vec<String> = density_presets()
                            .keys()
                            .filter(|(t, _)| t == task.id.as_str())
                            .map(|(_, d)| d.clone())
                            .collect();
                        return Err(err(format!(
                            "{} has no density preset for {}; presets: {}; or give cbins, rbins, max_npb and min_npb",
                            task.id,
                            get("density").unwrap_or("(none)"),
                            if known.is_empty() {
                                "none".to_owned()
                            } else {
                                known.join(", ")
                            }
                        )));
                    }
                };
            }
            let [cbins, rbins, max_npb, min_npb] = values;
            if !(1..=1000).contains(&cbins) || !(1..=1000).contains(&rbins) {
                return Err(err("cbins and rbins must be in 1..=1000"));
            }
            if max_npb == 0 || max_npb > 1_000_000 || min_npb > 1_000_000 {
                return Err(err("max_npb must be >= 1 and the bin counts at most 1000000"));
            }
            Some(Grid {
                cbins: cbins as u32,
                rbins: rbins as u32,
                max_npb: max_npb as u32,
                min_npb: min_npb as u32,
            })
        } else {
            None
        },
    )
}

impl FilterSpec {
    /// Parses `key=value` pairs separated by commas (several `--filter` flags are joined with commas).
    pub fn parse(text: &str, task: &Task) -> Result<Option<FilterSpec>, FilterError> {
        let pairs = key_values(text)?;
        if pairs.is_empty() {
            return Ok(None);
        }
        let get = |k: &str| pairs.get(k).map(String::as_str);

        let outliers_percent = match get("outliers_percent") {
            None => None,
            Some(v) => match number("outliers_percent", v)? {
                p if p > 0.0 && p <= 1.0 => Some(p),
                p => return Err(err(format!("outliers_percent={p} is outside (0, 1]"))),
            },
        };
        let noise_scale = match get("noise_scale") {
            None => None,
            Some(v) => match number("noise_scale", v)? {
                s if s > 0.0 && s <= 100.0 => Some(s),
                s => return Err(err(format!("noise_scale={s} is outside (0, 100]"))),
            },
        };
        let epsilon = match get("epsilon") {
            None => None,
            Some(v) => match number("epsilon", v)? {
                // The reference crashes on epsilon = 0 (its plot references an undefined variable).
                0.0 => {
                    return Err(err("epsilon=0 removes nothing and crashes DSRL's reference; omit it"));
                }
                e if e.abs() > MAX_EPSILON => {
                    return Err(err(format!("epsilon={v} is outside [-1e9, 1e9]")));
                }
                e => Some(e),
            },
        };
        let inpaint = inpaint_range(get("inpaint"), get("discard"))?;
        if inpaint.is_some() && epsilon.is_some() {
            return Err(err(
                "epsilon with inpaint is not supported: DSRL indexes the inpainted trajectory list with positions \
                 from the full list, so the combination removes the wrong trajectories",
            ));
        }
        let grid = density_grid(&pairs, task)?;
        let target_cost = match get("target_cost") {
            Some(v) => number("target_cost", v)?,
            None => task.lowest_cost_threshold(),
        };
        if !(0.0..=MAX_TARGET_COST).contains(&target_cost) {
            return Err(err(format!(
                "target_cost={} is outside [0, {MAX_TARGET_COST}] (an episode's cost return is at most \
                 its number of steps)",
                get("target_cost").unwrap_or_default()
            )));
        }
        if outliers_percent.is_some() && target_cost < 1.0 {
            return Err(err(
                "outliers need target_cost >= 1: relabelled outliers get cost returns drawn from 0..int(target_cost)",
            ));
        }
        let seed = match get("seed") {
            Some(v) => integer("seed", v)?,
            None => 0,
        };
        Ok(Some(FilterSpec {
            grid,
            outliers_percent,
            inpaint,
            epsilon,
            noise_scale,
            target_cost,
            seed,
        }))
    }

    /// The canonical form: only what changes the output, in pipeline order, numbers as Python prints them.
    pub fn canonical(&self) -> String {
        let mut s = String::new();
        let mut add = |k: &str, v: String| {
            if !s.is_empty() {
                s.push(',');
            }
            let _ = write!(s, "{k}={v}");
        };
        if let Some(g) = &self.grid {
            add("cbins", g.cbins.to_string());
            add("rbins", g.rbins.to_string());
            add("max_npb", g.max_npb.to_string());
            add("min_npb", g.min_npb.to_string());
            add("seed", self.seed.to_string());
        }
        if let Some(p) = self.outliers_percent {
            add("outliers_percent", canonical_number(p));
        }
        if let Some(r) = &self.inpaint {
            let v = [r.pcmin, r.pcmax, r.prmin, r.prmax].map(canonical_number).join(":");
            add("inpaint", v);
        }
        if let Some(e) = self.epsilon {
            add("epsilon", canonical_number(e));
        }
        if self.outliers_percent.is_some() || self.epsilon.is_some() {
            add("target_cost", canonical_number(self.target_cost));
        }
        if let Some(n) = self.noise_scale {
            add("noise_scale", canonical_number(n));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dsrl_suite::catalog::Catalog;

    fn ant() -> Task {
        Catalog::embedded().unwrap().get("OfflineAntRun-v0").unwrap().clone()
    }

    #[test]
    fn every_preset_row_is_a_catalog_task_with_sane_numbers() {
        let catalog = Catalog::embedded().unwrap();
        let presets = density_presets();
        assert_eq!(presets.len(), 60);
        for ((task, density), grid) in presets {
            catalog.get(&task).unwrap();
            let d: f64 = density.parse().unwrap();
            assert!(d > 0.0 && d < 1.0);
            assert!(
                grid.cbins > 0 && grid.rbins > 0 && grid.max_npb > grid.min_npb,
                "{task} {density}"
            );
        }
    }

    #[test]
    fn the_papers_names_and_dsrls_names_mean_the_same() {
        let t = ant();
        let a = FilterSpec::parse("noise=0.05", &t).unwrap().unwrap();
        let b = FilterSpec::parse("outliers_percent=0.05,target_cost=10", &t)
            .unwrap()
            .unwrap();
        assert_eq!(a, b);
        assert_eq!(a.canonical(), "outliers_percent=0.05,target_cost=10");
        let c = FilterSpec::parse("obs_noise=0.1", &t).unwrap().unwrap();
        assert_eq!(c.canonical(), "noise_scale=0.1");
        // Density comes from the task's preset; the density number itself is not part of the computation.
        let d = FilterSpec::parse("density=0.5, seed=3", &t).unwrap().unwrap();
        assert_eq!(d.canonical(), "cbins=10,rbins=50,max_npb=6,min_npb=2,seed=3");
        let e = FilterSpec::parse("cbins=10,rbins=50,max_npb=6,min_npb=2,seed=3", &t)
            .unwrap()
            .unwrap();
        assert_eq!(d.canonical(), e.canonical());
        let f = FilterSpec::parse("discard=tempting", &t).unwrap().unwrap();
        assert_eq!(f.canonical(), "inpaint=0.5:1:0.5:1");
        assert_eq!(FilterSpec::parse("", &t).unwrap(), None);
        // The seed only matters with the density filter.
        let g = FilterSpec::parse("obs_noise=0.1,seed=9", &t).unwrap().unwrap();
        assert_eq!(g.canonical(), "noise_scale=0.1");
    }

    #[test]
    fn bad_requests_say_what_is_wrong_and_list_the_keys() {
        let t = ant();
        for (text, expected) in [
            ("noise=2", "outside (0, 1]"),
            ("colour=red", "unknown key \"colour\""),
            ("epsilon=0", "epsilon=0"),
            ("inpaint=0:0.5:0.5:1;0.5:1:0:1", "several inpaint ranges"),
            ("inpaint=0:0.5:0.5:1,epsilon=3", "epsilon with inpaint"),
            ("noise=0.1,target_cost=0.5", "target_cost >= 1"),
            ("density=0.3", "no density preset for 0.3; presets: 0.5, 0.75"),
            ("density=1", "outside (0, 1)"),
            ("cbins=0,rbins=5,max_npb=3,min_npb=1", "1..=1000"),
            ("inpaint=0.6:0.5:0:1", "pcmin <= pcmax"),
            ("discard=bold", "not a preset"),
            ("noise=0.1,outliers_percent=0.2", "given twice"),
            ("seed=-1,density=0.5", "non-negative integer"),
            ("obs_noise=nan", "not a finite number"),
            // Found by an outside probe: 1e19 saturated `int(target_cost)` and panicked in the generator.
            ("noise=0.05,target_cost=1e19", "target_cost=1e19 is outside [0, 100000]"),
            ("noise=0.05,target_cost=9.3e18", "outside [0, 100000]"),
            ("epsilon=1,target_cost=100001", "outside [0, 100000]"),
            ("target_cost=-1", "outside [0, 100000]"),
            ("epsilon=1e300", "epsilon=1e300 is outside"),
        ] {
            let e = FilterSpec::parse(text, &t).unwrap_err().to_string();
            assert!(e.contains(expected), "{text}: {e}");
            assert!(e.contains("valid keys:"), "{text}: {e}");
        }
    }
}
