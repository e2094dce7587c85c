//! Pulse descriptors (`PulseWaves_Spec` records 200001..200255): a composition record followed
//! by one sampling record per sampling (outgoing or returning, per channel).
//!
//! Layout as the real files have it. The composition record stores `compression` *before*
//! `scanner_index` (the 0.3 draft lists them the other way round): every real file has
//! `0, 1` there with a scanner record 100001 present, or `0, 0` with none.

use super::error::PulseWavesError;
use super::le;

/// Bytes of a composition record in version 0.3 (description included).
pub const COMPOSITION_LEN: u32 = 92;
/// Bytes of a sampling record in version 0.3 (description included).
pub const SAMPLING_LEN: u32 = 104;
/// `optical_center_to_anchor` value meaning "no constant offset".
pub const NO_CONSTANT_OFFSET: u32 = 0x8FFF_FFFF;

/// The composition record: what a pulse of this descriptor holds.
#[derive(Clone, Debug, PartialEq)]
pub struct Composition {
    /// Duration from the optical centre to the anchor, sampling units (`None` when the file
    /// says there is no constant one, `0x8FFFFFFF`).
    pub optical_center_to_anchor: Option<i32>,
    /// Bytes at the start of each pulse's waves to skip.
    pub extra_wave_bytes: u16,
    /// Number of sampling records that follow.
    pub number_of_samplings: u16,
    /// Sampling unit of the pulse's time axis (anchor → target spans 1000 of them), ns.
    pub sample_units_ns: f32,
    /// Compression (0 = none; anything else is refused).
    pub compression: u32,
    /// Scanner record index (record ID `100000 + index`; 0 = none).
    pub scanner_index: u32,
    /// Description, text.
    pub description: String,
}

/// What a sampling records.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplingType {
    /// The outgoing pulse (type 1).
    Outgoing,
    /// A returning waveform (type 2).
    Returning,
}

/// A sampling record: how one sampling's segments are stored in the `.wvs` file.
#[derive(Clone, Debug, PartialEq)]
pub struct Sampling {
    /// Outgoing or returning.
    pub kind: SamplingType,
    /// Receiver channel.
    pub channel: u8,
    /// Bits of each segment's duration from the anchor in the waves: 0 (none: duration is the
    /// offset), 8, 16 or 32 (signed integers).
    pub bits_for_duration_from_anchor: u8,
    /// Scale of the stored duration, sampling units per count.
    pub scale_for_duration_from_anchor: f32,
    /// Offset of the stored duration, sampling units.
    pub offset_for_duration_from_anchor: f32,
    /// Bits of the stored number of segments: 0 (fixed, [`Sampling::number_of_segments`]), 8,
    /// 16 or 32.
    pub bits_for_number_of_segments: u8,
    /// Bits of each segment's stored number of samples: 0 (fixed,
    /// [`Sampling::number_of_samples`]), 8, 16 or 32.
    pub bits_for_number_of_samples: u8,
    /// Fixed number of segments (when not stored per pulse).
    pub number_of_segments: u16,
    /// Fixed number of samples per segment (when not stored per segment).
    pub number_of_samples: u32,
    /// Bits per sample: 8 or 16.
    pub bits_per_sample: u16,
    /// Lookup table index (record ID `300000 + index`; 0 = none). Not applied: samples stay
    /// raw counts.
    pub lookup_table_index: u16,
    /// Sample spacing, ns.
    pub sample_units_ns: f32,
    /// Description, text.
    pub description: String,
}

impl Sampling {
    /// Bytes per sample (1 or 2).
    pub fn bytes_per_sample(&self) -> u64 {
        u64::from(self.bits_per_sample / 8)
    }
}

/// A pulse descriptor: its composition and samplings, checked.
#[derive(Clone, Debug, PartialEq)]
pub struct PulseDescriptor {
    /// Index (record ID − 200000).
    pub index: u8,
    /// The composition record.
    pub composition: Composition,
    /// The sampling records, in waves order.
    pub samplings: Vec<Sampling>,
}

impl PulseDescriptor {
    /// Sample interval of every sampling of this descriptor, ns (checked equal).
    #[inline]
    pub fn sample_ns(&self) -> f64 {
        self.samplings
            .first()
            .map_or(f64::from(self.composition.sample_units_ns), |s| {
                f64::from(s.sample_units_ns)
            })
    }

    /// Largest bits per sample of the samplings (8 or 16).
    #[inline]
    pub fn bits(&self) -> u8 {
        self.samplings
            .iter()
            .map(|s| s.bits_per_sample)
            .max()
            .unwrap_or(8)
            .min(16) as u8
    }

    /// Decodes and checks the payload of record `200000 + index` of `file`.
    pub fn parse(
        payload: &[u8],
        index: u8,
        file: &str,
    ) -> Result<PulseDescriptor, PulseWavesError> {
        let at = |f: &str| {
            format!(
                "descriptor {index} (record {}): {f}",
                200_000 + index as u32
            )
        };
        let bad = |f: &str, r: String| PulseWavesError::invalid(file, at(f), r);
        let size = le::u32(payload, 0);
        if size < COMPOSITION_LEN || size as usize > payload.len() {
            return Err(bad(
                "composition size",
                format!(
                    "{size} bytes; must be at least {COMPOSITION_LEN} and fit the record's {} bytes",
                    payload.len()
                ),
            ));
        }
        let oc = le::u32(payload, 8);
        let composition = Composition {
            optical_center_to_anchor: (oc != NO_CONSTANT_OFFSET).then_some(oc as i32),
            extra_wave_bytes: le::u16(payload, 12),
            number_of_samplings: le::u16(payload, 14),
            sample_units_ns: le::f32(payload, 16),
            compression: le::u32(payload, 20),
            scanner_index: le::u32(payload, 24),
            description: le::text(payload, size as usize - 64, 64),
        };
        if composition.compression != 0 {
            return Err(PulseWavesError::unsupported(
                file,
                at("composition compression"),
                format!("compression {}", composition.compression),
            ));
        }
        let su = composition.sample_units_ns;
        if !(su.is_finite() && su > 0.0) {
            return Err(bad(
                "composition sample_units",
                format!("{su} ns; must be finite and positive"),
            ));
        }
        if composition.number_of_samplings == 0 {
            return Err(bad(
                "number_of_samplings",
                "0; a descriptor needs at least one sampling".into(),
            ));
        }
        let mut samplings = Vec::with_capacity(
            usize::from(composition.number_of_samplings)
                .min(payload.len() / SAMPLING_LEN as usize + 1),
        );
        let mut pos = size as usize;
        for k in 0..composition.number_of_samplings {
            let rest = payload.get(pos..).unwrap_or(&[]);
            let s_size = le::u32(rest, 0);
            if rest.len() < SAMPLING_LEN as usize
                || s_size < SAMPLING_LEN
                || s_size as usize > rest.len()
            {
                return Err(bad(
                    &format!("sampling {k} size"),
                    format!(
                        "{s_size} bytes with {} bytes left in the record (number_of_samplings {}); \
                         a sampling record has at least {SAMPLING_LEN}",
                        rest.len(),
                        composition.number_of_samplings
                    ),
                ));
            }
            samplings.push(parse_sampling(rest, s_size as usize, file, &|f| {
                at(&format!("sampling {k}: {f}"))
            })?);
            pos += s_size as usize;
        }
        if let Some(first) = samplings.first() {
            for (k, s) in samplings.iter().enumerate() {
                if s.sample_units_ns != first.sample_units_ns {
                    return Err(bad(
                        &format!("sampling {k}: sample_units"),
                        format!(
                            "{} ns differs from sampling 0's {} ns (a fwlidar pulse has one \
                             sample interval)",
                            s.sample_units_ns, first.sample_units_ns
                        ),
                    ));
                }
            }
        }
        Ok(PulseDescriptor {
            index,
            composition,
            samplings,
        })
    }
}

fn parse_sampling(
    b: &[u8],
    size: usize,
    file: &str,
    at: &dyn Fn(&str) -> String,
) -> Result<Sampling, PulseWavesError> {
    let bad = |f: &str, r: String| PulseWavesError::invalid(file, at(f), r);
    let kind = match le::u8(b, 8) {
        1 => SamplingType::Outgoing,
        2 => SamplingType::Returning,
        t => {
            return Err(bad(
                "type",
                format!("{t}; must be 1 (outgoing) or 2 (returning)"),
            ));
        }
    };
    let s = Sampling {
        kind,
        channel: le::u8(b, 9),
        bits_for_duration_from_anchor: le::u8(b, 11),
        scale_for_duration_from_anchor: le::f32(b, 12),
        offset_for_duration_from_anchor: le::f32(b, 16),
        bits_for_number_of_segments: le::u8(b, 20),
        bits_for_number_of_samples: le::u8(b, 21),
        number_of_segments: le::u16(b, 22),
        number_of_samples: le::u32(b, 24),
        bits_per_sample: le::u16(b, 28),
        lookup_table_index: le::u16(b, 30),
        sample_units_ns: le::f32(b, 32),
        description: le::text(b, size.saturating_sub(64), 64),
    };
    for (name, bits) in [
        (
            "bits_for_duration_from_anchor",
            s.bits_for_duration_from_anchor,
        ),
        ("bits_for_number_of_segments", s.bits_for_number_of_segments),
        ("bits_for_number_of_samples", s.bits_for_number_of_samples),
    ] {
        if !matches!(bits, 0 | 8 | 16 | 32) {
            return Err(bad(name, format!("{bits}; must be 0, 8, 16 or 32")));
        }
    }
    if !(s.scale_for_duration_from_anchor.is_finite()
        && s.offset_for_duration_from_anchor.is_finite())
    {
        return Err(bad(
            "scale/offset_for_duration_from_anchor",
            format!(
                "{} / {} must be finite",
                s.scale_for_duration_from_anchor, s.offset_for_duration_from_anchor
            ),
        ));
    }
    if !matches!(s.bits_per_sample, 8 | 16) {
        return Err(PulseWavesError::unsupported(
            file,
            at("bits_per_sample"),
            format!(
                "{} bits per sample (only 8 and 16 are read)",
                s.bits_per_sample
            ),
        ));
    }
    if !(s.sample_units_ns.is_finite() && s.sample_units_ns > 0.0) {
        return Err(bad(
            "sample_units",
            format!("{} ns; must be finite and positive", s.sample_units_ns),
        ));
    }
    let compression = le::u32(b, 36);
    if compression != 0 {
        return Err(PulseWavesError::unsupported(
            file,
            at("compression"),
            format!("compressed samples (compression {compression})"),
        ));
    }
    if s.bits_for_number_of_samples == 0 && s.number_of_samples == 0 {
        return Err(bad(
            "number_of_samples",
            "0 with bits_for_number_of_samples 0: every segment would be empty".into(),
        ));
    }
    Ok(s)
}
