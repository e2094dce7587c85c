//! `fwlidar import FILE --out CAPTURE`: converts a waveform file that fwlidar reads (LAS 1.3/1.4
//! with waveform packets, PulseWaves, or a capture) into the capture format, losslessly for what
//! the capture carries: every pulse with its GPS time, digitizer gain/offset, bits, segments
//! (kind, channel, start, samples) and — as GeoFrame records — its anchor and direction; the
//! navigation bytes of a capture; the sensor, time base and CRS in the header.
//!
//! Not carried (stated in `docs/formats.md`): LAS point attributes other than the waveform
//! (classification, intensity, the returns the vendor found), PulseWaves extra bytes and
//! per-sampling sample intervals that differ within a pulse (the readers refuse or report those).
//!
//! The capture is written as `CAPTURE.partial` and renamed when complete; an existing `CAPTURE`
//! is never overwritten, and a failed import leaves nothing behind.

use std::path::{Path, PathBuf};

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::core::facts::SourceFacts;
use crate::core::sensor::{SensorFile, SensorProfile};
use crate::format::{CaptureHeader, CaptureMeta, CaptureWriter, FlushPolicy};
use crate::pipeline::ports::SourceEvent;
use crate::pulse::PulsePool;

/// Arguments of `fwlidar import`.
#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// Input file: LAS or LAZ (.las/.laz, waveforms internal or in a .wdp beside it), PulseWaves
    /// (.pls with its .wvs), a NASA GEDI Level 1B granule (.h5), or a capture.
    pub file: PathBuf,
    /// Capture file to write (must not exist: captures are never overwritten).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Sensor profile (TOML, `config/sensors/`) for the capture header. Needed when the input
    /// does not describe its sensor completely (LAS never does); overrides what it says.
    #[arg(long)]
    pub sensor: Option<PathBuf>,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
}

/// What an import wrote.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct ImportCounts {
    /// Pulses written (frames and GeoFrames).
    pub pulses: u64,
    /// Of those, pulses with geometry (GeoFrame records).
    pub with_geometry: u64,
    /// Navigation chunks written.
    pub nav: u64,
}

/// Runs `fwlidar import`.
pub fn run(args: ImportArgs) -> Result<(), Failure> {
    let sensor = match &args.sensor {
        Some(p) => Some(
            crate::core::toml_load::load_file::<SensorFile>(p)
                .map_err(Failure::usage)?
                .sensor,
        ),
        None => None,
    };
    if args.out.exists() {
        return Err(Failure::job(format!(
            "{}: already exists; captures are never overwritten (choose another --out)",
            args.out.display()
        )));
    }
    let partial = partial_path(&args.out);
    if partial.exists() {
        return Err(Failure::job(format!(
            "{}: a partial import is in the way (another import running, or one that crashed); \
             remove it to import again",
            partial.display()
        )));
    }
    let bar = (!args.no_progress).then(|| {
        let bar = ProgressBar::new(0);
        bar.set_style(
            ProgressStyle::with_template("{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    });
    let result = import(&args.file, &partial, sensor, bar.as_ref());
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    match result {
        Ok(counts) => {
            std::fs::rename(&partial, &args.out).map_err(|e| {
                let _ = std::fs::remove_file(&partial);
                Failure::job(format!(
                    "{}: cannot rename into place: {e}",
                    args.out.display()
                ))
            })?;
            println!(
                "fwlidar import  {}  ->  {}\n  {} pulses ({} with anchor and direction), {} navigation chunks",
                args.file.display(),
                args.out.display(),
                counts.pulses,
                counts.with_geometry,
                counts.nav
            );
            Ok(())
        }
        Err(f) => {
            let _ = std::fs::remove_file(&partial);
            Err(f)
        }
    }
}

fn partial_path(out: &Path) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".partial");
    PathBuf::from(s)
}

/// Copies every event of the input into a new capture at `out` (which must not exist). The
/// header is written once the first event is known, so that a capture input's own header (its
/// first record) is carried over.
pub fn import(
    input: &Path,
    out: &Path,
    sensor: Option<SensorProfile>,
    bar: Option<&ProgressBar>,
) -> Result<ImportCounts, Failure> {
    let mut source = crate::source::open_file(input).map_err(Failure::job)?;
    let pool = PulsePool::new(4);
    let mut counts = ImportCounts::default();
    let mut writer: Option<CaptureWriter<std::fs::File>> = None;
    let job = |e: crate::format::CaptureError| Failure::job(e);
    loop {
        let event = source
            .next(&pool)
            .map_err(|e| Failure::job(format!("{}: {e}", input.display())))?;
        if writer.is_none() {
            let header = header_for(input, source.facts(), sensor.clone())?;
            writer = Some(
                CaptureWriter::create(out, &header.to_text(), FlushPolicy::default())
                    .map_err(job)?,
            );
        }
        let Some(w) = writer.as_mut() else {
            unreachable!("created above")
        };
        match event {
            SourceEvent::End => break,
            SourceEvent::Idle => {}
            SourceEvent::Nav(chunk) => {
                w.write_nav(chunk.port, chunk.receive_time_ns, &chunk.bytes)
                    .map_err(job)?;
                counts.nav += 1;
            }
            SourceEvent::Pulse(pulse) => {
                w.write_pulse(&pulse).map_err(job)?;
                counts.pulses += 1;
                counts.with_geometry += u64::from(pulse.geometry.is_some());
                pool.give(pulse);
            }
        }
        if let (Some(bar), Some((done, total))) = (bar, source.progress()) {
            bar.set_length(total);
            bar.set_position(done);
        }
    }
    if let Some(w) = writer {
        let file = w.finish().map_err(job)?;
        file.sync_all()
            .map_err(|e| Failure::job(format!("{}: cannot sync: {e}", out.display())))?;
    }
    Ok(counts)
}

/// The capture header of an import: the sensor from `--sensor`, else from the input; the time
/// base and CRS from the input.
fn header_for(
    input: &Path,
    facts: SourceFacts,
    sensor: Option<SensorProfile>,
) -> Result<CaptureHeader, Failure> {
    let sensor = sensor.or(facts.sensor).ok_or_else(|| {
        Failure::usage(format!(
            "{}: the file does not describe its sensor completely (wavelength, pulse width, \
             pulse rate, beam divergence); name a sensor profile with --sensor, e.g. \
             config/sensors/riegl_lms_q680i.toml",
            input.display()
        ))
    })?;
    let time_base = facts.time_base.ok_or_else(|| {
        Failure::job(format!(
            "{}: the reader could not tell the time base of the GPS times",
            input.display()
        ))
    })?;
    Ok(CaptureHeader {
        capture: CaptureMeta {
            software: format!("fwlidar {}", env!("CARGO_PKG_VERSION")),
            // The same input gives the same bytes: no wall clock in the header.
            created_unix_s: 0,
            time_base,
            origin: "imported".into(),
            crs: facts.crs,
            source_file: Some(input.display().to_string()),
        },
        sensor,
        scene: None,
    })
}
