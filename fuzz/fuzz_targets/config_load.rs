//! Arbitrary UTF-8 text through the configuration loader (all three file kinds) and the
//! capture Header parser. None of them may panic, whatever the text; errors are fine.
#![no_main]

use fwlidar::config::RunConfig;
use fwlidar::core::sensor::SensorFile;
use fwlidar::core::toml_load::load_str;
use fwlidar::format::CaptureHeader;
use fwlidar::sim::SceneFile;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    // Errors must render (Display walks every issue and its location).
    if let Err(e) = load_str::<RunConfig>(text, "fuzz.toml") {
        let _ = e.to_string();
    }
    if let Err(e) = load_str::<SensorFile>(text, "fuzz.toml") {
        let _ = e.to_string();
    }
    if let Err(e) = load_str::<SceneFile>(text, "fuzz.toml") {
        let _ = e.to_string();
    }
    if let Ok(h) = CaptureHeader::parse(text) {
        let _ = h.to_text();
    }
});
