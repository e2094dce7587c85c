//! Several inputs replayed one after another as one stream (`fwlidar replay A B C`): the flight
//! lines of a campaign into one output folder and one voxel store, as if they had been one
//! recording. Each input keeps its own georeferencing (its own trajectory) underneath; the
//! runner numbers the pulses on across the inputs, so the voxel store's per-tile watermarks
//! stay in order.

use crate::core::facts::SourceFacts;
use crate::pipeline::ports::{Source, SourceError, SourceEvent};
use crate::pulse::PulsePool;
use crate::source::DynSource;
use crate::source::report::{InputReport, SourceReport};

/// The inputs in order, each already opened (and georeferenced).
pub struct ChainSource {
    /// Input file names (for the report), in order.
    names: Vec<String>,
    /// The sources, in order.
    inputs: Vec<Box<DynSource>>,
    /// The one being read.
    current: usize,
}

impl ChainSource {
    /// Chains `inputs` (with their file names). They must state the same sensor, time base and
    /// CRS, so that one set of outputs describes them all; the error names the two files that
    /// differ and the fact.
    pub fn new(inputs: Vec<(String, Box<DynSource>)>) -> Result<Self, String> {
        if inputs.is_empty() {
            return Err("no input to replay".into());
        }
        let first = inputs[0].1.facts();
        for (name, s) in inputs.iter().skip(1) {
            let f = s.facts();
            let differ = |what: &str| {
                format!(
                    "{} and {name} cannot be replayed into one output: their {what} differ",
                    inputs[0].0
                )
            };
            if f.sensor != first.sensor {
                return Err(differ("sensor descriptions"));
            }
            if f.time_base != first.time_base {
                return Err(differ("time bases"));
            }
            if f.crs != first.crs {
                return Err(differ("coordinate reference systems"));
            }
            if f.t0_is_emission != first.t0_is_emission {
                return Err(differ("pulse time origins (t0)"));
            }
        }
        let (names, inputs) = inputs.into_iter().unzip();
        Ok(ChainSource {
            names,
            inputs,
            current: 0,
        })
    }
}

impl Source for ChainSource {
    type Report = SourceReport;

    fn name(&self) -> &'static str {
        "inputs in sequence"
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        while let Some(s) = self.inputs.get_mut(self.current) {
            match s.next(pool)? {
                SourceEvent::End => self.current += 1,
                e => return Ok(e),
            }
        }
        Ok(SourceEvent::End)
    }

    fn progress(&self) -> Option<(u64, u64)> {
        let mut sum = (0u64, 0u64);
        for s in &self.inputs {
            let (d, t) = s.progress()?;
            sum = (sum.0 + d, sum.1 + t);
        }
        Some(sum)
    }

    /// Every input's whole report, in order (`summary.json` shows them under `inputs`, and
    /// their counts added up at the top: [`sequence_json`]).
    fn report(&self) -> SourceReport {
        SourceReport::of(InputReport::Sequence(
            self.names
                .iter()
                .cloned()
                .zip(self.inputs.iter().map(|s| s.report()))
                .collect(),
        ))
    }

    fn facts(&self) -> SourceFacts {
        self.inputs[0].facts()
    }

    fn held_pulses(&self) -> usize {
        self.inputs
            .iter()
            .map(|s| s.held_pulses())
            .max()
            .unwrap_or(0)
    }
}

/// A sequence's report as `summary.json` holds it: every input's report under `inputs`
/// (`{"input": file, "report": …}`), and their counts summed at the top (largest values,
/// `largest_*` and `max_*`, are the largest; a text is kept where the inputs agree).
pub fn sequence_json(inputs: &[(String, SourceReport)]) -> serde_json::Value {
    let reports: Vec<serde_json::Value> = inputs.iter().map(|(_, r)| r.to_json()).collect();
    let mut top = match reports.first() {
        Some(first) => reports
            .iter()
            .skip(1)
            .fold(first.clone(), |acc, r| combine("", &acc, r))
            .as_object()
            .cloned()
            .unwrap_or_default(),
        None => serde_json::Map::new(),
    };
    top.insert(
        "inputs".into(),
        serde_json::Value::Array(
            inputs
                .iter()
                .zip(reports)
                .map(|((n, _), r)| serde_json::json!({"input": n, "report": r}))
                .collect(),
        ),
    );
    serde_json::Value::Object(top)
}

/// Two inputs' reports as one: numbers added (the larger for `largest_*`/`max_*` keys), objects
/// combined key by key, anything else kept where equal and dropped where not (`Null`).
fn combine(key: &str, a: &serde_json::Value, b: &serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut out = serde_json::Map::new();
            for (k, v) in x {
                let c = match y.get(k) {
                    Some(w) => combine(k, v, w),
                    None => v.clone(),
                };
                if !c.is_null() {
                    out.insert(k.clone(), c);
                }
            }
            for (k, w) in y {
                if !x.contains_key(k) {
                    out.insert(k.clone(), w.clone());
                }
            }
            Value::Object(out)
        }
        (Value::Number(x), Value::Number(y)) => {
            let largest = key.starts_with("largest") || key.starts_with("max");
            match (x.as_u64(), y.as_u64()) {
                (Some(p), Some(q)) => Value::from(if largest { p.max(q) } else { p + q }),
                _ => {
                    let (p, q) = (x.as_f64().unwrap_or(0.0), y.as_f64().unwrap_or(0.0));
                    serde_json::Number::from_f64(if largest { p.max(q) } else { p + q })
                        .map_or(Value::Null, Value::Number)
                }
            }
        }
        _ if a == b => a.clone(),
        _ => Value::Null,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::Pulse;

    /// Pulses `0..n` with `gps_time` = first + k, a nav chunk after each.
    struct Fake {
        first: f64,
        n: usize,
        k: usize,
        nav_next: bool,
        facts: SourceFacts,
    }

    impl Source for Fake {
        type Report = SourceReport;

        fn name(&self) -> &'static str {
            "fake"
        }
        fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
            if self.nav_next {
                self.nav_next = false;
                return Ok(SourceEvent::Nav(crate::pipeline::ports::NavChunk {
                    port: 0,
                    receive_time_ns: 0,
                    bytes: vec![self.k as u8],
                }));
            }
            if self.k == self.n {
                return Ok(SourceEvent::End);
            }
            let mut p: Box<Pulse> = pool.take();
            p.gps_time = self.first + self.k as f64;
            self.k += 1;
            self.nav_next = true;
            Ok(SourceEvent::Pulse(p))
        }
        fn progress(&self) -> Option<(u64, u64)> {
            Some((self.k as u64, self.n as u64))
        }
        fn report(&self) -> SourceReport {
            SourceReport {
                georeference: Some(crate::source::report::GeoreferenceReport {
                    largest_wait_pulses: self.n as u64,
                    ..Default::default()
                }),
                ..SourceReport::of(InputReport::Capture(
                    crate::source::capture::CaptureReport {
                        file: format!("f{}", self.first),
                        version: "1.0".into(),
                        records: crate::source::capture::CaptureStats {
                            frames: self.k as u64,
                            ..Default::default()
                        },
                        ..Default::default()
                    },
                ))
            }
        }
        fn facts(&self) -> SourceFacts {
            self.facts.clone()
        }
    }

    fn fake(first: f64, n: usize) -> Box<DynSource> {
        Box::new(Fake {
            first,
            n,
            k: 0,
            nav_next: false,
            facts: SourceFacts::default(),
        })
    }

    #[test]
    fn inputs_come_in_order_and_reports_add_up() {
        let mut c = ChainSource::new(vec![
            ("a".into(), fake(100.0, 3)),
            ("b".into(), fake(0.0, 2)),
        ])
        .unwrap();
        let pool = PulsePool::new(4);
        let (mut times, mut navs) = (Vec::new(), 0);
        loop {
            match c.next(&pool).unwrap() {
                SourceEvent::Pulse(p) => times.push(p.gps_time),
                SourceEvent::Nav(_) => navs += 1,
                SourceEvent::End => break,
                SourceEvent::Idle => {}
            }
        }
        assert_eq!(times, vec![100.0, 101.0, 102.0, 0.0, 1.0]);
        assert_eq!(navs, 5);
        assert_eq!(c.progress(), Some((5, 5)));
        let report = c.report();
        assert_eq!(report.georeference().unwrap().largest_wait_pulses, 3);
        let r = report.to_json();
        assert_eq!(r["records"]["frames"], 5);
        assert_eq!(r["georeference"]["largest_wait_pulses"], 3);
        assert_eq!(r["version"], "1.0");
        assert!(r.get("file").is_none(), "differing texts are dropped: {r}");
        assert_eq!(r["inputs"][1]["input"], "b");
        assert_eq!(r["inputs"][1]["report"]["file"], "f0");
    }

    #[test]
    fn inputs_of_different_sensors_are_refused_by_name() {
        let other = Box::new(Fake {
            first: 0.0,
            n: 1,
            k: 0,
            nav_next: false,
            facts: SourceFacts {
                crs: Some("EPSG:32633".into()),
                ..SourceFacts::default()
            },
        });
        let e = ChainSource::new(vec![
            ("a.las".into(), fake(0.0, 1)),
            ("b.las".into(), other),
        ])
        .err()
        .unwrap();
        assert!(
            e.contains("a.las and b.las") && e.contains("coordinate"),
            "{e}"
        );
    }
}
