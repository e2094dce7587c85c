//! Decimal text of a float with a fixed number of decimals, written exactly as Rust's
//! `format!("{x:.N}")` writes it (the value's exact binary expansion rounded half to even at the
//! N-th decimal, the sign of a negative value kept even when it rounds to zero), without the
//! general float formatter: an integer multiplication and a shift for every value below 10^15
//! with at most 9 decimals (`pulse_metrics.csv` writes ~160 such numbers per pulse; the
//! formatter's exact mode cost ~20 µs a row). Other values (larger, NaN, infinite, more
//! decimals) go through `format!` itself.

use std::fmt::Write as _;

/// 10^d for d in 0..=9.
const POW10: [u64; 10] = [
    1,
    10,
    100,
    1_000,
    10_000,
    100_000,
    1_000_000,
    10_000_000,
    100_000_000,
    1_000_000_000,
];

/// Appends `x` with `decimals` decimals to `out`, the very text of `format!("{x:.decimals$}")`.
pub fn push_fixed(out: &mut String, x: f64, decimals: usize) {
    if !x.is_finite() || decimals >= POW10.len() || x.abs() >= 1e15 {
        let _ = write!(out, "{x:.decimals$}");
        return;
    }
    let bits = x.to_bits();
    let exp_bits = ((bits >> 52) & 0x7ff) as i32;
    let fraction = bits & ((1u64 << 52) - 1);
    // |x| = m × 2^e exactly.
    let (m, e) = if exp_bits == 0 {
        (fraction, -1074)
    } else {
        (fraction | (1u64 << 52), exp_bits - 1075)
    };
    let scale = POW10[decimals];
    // |x| × 10^decimals < 10^24 < 2^80: no overflow.
    let n = u128::from(m) * u128::from(scale);
    let q = if e >= 0 {
        n << e
    } else {
        let k = (-e) as u32;
        if k >= 128 {
            0 // n < 2^83 is below half of 2^k: rounds to 0
        } else {
            let q = n >> k;
            let rem = n & ((1u128 << k) - 1);
            let half = 1u128 << (k - 1);
            if rem > half || (rem == half && q & 1 == 1) {
                q + 1
            } else {
                q
            }
        }
    };
    // Digits from the right into a stack buffer: the fraction, the point, the integer part,
    // the sign; u64 arithmetic unless the scaled value needs more.
    let mut buf = [0u8; 48];
    let mut i = buf.len();
    let (mut int, mut frac) = match u64::try_from(q) {
        Ok(q) => (u128::from(q / scale), q % scale),
        Err(_) => (q / u128::from(scale), (q % u128::from(scale)) as u64),
    };
    if decimals > 0 {
        for _ in 0..decimals {
            i -= 1;
            buf[i] = b'0' + (frac % 10) as u8;
            frac /= 10;
        }
        i -= 1;
        buf[i] = b'.';
    }
    if let Ok(mut v) = u64::try_from(int) {
        loop {
            i -= 1;
            buf[i] = b'0' + (v % 10) as u8;
            v /= 10;
            if v == 0 {
                break;
            }
        }
    } else {
        loop {
            i -= 1;
            buf[i] = b'0' + (int % 10) as u8;
            int /= 10;
            if int == 0 {
                break;
            }
        }
    }
    if bits >> 63 == 1 {
        i -= 1;
        buf[i] = b'-';
    }
    // ASCII digits, a point and a sign.
    out.push_str(std::str::from_utf8(&buf[i..]).unwrap_or_default());
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(x: f64, d: usize) {
        let mut got = String::new();
        push_fixed(&mut got, x, d);
        assert_eq!(got, format!("{x:.d$}"), "{x:e} with {d} decimals");
    }

    #[test]
    fn ties_round_to_even_and_negative_zero_keeps_its_sign() {
        for (x, d) in [
            (0.25, 1),
            (0.35, 1),
            (0.5, 0),
            (1.5, 0),
            (2.5, 0),
            (-0.0001, 3),
            (-0.0, 3),
            (0.0, 3),
            (0.125, 2),
            (0.375, 2),
            (9.9995, 3),
            (-9.9995, 3),
            (0.9999999999, 9),
            (5e-324, 9),
            (-5e-324, 0),
            (2.2250738585072014e-308, 6),
            (999_999_999_999_999.9, 3),
            (1e15, 3),
            (f64::NAN, 3),
            (f64::INFINITY, 2),
            (f64::NEG_INFINITY, 2),
            (1.0, 12),
            (f64::from(f32::from_bits(1)), 9),
            (f64::from(f32::MIN_POSITIVE), 9),
            (f64::from(f32::MAX), 3),
        ] {
            check(x, d);
        }
    }

    #[test]
    fn random_values_of_every_magnitude_match_format() {
        // A fixed xorshift: reproducible, every exponent from 1e-12 to 1e15 and every decimals.
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for _ in 0..200_000 {
            let r = next();
            let mant = (r >> 11) as f64 / (1u64 << 53) as f64;
            let exp = (next() % 28) as i32 - 12;
            let x = (mant * 10f64.powi(exp)) * if r & 1 == 1 { -1.0 } else { 1.0 };
            let d = (next() % 10) as usize;
            check(x, d);
            // The f32 values `pulse_metrics.csv` writes, widened exactly.
            check(f64::from(x as f32), d);
        }
        // Exact ties: k / 2^j with few bits.
        for j in 1..=20 {
            for k in 0..200u32 {
                let x = f64::from(k) / f64::from(1u32 << j);
                for d in 0..10 {
                    check(x, d);
                    check(-x, d);
                }
            }
        }
    }
}
