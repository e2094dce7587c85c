//! The loud end of a run: what in a [`RunReport`] means the output is empty or badly thinned,
//! with the reason and the configuration key to change (`summary.json` → `warnings`, and a
//! block at the end of the one-screen summary).
//!
//! A warning is raised when
//!
//! - **an output is empty**: no pulse reached the outputs (`output.no_pulses`), the decompose
//!   stage found no return in any pulse that did (`output.no_returns`, as `returns.csv` or
//!   `returns.las` saw them), or nothing was deposited
//!   in the voxel store that was asked for (`voxels.nothing_deposited`);
//! - **one reason takes more than [`WARN_SHARE`]** of the pulses: a stage's drop reason
//!   (`deconvolve.bad_kernel`), a stage's note (pulses passed on partly unprocessed, e.g.
//!   `deconvolve.no_outgoing`), a georeference miss (`georeference.navigation_late`, a share of
//!   the pulses read), the input edge's `input_queue_full`, or a sink's skip counter
//!   (`voxels.pulses_no_geometry`, `las.pulses_without_geometry`, a share of the pulses out;
//!   return bins outside the voxel grid are not pulses and only explain an empty store: a
//!   recording window reaching below the ground puts many there harmlessly);
//! - **a limit bit at all**: `deconvolve.kernel_over_max_taps` (a kernel cut to `max_taps`)
//!   warns from its first pulse.
//!
//! Each known reason maps to the setting that governs it (`pipeline.stages[1].max_taps`:
//! stage indices count the `[[pipeline.stages]]` tables from 0) and a sentence saying what to
//! do; a reason the input alone causes (a damaged file, NaN samples) names no setting.

use serde::Serialize;

use super::RunReport;
use crate::config::RunConfig;
use crate::pipeline::runner::INPUT_QUEUE_FULL;
use crate::source::georeferencing::OnMissing;
use crate::stages::{Chain, StageKind};
use crate::voxel::voxelise::DepositStats;

/// Share of the pulses (or bins) above which one reason is a warning: 10 %.
pub const WARN_SHARE: f64 = 0.10;

/// One warning of a run (`summary.json` → `warnings[]`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RunWarning {
    /// What happened, a dotted code: a drop reason as in `dropped` (`deconvolve.bad_kernel`),
    /// a stage's note (`deconvolve.kernel_over_max_taps`), a georeference miss
    /// (`georeference.navigation_late`), a sink's counter (`voxels.pulses_no_geometry`), or an
    /// empty output (`output.no_pulses`, `output.no_returns`, `voxels.nothing_deposited`).
    pub reason: String,
    /// Pulses it concerns.
    pub count: u64,
    /// `count` as a share of the whole it belongs to (0 to 1): the pulses in for stage drops
    /// and notes, the pulses read for georeference misses, the pulses out for sinks' pulse
    /// counters; 1 for an empty output.
    pub share: f64,
    /// The configuration key to change (e.g. `pipeline.stages[1].max_taps`); `null` when the
    /// input itself is at fault.
    pub setting: Option<String>,
    /// What happened and what to do, one or two sentences.
    pub message: String,
}

impl RunWarning {
    fn new(reason: impl Into<String>, count: u64, whole: u64, rule: Rule) -> Self {
        RunWarning {
            reason: reason.into(),
            count,
            share: share(count, whole),
            setting: rule.setting,
            message: rule.advice,
        }
    }
}

fn share(count: u64, whole: u64) -> f64 {
    if whole == 0 {
        0.0
    } else {
        count as f64 / whole as f64
    }
}

/// The setting and the advice for one reason.
struct Rule {
    setting: Option<String>,
    advice: String,
}

fn rule(setting: Option<String>, advice: impl Into<String>) -> Rule {
    Rule {
        setting,
        advice: advice.into(),
    }
}

/// Every warning of a run: empty outputs first, then by share (largest first). `chain` is the
/// run's stage chain (its stages say what their drop reasons and notes mean).
pub fn run_warnings(report: &RunReport, chain: &Chain, config: &RunConfig) -> Vec<RunWarning> {
    let mut shares = Vec::new();
    stage_warnings(report, chain, &mut shares);
    input_edge_warning(report, &mut shares);
    georeference_warnings(report, config, &mut shares);
    sink_warnings(report, &mut shares);
    shares.sort_by(|a, b| b.share.total_cmp(&a.share));
    let mut out = empty_output_warnings(report, chain, config, &shares);
    out.extend(shares);
    out
}

/// `pipeline.stages[i].key`.
fn stage_key(i: usize, key: &str) -> Option<String> {
    Some(format!("pipeline.stages[{i}].{key}"))
}

/// The chain's stage behind `stages[i]` of the report, when it is the same kind.
fn stage_of<'c>(chain: &'c Chain, i: usize, name: &str) -> Option<&'c dyn StageKind> {
    chain.stage(i).filter(|s| s.kind() == name)
}

/// Drops and notes of each stage above the share, and any the stage warns about from the
/// first (a limit that bit, e.g. a kernel cut to `max_taps`).
fn stage_warnings(report: &RunReport, chain: &Chain, out: &mut Vec<RunWarning>) {
    for (i, st) in report.stages.iter().enumerate() {
        let kind = stage_of(chain, i, &st.name);
        let always = |reason: &str| kind.is_some_and(|k| k.always_warns(reason));
        for (reason, &n) in &st.dropped {
            if (n > 0 && always(reason)) || share(n, report.pulses_in) > WARN_SHARE {
                let rule = drop_rule(kind, &st.name, reason, i);
                out.push(RunWarning::new(
                    format!("{}.{reason}", st.name),
                    n,
                    report.pulses_in,
                    rule,
                ));
            }
        }
        for (note, &n) in &st.notes {
            if (n > 0 && always(note)) || share(n, report.pulses_in) > WARN_SHARE {
                out.push(RunWarning::new(
                    format!("{}.{note}", st.name),
                    n,
                    report.pulses_in,
                    note_rule(kind, &st.name, note, i),
                ));
            }
        }
    }
}

/// The setting and advice for a stage's drop reason: the stage's own, else the rules every
/// stage shares.
fn drop_rule(kind: Option<&dyn StageKind>, stage: &str, reason: &str, i: usize) -> Rule {
    let at = format!("pipeline.stages[{i}]");
    if let Some(a) = kind.and_then(|k| k.drop_advice(reason, &at)) {
        return rule(a.setting, a.text);
    }
    match reason {
        "segment_too_long" => rule(
            stage_key(i, "max_samples"),
            format!(
                "{stage} dropped pulses with a segment longer than its max_samples; raise max_samples \
                 (buffers and the worst-case cost grow with it)"
            ),
        ),
        "not_denoised" => rule(
            Some("pipeline.stages".into()),
            format!("{stage} needs a denoise stage before it; add one in front"),
        ),
        "non_finite_input" => rule(None, "the input holds NaN or infinite samples"),
        "segment_out_of_bounds" | "bad_digitizer_parameters" | "length_mismatch" => rule(
            None,
            "the input's pulses are inconsistent (segments past their samples, or a bad sample \
             interval); the file is damaged",
        ),
        _ => rule(
            stage_key(i, "type"),
            format!("the {stage} stage dropped them; see its documentation (docs/signal.md)"),
        ),
    }
}

/// The setting and advice for a stage's note (pulses passed on partly unprocessed).
fn note_rule(kind: Option<&dyn StageKind>, stage: &str, note: &str, i: usize) -> Rule {
    let at = format!("pipeline.stages[{i}]");
    match kind.and_then(|k| k.note_advice(note, &at)) {
        Some(a) => rule(a.setting, a.text),
        None => rule(
            stage_key(i, "type"),
            format!("passed on partly unprocessed by the {stage} stage"),
        ),
    }
}

fn input_edge_warning(report: &RunReport, out: &mut Vec<RunWarning>) {
    let n = report.dropped.get(INPUT_QUEUE_FULL).copied().unwrap_or(0);
    let whole = report.pulses_in + n;
    if share(n, whole) > WARN_SHARE {
        out.push(RunWarning::new(
            INPUT_QUEUE_FULL,
            n,
            whole,
            rule(
                Some("pipeline.input_edge".into()),
                "the workers could not keep up and the input edge dropped the newest pulses; \
                 input_edge = \"block\" loses none on replay, or raise pipeline.workers / lower \
                 the stages' cost",
            ),
        ));
    }
}

/// Pulses the georeferencing dropped, by reason, and the pulses it read.
fn georeference_misses(report: &RunReport, config: &RunConfig) -> (Vec<(String, u64)>, u64) {
    let missed: Vec<(String, u64)> = report
        .source
        .georeference()
        .map(|g| g.missed.into_iter().collect())
        .unwrap_or_default();
    let dropped: u64 = if config.georeference.on_missing == OnMissing::Drop {
        missed.iter().map(|(_, n)| n).sum()
    } else {
        0
    };
    (missed, report.pulses_in + dropped)
}

fn georeference_warnings(report: &RunReport, config: &RunConfig, out: &mut Vec<RunWarning>) {
    let (missed, read) = georeference_misses(report, config);
    for (reason, n) in missed {
        if share(n, read) <= WARN_SHARE {
            continue;
        }
        let r = match reason.as_str() {
            "navigation_late" => rule(
                Some("georeference.max_wait_s".into()),
                "pulses waited longer than max_wait_s (or max_pending pulses) for navigation; \
                 raise georeference.max_wait_s / max_pending",
            ),
            "navigation_gap" => rule(
                Some("georeference.max_gap_s".into()),
                "the navigation has gaps longer than max_gap_s at these pulses' times; raise \
                 georeference.max_gap_s to interpolate across them",
            ),
            "before_navigation" | "no_navigation_after" => rule(
                Some("georeference.pulse_time_offset_s".into()),
                "these pulses' times lie outside the navigation's time span; check the \
                 digitizer clock offset (pulse_time_offset_s) and the navigation recorded with \
                 the capture, or set on_missing = \"pass\"",
            ),
            "no_output_crs" => rule(
                Some("georeference.output_epsg".into()),
                "no output CRS could be decided; name one with output_epsg",
            ),
            _ => rule(
                Some("georeference.on_missing".into()),
                "the trajectory could not place these pulses",
            ),
        };
        out.push(RunWarning::new(
            format!("georeference.{reason}"),
            n,
            read,
            r,
        ));
    }
}

/// The voxel sink's bins counters: `(counter, setting, advice)`.
type BinsCounter = fn(&DepositStats) -> u64;

const VOXEL_BINS: [(BinsCounter, &str, &str); 3] = [
    (
        |d| d.bins_outside_heights,
        "voxels.z_range_m",
        "return bins fell outside the voxel grid's height range; widen voxels.z_range_m (or \
         height = \"above_dem\" with a DEM)",
    ),
    (
        |d| d.bins_outside_extent,
        "voxels.extent_m",
        "return bins fell outside the voxel store's horizontal extent; set voxels.extent_m to \
         the survey area (or raise auto_extent_m)",
    ),
    (
        |d| d.bins_outside_dem,
        "georeference.dem",
        "return bins fell where the DEM has no height; use a DEM covering the survey",
    ),
];

fn sink_warnings(report: &RunReport, out: &mut Vec<RunWarning>) {
    let no_geometry = || {
        rule(
            Some("georeference.enabled".into()),
            "pulses reached the sink without geometry (not georeferenced); enable \
             [georeference] (navigation recorded with the capture) or use an input that \
             carries its geometry",
        )
    };
    if let Some(v) = report.sinks.voxels() {
        let n = v.deposits.pulses_no_geometry;
        if share(n, report.pulses_out) > WARN_SHARE {
            out.push(RunWarning::new(
                "voxels.pulses_no_geometry",
                n,
                report.pulses_out,
                no_geometry(),
            ));
        }
    }
    if let Some(las) = report.sinks.las() {
        let n = las.pulses_without_geometry;
        if share(n, report.pulses_out) > WARN_SHARE {
            out.push(RunWarning::new(
                "las.pulses_without_geometry",
                n,
                report.pulses_out,
                no_geometry(),
            ));
        }
    }
}

/// No pulse out, no return found, nothing deposited: each names the largest cause found in
/// `causes` (the share warnings) when there is one.
fn empty_output_warnings(
    report: &RunReport,
    chain: &Chain,
    config: &RunConfig,
    causes: &[RunWarning],
) -> Vec<RunWarning> {
    let mut out = Vec::new();
    let main = causes.first();
    let because = |main: Option<&RunWarning>| match main {
        Some(w) => (
            w.setting.clone(),
            format!(
                "; the largest cause: {} ({} pulses, {:.0} %; its warning says what to do)",
                w.reason,
                w.count,
                100.0 * w.share
            ),
        ),
        None => (None, String::new()),
    };
    let (_, read) = georeference_misses(report, config);
    if report.pulses_out == 0 {
        let (setting, cause) = because(main);
        let message = if read == 0 {
            "the input held no pulses (check it with `fwlidar inspect FILE`)".to_string()
        } else {
            format!("none of the {read} pulses read reached the outputs{cause}")
        };
        out.push(RunWarning {
            reason: "output.no_pulses".into(),
            count: read,
            share: if read == 0 { 0.0 } else { 1.0 },
            setting,
            message,
        });
    }
    // The stage that finds the returns, and whether it found any, as the returns' outputs saw
    // it (`None` without one).
    let finder = (0..report.stages.len())
        .filter_map(|i| Some((i, chain.stage(i)?)))
        .find(|(_, s)| s.products().returns);
    let any_return = match (report.sinks.returns_csv(), report.sinks.las()) {
        (Some(csv), _) => Some(csv.rows > 0),
        (None, Some(las)) => Some(las.pulses_without_returns < report.pulses_out),
        (None, None) => None,
    };
    if let (Some((i, stage)), Some(false)) = (finder, any_return)
        && report.pulses_out > 0
        && let Some(advice) = stage.no_returns_advice(&format!("pipeline.stages[{i}]"))
    {
        out.push(RunWarning {
            reason: "output.no_returns".into(),
            count: report.pulses_out,
            share: 1.0,
            setting: advice.setting,
            message: format!(
                "the {} stage found no return in any of the {} pulses out{}",
                stage.kind(),
                report.pulses_out,
                advice.text
            ),
        });
    }
    if let Some(v) = report.sinks.voxels()
        && config.voxels.enabled
        && v.deposits.bins_deposited + v.deposits.bins_resumed == 0
    {
        let d = &v.deposits;
        let (setting, message) = if report.pulses_out == 0 {
            let (setting, cause) = because(main);
            (setting, format!("no pulse reached the voxel store{cause}"))
        } else if d.pulses_no_geometry + d.pulses_non_finite >= report.pulses_out {
            (
                Some("georeference.enabled".to_string()),
                "no pulse had geometry to place its bins (not georeferenced); enable \
                 [georeference] or use an input that carries its geometry"
                    .to_string(),
            )
        } else {
            match VOXEL_BINS
                .iter()
                .max_by_key(|(k, _, _)| k(d))
                .filter(|(k, _, _)| k(d) > 0)
            {
                Some((_, setting, advice)) => (Some(setting.to_string()), advice.to_string()),
                None => (
                    Some("pipeline.stages".to_string()),
                    "the pulses out had no processed return bins to deposit".to_string(),
                ),
            }
        };
        out.push(RunWarning {
            reason: "voxels.nothing_deposited".into(),
            count: read,
            share: 1.0,
            setting,
            message: format!("nothing was deposited in voxels.zarr: {message}"),
        });
    }
    out
}

/// The warnings as a block for the end of the one-screen summary (empty when there are none).
pub fn warnings_block(warnings: &[RunWarning]) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    if warnings.is_empty() {
        return s;
    }
    let _ = writeln!(
        s,
        "  !! WARNING: {} problem{} in this run (summary.json → warnings):",
        warnings.len(),
        if warnings.len() == 1 { "" } else { "s" }
    );
    for w in warnings {
        let _ = writeln!(
            s,
            "  !! {}: {} pulses ({:.1} %): {}",
            w.reason,
            w.count,
            100.0 * w.share,
            w.message
        );
        if let Some(k) = &w.setting {
            let _ = writeln!(s, "  !!    setting to change: {k}");
        }
    }
    s
}

/// Logs each warning at warn level (stderr).
pub fn log_warnings(warnings: &[RunWarning]) {
    for w in warnings {
        tracing::warn!(
            reason = %w.reason,
            count = w.count,
            share = w.share,
            setting = w.setting.as_deref().unwrap_or("-"),
            "{}",
            w.message
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::telemetry::StageReport;
    use std::collections::BTreeMap;

    fn stage(name: &str, dropped: &[(&str, u64)], notes: &[(&str, u64)]) -> StageReport {
        let map = |v: &[(&str, u64)]| -> BTreeMap<String, u64> {
            v.iter().map(|(k, n)| (k.to_string(), *n)).collect()
        };
        StageReport {
            name: name.into(),
            received: 0,
            sent: 0,
            dropped: map(dropped),
            errors: 0,
            notes: map(notes),
            service: Default::default(),
            since_arrival: Default::default(),
        }
    }

    fn report(pulses_in: u64, pulses_out: u64, stages: Vec<StageReport>) -> RunReport {
        let mut dropped = BTreeMap::new();
        for s in &stages {
            for (r, n) in &s.dropped {
                dropped.insert(format!("{}.{r}", s.name), *n);
            }
        }
        RunReport {
            fwlidar_version: String::new(),
            workers: 1,
            pulses_in,
            pulses_out,
            dropped_total: dropped.values().sum(),
            dropped,
            errors: 0,
            stages,
            end_to_end: Default::default(),
            source: Default::default(),
            nav: Default::default(),
            sinks: Default::default(),
            pool_allocations: 0,
            stopped_early: false,
            fatal: None,
            wall_time_s: 0.0,
            pulses_per_s: 0.0,
        }
    }

    use crate::sink::returns_csv::ReturnsCsvReport;
    use crate::sink::voxel_tiles::VoxelReport;
    use crate::sink::{SinkReport, SinkReports};

    /// Sinks' reports: `returns.csv` with `rows` (when given) and the voxel store's deposits.
    fn sinks(rows: Option<u64>, deposits: DepositStats) -> SinkReports {
        let mut v = Vec::new();
        if let Some(rows) = rows {
            v.push((
                "returns_csv",
                SinkReport::ReturnsCsv(ReturnsCsvReport {
                    rows,
                    returns_outside_dem: None,
                }),
            ));
        }
        v.push((
            "voxels",
            SinkReport::Voxels(Box::new(VoxelReport {
                deposits,
                ..Default::default()
            })),
        ));
        SinkReports(v)
    }

    /// `returns.las` alone, with `pulses_without_returns`.
    fn las_only(pulses_without_returns: u64) -> SinkReports {
        SinkReports(vec![(
            "las",
            SinkReport::Las(crate::sink::las_wave::LasWaveReport {
                pulses_without_returns,
                ..Default::default()
            }),
        )])
    }

    fn replay_config() -> RunConfig {
        crate::config::load_run_config(None).unwrap()
    }

    /// A chain of the stages a test report names, each with its defaults (a deconvolve stage
    /// takes its kernel from the outgoing pulse).
    fn chain_of(r: &RunReport) -> Chain {
        let defaults = crate::stages::StageConfig::defaults();
        let stages: Vec<crate::stages::StageConfig> = r
            .stages
            .iter()
            .map(|s| {
                defaults
                    .iter()
                    .find(|d| d.kind() == s.name)
                    .cloned()
                    .unwrap()
            })
            .collect();
        let facts = crate::core::facts::SourceFacts::default();
        Chain::prepare(
            &stages,
            &crate::stages::RunContext {
                facts: &facts,
                dem: None,
                writes_returns: true,
                learned_response: None,
            },
        )
        .unwrap()
    }

    fn warnings_of(r: &RunReport, cfg: &RunConfig) -> Vec<RunWarning> {
        run_warnings(r, &chain_of(r), cfg)
    }

    #[test]
    fn every_pulse_dropped_names_the_reason_and_the_setting() {
        let r = report(
            1000,
            0,
            vec![
                stage("denoise", &[], &[]),
                stage("deconvolve", &[("kernel_over_max_taps", 1000)], &[]),
                stage("decompose", &[], &[]),
            ],
        );
        let w = warnings_of(&r, &replay_config());
        let reasons: Vec<&str> = w.iter().map(|w| w.reason.as_str()).collect();
        assert_eq!(
            reasons,
            ["output.no_pulses", "deconvolve.kernel_over_max_taps"],
            "{w:#?}"
        );
        assert_eq!(w[0].setting.as_deref(), Some("pipeline.stages[1].max_taps"));
        assert!(
            w[0].message.contains("kernel_over_max_taps"),
            "{}",
            w[0].message
        );
        assert_eq!((w[1].count, w[1].share), (1000, 1.0));
        assert_eq!(w[1].setting.as_deref(), Some("pipeline.stages[1].max_taps"));
        let block = warnings_block(&w);
        assert!(block.contains("WARNING: 2 problems"), "{block}");
        assert!(block.contains("pipeline.stages[1].max_taps"), "{block}");
    }

    #[test]
    fn shares_at_or_below_the_threshold_are_quiet_except_a_limit_that_bit() {
        let quiet = report(
            1000,
            900,
            vec![stage(
                "deconvolve",
                &[("bad_kernel", 100)],
                &[("no_outgoing", 50)],
            )],
        );
        assert!(warnings_of(&quiet, &replay_config()).is_empty());
        let loud = report(
            1000,
            899,
            vec![stage(
                "deconvolve",
                &[("bad_kernel", 101)],
                &[("no_outgoing", 50)],
            )],
        );
        let w = warnings_of(&loud, &replay_config());
        assert_eq!(w.len(), 1, "{w:#?}");
        assert_eq!(w[0].reason, "deconvolve.bad_kernel");
        assert_eq!(w[0].setting.as_deref(), Some("pipeline.stages[0].kernel"));
        let cut = report(
            1000,
            1000,
            vec![stage("deconvolve", &[], &[("kernel_over_max_taps", 1)])],
        );
        let w = warnings_of(&cut, &replay_config());
        assert_eq!(w.len(), 1, "{w:#?}");
        assert_eq!(w[0].reason, "deconvolve.kernel_over_max_taps");
        assert_eq!(w[0].count, 1);
    }

    #[test]
    fn empty_inputs_outputs_and_voxel_stores_say_why() {
        let cfg = replay_config();
        let w = warnings_of(&report(0, 0, vec![]), &cfg);
        assert_eq!(w.len(), 1);
        assert_eq!(w[0].reason, "output.no_pulses");
        assert!(w[0].message.contains("held no pulses"), "{}", w[0].message);

        let mut r = report(10, 10, vec![stage("decompose", &[], &[])]);
        r.sinks = sinks(
            Some(0),
            DepositStats {
                pulses_no_geometry: 10,
                ..Default::default()
            },
        );
        let w = warnings_of(&r, &cfg);
        let by = |reason: &str| w.iter().find(|w| w.reason == reason).cloned();
        let no_returns = by("output.no_returns").expect("no returns");
        let mut las_only = r.clone();
        las_only.sinks = self::las_only(10);
        let w2 = warnings_of(&las_only, &cfg);
        assert_eq!(w2[0].reason, "output.no_returns", "{w2:#?}");
        las_only.sinks = self::las_only(9);
        assert!(warnings_of(&las_only, &cfg).is_empty());
        assert_eq!(
            no_returns.setting.as_deref(),
            Some("pipeline.stages[0].min_snr")
        );
        let voxels = by("voxels.nothing_deposited").expect("nothing deposited");
        assert_eq!(voxels.setting.as_deref(), Some("georeference.enabled"));
        let no_geo = by("voxels.pulses_no_geometry").expect("no geometry");
        assert_eq!(no_geo.share, 1.0);

        // Bins above the grid: the height range is the setting; a resumed store is not empty.
        r.sinks = sinks(
            Some(30),
            DepositStats {
                bins_outside_heights: 400,
                ..Default::default()
            },
        );
        let w = warnings_of(&r, &cfg);
        assert_eq!(w[0].reason, "voxels.nothing_deposited");
        assert_eq!(w[0].setting.as_deref(), Some("voxels.z_range_m"));
        assert_eq!(w.len(), 1, "{w:#?}");
        // Bins outside the grid beside deposits are no warning (a window below the ground).
        r.sinks = sinks(
            Some(30),
            DepositStats {
                bins_deposited: 10,
                bins_outside_heights: 400,
                ..Default::default()
            },
        );
        assert!(warnings_of(&r, &cfg).is_empty());
        r.sinks = sinks(
            Some(30),
            DepositStats {
                bins_resumed: 400,
                ..Default::default()
            },
        );
        assert!(warnings_of(&r, &cfg).is_empty());
    }

    #[test]
    fn georeference_misses_are_a_share_of_the_pulses_read() {
        let mut r = report(600, 600, vec![]);
        r.source.georeference = Some(crate::source::report::GeoreferenceReport {
            missed: [
                ("navigation_gap".into(), 400),
                ("before_navigation".into(), 10),
            ]
            .into(),
            ..Default::default()
        });
        let w = warnings_of(&r, &replay_config());
        assert_eq!(w.len(), 1, "{w:#?}");
        assert_eq!(w[0].reason, "georeference.navigation_gap");
        // 600 pulses in and 410 dropped by the georeferencing (on_missing = "drop") were read.
        assert_eq!(w[0].share, 400.0 / 1010.0);
        assert_eq!(w[0].setting.as_deref(), Some("georeference.max_gap_s"));
    }
}
