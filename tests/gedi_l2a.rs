//! NASA's L2A algorithm from the L1B waveforms of the fixture, checked step by step against
//! every intermediate the L2A fixture stores for its 32 shots, group by group (issue 56;
//! `docs/gedi_l2a.md`): the thresholds, the search window, `toploc`, `botloc`, the modes, the
//! lowest mode, `rx_cumulative` and `rh_aN`.

use std::collections::BTreeMap;

use fwlidar::forest::gedi_check::read_f64;
use fwlidar::forest::gedi_l2a::{GROUPS, process, process_groups};
use fwlidar::format::gedi::GediL1b;
use hdf5_reader::Hdf5File;

const L1B: &str = "waveform/gedi/GEDI01_B_O01964_beams0001_1011.h5";
const L2A: &str = "waveform/gedi/GEDI02_A_O01964_beams0001_1011.h5";

#[test]
fn every_group_reproduces_l2a_to_the_bin() {
    let dir = fwlidar::fixtures::dir();
    let l1b = GediL1b::open(&dir.join(L1B)).unwrap();
    let l2a_path = dir.join(L2A);
    let fa = Hdf5File::open(&l2a_path).unwrap();
    let pa = l2a_path.display().to_string();
    // (group, quantity) -> (exact, compared)
    let mut tally: BTreeMap<(u8, &str), (usize, usize)> = BTreeMap::new();
    let mut count = |g: u8, what: &'static str, ok: bool| {
        let e = tally.entry((g, what)).or_insert((0, 0));
        e.0 += usize::from(ok);
        e.1 += 1;
    };
    let mut shots = 0;
    for beam_name in l1b.beams() {
        let beam = l1b.read_beam(beam_name).unwrap();
        let (mut rx, mut tx) = (Vec::new(), Vec::new());
        l1b.read_waveforms(&beam, 0..beam.shots.len(), &mut rx, &mut tx)
            .unwrap();
        let read = |d: &str| read_f64(&fa, &format!("{beam_name}/{d}"), &pa).unwrap();
        let a_shots = read("shot_number");
        let base = beam.shots.first().map(|s| s.rx_start).unwrap_or(0);
        for s in &beam.shots {
            let Some(ia) = a_shots.iter().position(|&v| v == s.shot_number as f64) else {
                continue;
            };
            shots += 1;
            let off = (s.rx_start - base) as usize;
            let w = &rx[off..off + s.rx_count as usize];
            let dz = (s.bin0[2] - s.lastbin[2]) / f64::from(s.rx_count - 1);
            let (mean, sd) = (s.noise_mean as f32, s.noise_stddev as f32);
            let all = process_groups(w, mean, sd, dz, &GROUPS);
            for (g, r) in GROUPS.iter().zip(all) {
                let n = g.number;
                let at = |d: &str| format!("rx_processing_a{n}/{d}");
                let r = r.unwrap_or_else(|| panic!("shot {} group {n}: no result", s.shot_number));
                // One group alone gives the same as all six together.
                assert_eq!(process(w, mean, sd, dz, g).as_ref(), Some(&r));
                count(
                    n,
                    "front_threshold",
                    f64::from(r.front_threshold) == read(&at("front_threshold"))[ia],
                );
                count(
                    n,
                    "back_threshold",
                    f64::from(r.back_threshold) == read(&at("back_threshold"))[ia],
                );
                count(n, "toploc", r.toploc == read(&at("toploc"))[ia]);
                count(n, "botloc", r.botloc == read(&at("botloc"))[ia]);
                count(n, "zcross", r.zcross == Some(read(&at("zcross"))[ia]));
                let modes = read(&at("rx_modelocs"));
                let k = read(&at("rx_nummodes"))[ia] as usize;
                let per = modes.len() / a_shots.len();
                count(
                    n,
                    "rx_modelocs",
                    r.modes.as_slice() == &modes[ia * per..ia * per + k],
                );
                count(
                    n,
                    "selected_mode",
                    r.selected_mode.map(|m| m as f64) == Some(read(&at("selected_mode"))[ia]),
                );
                let fl = read(&at("selected_mode_flag"))[ia];
                count(
                    n,
                    "selected_mode_flag",
                    f64::from(r.selected_mode_flag) == fl,
                );
                let elev = read(&format!("geolocation/elev_lowestmode_a{n}"))[ia];
                let ours = r.zcross.map(|z| (s.bin0[2] - z * dz) as f32);
                count(n, "elev_lowestmode", ours.map(f64::from) == Some(elev));
                let cum = read(&at("rx_cumulative"));
                let cum = &cum[ia * 101..ia * 101 + 101];
                count(n, "rx_cumulative", r.cumulative.as_slice() == cum);
                let rh = read(&format!("geolocation/rh_a{n}"));
                let rh = &rh[ia * 101..ia * 101 + 101];
                let ours: Vec<f64> = r.rh_cm.iter().map(|&v| f64::from(v)).collect();
                count(n, "rh", ours.as_slice() == rh);
            }
        }
    }
    assert_eq!(shots, 32);
    let mut all = true;
    for ((g, what), (ok, n)) in &tally {
        println!("a{g} {what}: {ok} of {n} exact");
        all &= ok == n;
    }
    assert!(all, "not every intermediate is exact (above)");
}
