//! Real full-waveform files from other people's instruments and software, through our readers
//! and the command line: the RIEGL LMS-Q680i flight line stored both as LAS 1.4 + .wdp and as
//! PulseWaves pins the LAS parametric-line sign convention (every LAS point lies on its
//! PulseWaves pulse's ray), and `replay` / `import` accept both formats directly.
//!
//! Reads `tests/data/waveform/` (see tests/data/MANIFEST.md); fails naming what is missing.

use std::path::Path;

use fwlidar::pipeline::ports::SourceEvent;
use fwlidar::pulse::{Pulse, PulsePool, SegmentKind};
use fwlidar::source::open_file;

mod common;
use common::{fixture, fwlidar, text};

const RIEGL: &str = "waveform/riegl_q680i/100429_152240_2535pt_UTM";

/// A pulse as plain data, copied out of the pool's recycled pulse.
#[derive(Clone, Debug)]
struct Shot {
    gps_time: f64,
    anchor: [f64; 3],
    direction: [f64; 3],
    sample_ns: f64,
    /// (kind, channel, start_ns, samples)
    segments: Vec<(SegmentKind, u8, f64, Vec<u16>)>,
}

fn shot_of(p: &Pulse) -> Shot {
    let g = p
        .geometry
        .expect("a pulse of a LAS or PulseWaves file carries its geometry");
    Shot {
        gps_time: p.gps_time,
        anchor: g.anchor,
        direction: g.direction,
        sample_ns: p.sample_ns,
        segments: (0..p.segments.len())
            .map(|i| {
                let s = p.segments[i];
                (s.kind, s.channel, s.start_ns, p.raw_of(i).to_vec())
            })
            .collect(),
    }
}

/// Every pulse of a file through [`open_file`], the path `replay` and `import` take.
fn read_all(path: &Path) -> Vec<Shot> {
    let mut src = open_file(path).unwrap_or_else(|e| panic!("{e}"));
    let pool = PulsePool::new(4);
    let mut out = Vec::new();
    loop {
        match src.next(&pool).unwrap_or_else(|e| panic!("{e}")) {
            SourceEvent::Pulse(p) => {
                out.push(shot_of(&p));
                pool.give(p);
            }
            SourceEvent::Nav(_) | SourceEvent::Idle => {}
            SourceEvent::End => break,
        }
    }
    out
}

fn add(a: [f64; 3], s: f64, d: [f64; 3]) -> [f64; 3] {
    [a[0] + s * d[0], a[1] + s * d[1], a[2] + s * d[2]]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// Distance of `p` from the line through `a` along `d`.
fn distance_to_ray(p: [f64; 3], a: [f64; 3], d: [f64; 3]) -> f64 {
    let ap = sub(p, a);
    let t = dot(ap, d) / dot(d, d);
    norm(sub(ap, [t * d[0], t * d[1], t * d[2]]))
}

/// One point of the LAS file as the bytes say, read here independently of the reader under
/// test (LAS 1.4 R15 §2.6, point data record format 9: format 6's 30 bytes, then the wave
/// packet fields).
struct RawLasPoint {
    xyz: [f64; 3],
    gps_time: f64,
    byte_offset: u64,
    packet_bytes: u32,
    location_ps: f32,
    xyz_t: [f32; 3],
}

fn raw_las_points(las: &[u8]) -> Vec<RawLasPoint> {
    let u16_at = |o: usize| u16::from_le_bytes(las[o..o + 2].try_into().unwrap());
    let u32_at = |o: usize| u32::from_le_bytes(las[o..o + 4].try_into().unwrap());
    let u64_at = |o: usize| u64::from_le_bytes(las[o..o + 8].try_into().unwrap());
    let f64_at = |o: usize| f64::from_le_bytes(las[o..o + 8].try_into().unwrap());
    let f32_at = |o: usize| f32::from_le_bytes(las[o..o + 4].try_into().unwrap());
    let i32_at = |o: usize| i32::from_le_bytes(las[o..o + 4].try_into().unwrap());
    assert_eq!(&las[..4], b"LASF");
    assert_eq!(las[104], 9, "the fixture is point format 9");
    let first = u32_at(96) as usize;
    let len = u16_at(105) as usize;
    let n = u64_at(247) as usize;
    let scale = [f64_at(131), f64_at(139), f64_at(147)];
    let offset = [f64_at(155), f64_at(163), f64_at(171)];
    (0..n)
        .map(|i| {
            let p = first + i * len;
            RawLasPoint {
                xyz: [0, 1, 2].map(|k| i32_at(p + 4 * k) as f64 * scale[k] + offset[k]),
                gps_time: f64_at(p + 22),
                byte_offset: u64_at(p + 31),
                packet_bytes: u32_at(p + 39),
                location_ps: f32_at(p + 43),
                xyz_t: [f32_at(p + 47), f32_at(p + 51), f32_at(p + 55)],
            }
        })
        .collect()
}

/// The golden cross-format test. For every LAS point: its PulseWaves pulse (nearest GPS time,
/// within 0.5 µs); the point lies on that pulse's ray within 3 mm; the LAS direction
/// −(x_t, y_t, z_t) is parallel to the pulse's direction; the point's .wdp samples equal one
/// return segment of the pulse, always on the same channel (RIEGL's low-power channel), and the
/// point lies `return_point_waveform_location` after that segment's first sample. Then the LAS
/// reader's own pulses: each starts where that segment starts (3 mm) with the same samples.
#[test]
fn riegl_las_points_lie_on_their_pulsewaves_rays() {
    let las_path = fixture(&format!("{RIEGL}.las"));
    let wdp = std::fs::read(fixture(&format!("{RIEGL}.wdp"))).unwrap();
    let pls_path = fixture(&format!("{RIEGL}.pls"));
    fixture(&format!("{RIEGL}.wvs"));
    let las = std::fs::read(&las_path).unwrap();
    let points = raw_las_points(&las);
    assert_eq!(points.len(), 2535);

    let mut pls = read_all(&pls_path);
    assert_eq!(pls.len(), 2368, "pulses of the PulseWaves file");
    pls.sort_by(|a, b| a.gps_time.total_cmp(&b.gps_time));

    // Both files store coordinates in whole millimetres (scale 0.001) and the PulseWaves time
    // in whole microseconds. The pulse's direction is (target − anchor) / 1000 sampling units,
    // both rounded, so a position `t` ns along the ray is known to within
    // √3 · 0.5 mm · (|1 − t/1000| + t/1000), plus √3 · 0.5 mm for the LAS point itself. Each
    // point must lie within that bound (≈ 6-7 mm at the ~4 µs of this flight's ranges); the
    // median must be under 3 mm. A sign error in the parametric line would put the first
    // sample 2 · L · |v| (metres) away.
    let half_mm = 0.5e-3 * 3f64.sqrt();
    let bound = |t: f64| half_mm * ((1.0 - t / 1000.0).abs() + t / 1000.0 + 1.0);
    let mut ray_mm = Vec::new();
    let mut las_ray_mm = Vec::new();
    let mut along_mm = Vec::new();
    let mut worst_angle = 0.0f64;
    let mut channels = std::collections::BTreeSet::new();
    // Per point, for the reader check: (gps_time, first-sample position on the PulseWaves ray,
    // samples, byte offset of its packet, how far the position may be off by rounding).
    type Expected = (f64, [f64; 3], Vec<u16>, u64, f64);
    let mut expected: Vec<Expected> = Vec::new();
    for (i, pt) in points.iter().enumerate() {
        let k = pls.partition_point(|s| s.gps_time < pt.gps_time);
        let best = [k.saturating_sub(1), k.min(pls.len() - 1)]
            .into_iter()
            .min_by(|&a, &b| {
                (pls[a].gps_time - pt.gps_time)
                    .abs()
                    .total_cmp(&(pls[b].gps_time - pt.gps_time).abs())
            })
            .unwrap();
        let pulse = &pls[best];
        let dt = (pulse.gps_time - pt.gps_time).abs();
        assert!(
            dt <= 0.5e-6 + 1e-9,
            "point {i}: no PulseWaves pulse within 0.5 us ({dt} s)"
        );

        let t =
            dot(sub(pt.xyz, pulse.anchor), pulse.direction) / dot(pulse.direction, pulse.direction);
        let d = distance_to_ray(pt.xyz, pulse.anchor, pulse.direction);
        assert!(
            d <= bound(t),
            "point {i}: {d} m from its pulse's ray (rounding allows {} m)",
            bound(t)
        );
        ray_mm.push(d * 1e3);
        // The same with the LAS file's own direction (f32, ~1e-7 relative) through the
        // PulseWaves anchor: the PulseWaves direction's rounding drops out and only the files'
        // millimetre positions (and RIEGL's own placing of the points) are left: within 3 mm.
        let las_ray = distance_to_ray(pt.xyz, pulse.anchor, pt.xyz_t.map(|v| v as f64));
        las_ray_mm.push(las_ray * 1e3);
        assert!(
            las_ray <= 0.003,
            "point {i}: {las_ray} m from the line through its pulse's anchor along x(t), y(t), z(t)"
        );

        let las_dir = pt.xyz_t.map(|v| -(v as f64));
        let cos = dot(las_dir, pulse.direction) / (norm(las_dir) * norm(pulse.direction));
        worst_angle = worst_angle.max(cos.clamp(-1.0, 1.0).acos());
        assert!(
            cos > 0.999_99,
            "point {i}: LAS direction not along the pulse (cos {cos})"
        );

        let at = pt.byte_offset as usize;
        let bytes = &wdp[at..at + pt.packet_bytes as usize];
        let samples: Vec<u16> = bytes
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        let seg = pulse
            .segments
            .iter()
            .find(|s| s.0 == SegmentKind::Return && s.3 == samples)
            .unwrap_or_else(|| {
                panic!(
                    "point {i}: no return segment of its pulse has the .wdp samples ({} samples; \
                     segments {:?})",
                    samples.len(),
                    pulse
                        .segments
                        .iter()
                        .map(|s| (s.1, s.2, s.3.len()))
                        .collect::<Vec<_>>()
                )
            });
        channels.insert(seg.1);
        let start = add(pulse.anchor, seg.2, pulse.direction);
        let at_point = add(start, pt.location_ps as f64 / 1000.0, pulse.direction);
        let along = norm(sub(at_point, pt.xyz));
        assert!(
            along <= bound(t) + 0.0015,
            "point {i}: {along} m from `return_point_waveform_location` after its segment start"
        );
        along_mm.push(along * 1e3);
        expected.push((
            pt.gps_time,
            start,
            samples,
            pt.byte_offset,
            bound(t) + half_mm,
        ));
    }
    assert_eq!(
        channels.len(),
        1,
        "every LAS packet is one channel's segment: {channels:?}"
    );
    let pct = |v: &mut Vec<f64>, q: f64| {
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * q).round() as usize]
    };
    let (r50, r95, r100) = (
        pct(&mut ray_mm, 0.5),
        pct(&mut ray_mm, 0.95),
        pct(&mut ray_mm, 1.0),
    );
    let (l50, l100) = (pct(&mut las_ray_mm, 0.5), pct(&mut las_ray_mm, 1.0));
    let (a50, a95, a100) = (
        pct(&mut along_mm, 0.5),
        pct(&mut along_mm, 0.95),
        pct(&mut along_mm, 1.0),
    );
    eprintln!(
        "golden: {} of {} points matched; distance from the ray median {r50:.2} / p95 \
         {r95:.2} / max {r100:.2} mm; from the point L ps after the segment start median \
         {a50:.2} / p95 {a95:.2} / max {a100:.2} mm; from the line along the LAS direction \
         through the PulseWaves anchor median {l50:.2} / max {l100:.2} mm; worst angle \
         {worst_angle:.2e} rad; \
         channel {channels:?}",
        points.len(),
        points.len()
    );
    assert!(r50 < 3.0 && a50 < 3.0, "median within 3 mm");

    // The LAS reader: one pulse per run of consecutive points naming the same packet (its
    // documented grouping: the RIEGL file names one packet again after others, so 2375
    // distinct packets give 2376 pulses), in file order, starting where the PulseWaves segment
    // starts, with the same samples.
    let las_pulses = read_all(&las_path);
    expected.dedup_by(|a, b| a.3 == b.3);
    assert_eq!(
        las_pulses.len(),
        expected.len(),
        "one pulse per run of a packet"
    );
    for (n, (p, e)) in las_pulses.iter().zip(&expected).enumerate() {
        assert_eq!(p.gps_time, e.0, "LAS pulse {n}: time of its first point");
        let off = norm(sub(e.1, p.anchor));
        assert!(
            off <= e.4,
            "LAS pulse {n}: first sample {off} m from the PulseWaves segment start"
        );
        assert_eq!(p.segments.len(), 1);
        assert_eq!(p.segments[0].0, SegmentKind::Return);
        assert_eq!(p.segments[0].2, 0.0, "the anchor is the first sample");
        assert_eq!(p.segments[0].3, e.2, "LAS pulse {n}: samples");
        assert!((p.sample_ns - 1.0).abs() < 1e-12);
        assert!(
            (norm(p.direction) - 0.1499).abs() < 0.0005,
            "half the speed of light in air per ns: {:?}",
            p.direction
        );
        assert!(p.direction[2] < 0.0, "downward");
    }
}

/// `import` of each real format keeps every pulse: the capture inspects exactly as the file.
#[test]
fn import_of_las_and_pulsewaves_keeps_every_pulse() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            fixture(&format!("{RIEGL}.las")),
            Some("config/sensors/riegl_lms_q680i.toml"),
        ),
        (fixture(&format!("{RIEGL}.pls")), None),
        (fixture("waveform/pulsewaves/test.pls"), None),
    ];
    for (i, (input, sensor)) in cases.iter().enumerate() {
        let out = dir.path().join(format!("imported{i}.fwcap"));
        let mut args = vec![
            "import",
            input.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-progress",
        ];
        if let Some(s) = sensor {
            args.extend(["--sensor", s]);
        }
        let o = fwlidar(&args);
        assert!(
            o.status.success(),
            "{}: {}",
            input.display(),
            text(&o.stderr)
        );
        let a = fwlidar(&["inspect", input.to_str().unwrap(), "--pulses", "--json"]);
        let b = fwlidar(&["inspect", out.to_str().unwrap(), "--pulses", "--json"]);
        assert!(a.status.success(), "{}", text(&a.stderr));
        assert!(b.status.success(), "{}", text(&b.stderr));
        assert!(text(&a.stdout).lines().count() > 0);
        assert!(
            a.stdout == b.stdout,
            "{}: the imported capture differs from the file",
            input.display()
        );
        let o = fwlidar(&["inspect", out.to_str().unwrap()]);
        let info = text(&o.stdout);
        assert!(info.contains("origin: imported"), "{info}");
    }
}

/// A LAS file states no sensor, and LVIS's scanner record has no pulse rate: import asks for a
/// sensor profile rather than inventing one, and writes nothing.
#[test]
fn import_without_a_complete_sensor_says_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    for input in [
        fixture(&format!("{RIEGL}.las")),
        fixture("waveform/pulsewaves/lvis_example1.pls"),
    ] {
        let out = dir.path().join("x.fwcap");
        let o = fwlidar(&[
            "import",
            input.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-progress",
        ]);
        let err = text(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(err.contains("--sensor"), "{err}");
        assert!(
            err.contains(input.file_name().unwrap().to_str().unwrap()),
            "{err}"
        );
        assert!(!out.exists());
    }
}

/// `replay` takes LAS and PulseWaves files directly; pulses carry their geometry, so the
/// returns have coordinates, and they lie near the LAS file's own points.
#[test]
fn replay_of_las_and_pulsewaves_writes_located_returns() {
    let dir = tempfile::tempdir().unwrap();
    let las_path = fixture(&format!("{RIEGL}.las"));
    let points = raw_las_points(&std::fs::read(&las_path).unwrap());
    let (zmin, zmax) = points.iter().fold((f64::MAX, f64::MIN), |(a, b), p| {
        (a.min(p.xyz[2]), b.max(p.xyz[2]))
    });
    for (name, input) in [
        ("las", las_path.clone()),
        ("pls", fixture(&format!("{RIEGL}.pls"))),
    ] {
        let out = dir.path().join(name);
        let o = fwlidar(&[
            "replay",
            input.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-progress",
            "--set",
            "output.returns=true",
        ]);
        assert!(o.status.success(), "{name}: {}", text(&o.stderr));
        let csv = std::fs::read_to_string(out.join("returns.csv")).unwrap();
        let mut lines = csv.lines();
        let head: Vec<&str> = lines.next().unwrap().split(',').collect();
        let zi = head.iter().position(|h| *h == "z").expect("a z column");
        let zs: Vec<f64> = lines
            .map(|l| l.split(',').nth(zi).unwrap().parse::<f64>().unwrap())
            .collect();
        assert!(zs.len() > 1000, "{name}: {} returns", zs.len());
        // The returns are where the terrain and vegetation are (the LAS points' height range,
        // with a few metres for the pulse tails), not at the aircraft.
        let inside = zs
            .iter()
            .filter(|z| **z > zmin - 5.0 && **z < zmax + 5.0)
            .count();
        assert!(
            inside as f64 >= 0.95 * zs.len() as f64,
            "{name}: {inside} of {} returns within the points' heights {zmin:.1}..{zmax:.1} m",
            zs.len()
        );
    }
}

/// A waveform file whose sample file is missing: a clear error naming both files, non-zero exit.
#[test]
fn missing_wdp_or_wvs_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    for ext in ["las", "pls"] {
        let lone = dir.path().join(format!("lone.{ext}"));
        std::fs::copy(fixture(&format!("{RIEGL}.{ext}")), &lone).unwrap();
        let o = fwlidar(&["inspect", lone.to_str().unwrap(), "--pulses", "--json"]);
        assert_eq!(o.status.code(), Some(1), "{ext}: {}", text(&o.stderr));
        let err = text(&o.stderr);
        let side = if ext == "las" { "lone.wdp" } else { "lone.wvs" };
        assert!(
            err.contains(&format!("lone.{ext}")) || err.contains(side),
            "{ext}: {err}"
        );
        assert!(err.contains(side), "{ext}: {err}");
    }
}
