//! The scene simulator: pulses per second for the survey-line scene (`config/scenes/
//! survey_line.toml`: 400 kHz, oscillating mirror, a stand of trees, grass, buildings) with no
//! effects, with each effect alone, and with the scene's own cheap set — the cost of each
//! effect is the difference from the no-effect run.

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::pulse::Pulse;
use fwlidar::sim::world::scene::{Effect, WorldScene};
use fwlidar::sim::world::{ShotTruth, WorldSim};

const BATCH: u64 = 2000;

fn sim(effects: &[Effect]) -> WorldSim {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes/survey_line.toml");
    let (mut scene, sensor) = WorldScene::load(&path).unwrap();
    scene.effects = effects.to_vec();
    scene.flight.max_pulses = None;
    // Over the stand of trees from the first pulse (the line starts over open grass).
    scene.flight.lines[0].start_m = [-100.0, 0.0];
    WorldSim::new(&scene, &sensor, path.parent().unwrap()).unwrap()
}

fn pulses(c: &mut Criterion) {
    let mut g = c.benchmark_group("sim_survey_line");
    g.throughput(Throughput::Elements(BATCH));
    let cases: Vec<(&str, Vec<Effect>)> = vec![
        ("none", vec![]),
        ("noise", vec![Effect::Noise]),
        (
            "quantisation_saturation",
            vec![Effect::Quantisation, Effect::Saturation],
        ),
        ("off_nadir", vec![Effect::OffNadir]),
        ("timing_jitter", vec![Effect::TimingJitter]),
        ("ringing", vec![Effect::Ringing]),
        ("packet_loss", vec![Effect::PacketLoss]),
        ("footprint", vec![Effect::Footprint]),
        (
            "scene_set",
            vec![
                Effect::Noise,
                Effect::Quantisation,
                Effect::Saturation,
                Effect::OffNadir,
            ],
        ),
    ];
    for (name, effects) in cases {
        let mut s = sim(&effects);
        let (mut p, mut t) = (Pulse::default(), ShotTruth::default());
        g.bench_function(name, |b| {
            b.iter(|| {
                for _ in 0..BATCH {
                    if s.fill_next(&mut p, &mut t).is_none() {
                        s = sim(&effects);
                        s.fill_next(&mut p, &mut t);
                    }
                    black_box(&p);
                }
            })
        });
    }
    g.finish();
}

criterion_group!(benches, pulses);
criterion_main!(benches);
