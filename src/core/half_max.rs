//! Where a pulse crosses a level on both sides of its peak: the shared step of every full
//! width at half maximum in the crate (a GEDI transmit waveform's, a deconvolution kernel's).

/// The crossings of `level` on both sides of sample `k` of a record of `len` samples whose
/// values `v` gives (`v(k)` above `level`), in samples: walking out from `k` while samples stay
/// above `level`, each crossing is interpolated linearly between the last sample above and the
/// next one. `Err(i)` on a side where the record ends first, `i` the last sample above there.
pub fn crossings(
    len: usize,
    v: impl Fn(usize) -> f64,
    k: usize,
    level: f64,
) -> (Result<f64, usize>, Result<f64, usize>) {
    let mut l = k;
    while l > 0 && v(l - 1) > level {
        l -= 1;
    }
    let mut r = k;
    while r + 1 < len && v(r + 1) > level {
        r += 1;
    }
    let left = if l == 0 {
        Err(l)
    } else {
        Ok((l - 1) as f64 + (level - v(l - 1)) / (v(l) - v(l - 1)))
    };
    let right = if r + 1 >= len {
        Err(r)
    } else {
        Ok(r as f64 + (v(r) - level) / (v(r) - v(r + 1)))
    };
    (left, right)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crossings_are_interpolated_and_record_ends_reported() {
        let x = [0.0, 1.0, 3.0, 4.0, 2.0, 0.0];
        let v = |i: usize| x[i];
        // Level 2 on the way up between samples 1 and 2 (1 → 3), down at sample 4 exactly.
        let (l, r) = crossings(x.len(), v, 3, 2.0);
        assert_eq!(l, Ok(1.5));
        assert_eq!(r, Ok(3.0 + 2.0 / 2.0));
        // A record that starts above the level: the left side ends first.
        let (l, r) = crossings(4, |i| [3.0, 4.0, 2.0, 0.0][i], 1, 1.0);
        assert_eq!(l, Err(0));
        assert_eq!(r, Ok(2.5));
        let (_, r) = crossings(2, |i| [1.0, 4.0][i], 1, 0.5);
        assert_eq!(r, Err(1));
    }
}
