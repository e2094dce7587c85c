//! The system response learned from a replay's own input before the run starts
//! ([`crate::signal::learned_response`]): the first [`LEARN_PULSES`] pulses of the first input
//! file are read once, the response is learned and frozen, and the `decompose` stage finds
//! echoes against it. The summary says so ([`ResponseReport`]).

use std::path::Path;
use std::sync::Arc;

use serde::Serialize;

use super::RunError;
use crate::pipeline::ports::SourceEvent;
use crate::pulse::PulsePool;
use crate::signal::learned_response::{ResponseFile, ResponseLearner};
use crate::stages::Chain;

/// Pulses read from the start of the input to learn the response.
pub const LEARN_PULSES: u64 = 20_000;

/// Reads the first `max_pulses` pulses of `path` and learns the response of each channel.
/// `Ok(Err(why))` when the file holds too few clean single echoes (the run goes on without
/// one); `Err` when the file cannot be read.
pub fn learn_from_file(
    path: &Path,
    max_pulses: u64,
) -> Result<Result<ResponseFile, String>, RunError> {
    let mut learner = ResponseLearner::new();
    read_into(&mut learner, path, max_pulses)?;
    let from = format!(
        "learned from the first {} pulses of {}",
        learner.pulses(),
        path.display()
    );
    Ok(learner.finish(&from).map_err(|e| e.to_string()))
}

/// Feeds the pulses of `path` to `learner` until it has seen `max_pulses` in all (the file's
/// own reader, no georeferencing); errors name the file.
pub fn read_into(
    learner: &mut ResponseLearner,
    path: &Path,
    max_pulses: u64,
) -> Result<(), RunError> {
    let mut source = crate::source::open_file(path).map_err(RunError::job)?;
    let pool = PulsePool::new(4);
    while learner.pulses() < max_pulses {
        match source
            .next(&pool)
            .map_err(|e| RunError::job(format!("{}: {e}", path.display())))?
        {
            SourceEvent::End => break,
            SourceEvent::Idle | SourceEvent::Nav(_) => {}
            SourceEvent::Pulse(p) => {
                learner.add_pulse(&p);
                pool.give(p);
            }
        }
    }
    Ok(())
}

/// The response a run used, for `summary.json` (`response`) and the printed summary.
#[derive(Clone, Debug, Serialize)]
pub struct ResponseReport {
    /// Where it came from (`learned from the first N pulses of FILE`, or the file named).
    pub source: String,
    /// Echo model the `decompose` stage used: `response` or `gaussian`.
    pub model: &'static str,
    /// Why none could be learned, when none was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub not_learned: Option<String>,
    /// Per channel: echoes averaged, FWHM (ns), whether Gaussian, whether the shape changes
    /// with amplitude.
    pub channels: Vec<ChannelReport>,
}

/// One channel of a [`ResponseReport`].
#[derive(Clone, Debug, Serialize)]
pub struct ChannelReport {
    /// Digitizer channel.
    pub channel: u16,
    /// Echoes averaged.
    pub echoes: usize,
    /// Full width at half maximum, ns.
    pub fwhm_ns: f64,
    /// Extent of the shape after its peak, ns (its tail).
    pub tail_ns: f64,
    /// Whether it is Gaussian.
    pub gaussian: bool,
    /// Whether its shape changes with amplitude (absent when the amplitudes span too narrow a
    /// range to tell).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub changes_with_amplitude: Option<bool>,
}

/// The response of `chain`'s `decompose` stage after it was prepared, or `None` when the
/// chain fits Gaussians without having asked for a response; `not_learned` says why a
/// requested one is missing.
pub fn response_report(chain: &Chain, not_learned: Option<&str>) -> Option<ResponseReport> {
    use crate::stages::StageConfig;
    use crate::stages::decompose::EchoModel;
    let d = chain.stages().iter().find_map(|s| match s {
        StageConfig::Decompose(d) => Some(d),
        _ => None,
    })?;
    if d.learned.is_none() && not_learned.is_none() && d.response.is_none() {
        return None;
    }
    let file: Option<&Arc<ResponseFile>> = d.learned.as_ref();
    let source = match (&d.response, file) {
        (Some(p), _) => format!("file {}", p.display()),
        (None, Some(f)) => f.learned_from.clone(),
        (None, None) => "none".into(),
    };
    Some(ResponseReport {
        source,
        model: if d.model == EchoModel::Response {
            "response"
        } else {
            "gaussian"
        },
        not_learned: not_learned.map(str::to_string),
        channels: file
            .map(|f| {
                f.responses
                    .iter()
                    .map(|r| ChannelReport {
                        channel: r.channel,
                        echoes: r.echoes,
                        fwhm_ns: f64::from(r.fwhm_samples) * r.sample_ns,
                        tail_ns: f64::from(r.end_samples()) * r.sample_ns,
                        gaussian: r.is_gaussian(),
                        changes_with_amplitude: r.changes_with_amplitude(),
                    })
                    .collect()
            })
            .unwrap_or_default(),
    })
}

impl ResponseReport {
    /// The printed summary's lines (each within 100 columns): where the response came from
    /// and what the decomposition does with it, then one line per channel.
    pub fn lines(&self) -> Vec<String> {
        if self.not_learned.is_some() {
            return vec![
                "response: none could be learned (too few clean single echoes; summary.json \
                 says why): Gaussian echoes"
                    .into(),
            ];
        }
        // "learned from the first N pulses of PATH": the input is named above already.
        let source = match self.source.split_once(" of ") {
            Some((head, _)) if self.source.starts_with("learned") => head,
            _ => self.source.as_str(),
        };
        let mut out = vec![format!(
            "response: {source}, frozen; {}",
            if self.model == "response" {
                "echoes are found against it"
            } else {
                "it is Gaussian: Gaussians are fitted"
            }
        )];
        for c in &self.channels {
            out.push(format!(
                "    channel {}: FWHM {:.1} ns, tail to +{:.0} ns, from {} echoes",
                c.channel, c.fwhm_ns, c.tail_ns, c.echoes
            ));
        }
        out
    }
}
