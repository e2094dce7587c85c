//! Arbitrary bytes through the hyper point cloud reader of `fwlidar trees`
//! (`fwlidar::trees::points::parse_hyper_points`): it promises an error naming the field, never
//! a panic or an allocation larger than the input warrants.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = fwlidar::trees::points::parse_hyper_points(Path::new("fuzz.las"), data);
});
