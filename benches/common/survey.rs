//! Survey-line pulses for the benches that time a stage on the survey line's real mix of empty,
//! sparse and canopy pulses (`benches/signal.rs`, `benches/decompose.rs`).

#![allow(dead_code)]

use std::path::Path;

use fwlidar::pulse::Pulse;
use fwlidar::sim::world::scene::WorldScene;
use fwlidar::sim::world::{ShotTruth, WorldSim};

/// `count` pulses of `config/scenes/survey_line.toml` with their truth, every `stride`-th of
/// the scene's pulses, the line starting at `start_east_m` (metres east) or where the scene
/// starts it; raw, as `fwlidar simulate` writes them.
pub fn survey_line_pulses(
    count: usize,
    stride: usize,
    start_east_m: Option<f64>,
) -> Vec<(Pulse, ShotTruth)> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes/survey_line.toml");
    let (mut scene, sensor) = WorldScene::load(&path).unwrap();
    scene.flight.max_pulses = None;
    if let Some(e) = start_east_m {
        scene.flight.lines[0].start_m = [e, 0.0];
    }
    let mut sim = WorldSim::new(&scene, &sensor, path.parent().unwrap()).unwrap();
    let mut out = Vec::with_capacity(count);
    let (mut p, mut t) = (Pulse::default(), ShotTruth::default());
    let mut i = 0usize;
    while out.len() < count {
        match sim.fill_next(&mut p, &mut t) {
            None => break,
            Some(false) => continue,
            Some(true) => {}
        }
        if i.is_multiple_of(stride) {
            out.push((p.clone(), t.clone()));
        }
        i += 1;
    }
    out
}
