//! The ground floor: what every other module may use and that uses no other module of the crate.
//!
//! - [`units`]: the speed of light and the unit conversions built on it, defined once;
//! - [`validate`]: the [`Validate`](validate::Validate) trait and its [`Validator`](validate::Validator)
//!   (semantic checks of a configuration, each problem with its field path);
//! - [`toml_load`] and [`overrides`]: loading a TOML configuration with every problem reported
//!   at once ([`config_error`]), and `--set KEY=VALUE` overrides;
//! - [`sensor`]: the sensor profile a capture carries and the stages read their physics from;
//! - [`facts`]: what an input states about itself;
//! - [`atomic_file`]: output files that appear complete or not at all;
//! - [`nap`]: short naps instead of a wake-up per item on the live input path;
//! - [`fixed_text`]: decimal text of floats with a fixed number of decimals, fast and exactly as
//!   `format!` writes it;
//! - [`half_max`]: where a pulse crosses a level on both sides of its peak (every FWHM).

pub mod atomic_file;
pub mod config_error;
pub mod facts;
pub mod fixed_text;
pub mod half_max;
pub mod nap;
pub mod overrides;
pub mod sensor;
pub mod toml_load;
pub mod units;
pub mod validate;
