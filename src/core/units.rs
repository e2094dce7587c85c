//! Physical constants and unit conversions, defined once.
//!
//! The speed of light is defined here and nowhere else: every range from a time of flight, every
//! bin spacing along a beam and every simulated delay derives from [`C_M_PER_S`].

/// Speed of light in vacuum, m/s (exact, by the definition of the metre).
pub const C_M_PER_S: f64 = 299_792_458.0;

/// Speed of light in vacuum, m/ns. `C_M_PER_S / 1e9` is correctly rounded, so this is the
/// nearest `f64` to 0.299 792 458.
pub const C_M_PER_NS: f64 = C_M_PER_S / 1e9;

/// Half the speed of light in vacuum, m/ns: the range covered per ns of two-way travel time
/// (one digitizer bin of 1 ns spans this much along the beam, in vacuum).
pub const HALF_C_M_PER_NS: f64 = C_M_PER_NS / 2.0;

/// Range per ns of two-way travel time in a medium of refractive index `n` (1 = vacuum; air at
/// sea level is about 1.000 29), m/ns: c / (2 n).
pub const fn half_c_in_m_per_ns(refractive_index: f64) -> f64 {
    C_M_PER_NS / (2.0 * refractive_index)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derived_constants_equal_the_decimal_values() {
        // The unit changes are exact, so the derived constants are the very bits of the
        // decimal values they stand for.
        assert_eq!(C_M_PER_NS, 0.299_792_458);
        assert_eq!(HALF_C_M_PER_NS, 0.149_896_229);
        assert_eq!(half_c_in_m_per_ns(1.0), HALF_C_M_PER_NS);
        assert!(half_c_in_m_per_ns(1.000_29) < HALF_C_M_PER_NS);
    }
}
