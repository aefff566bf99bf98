//! Floats as ordered integers: the residual of a value against its prediction, counted in units
//! in the last place (ULPs) and zig-zag coded, and its inverse. Every bit pattern (NaN payloads,
//! infinities, -0.0) round-trips; a close prediction leaves a small residual. Shared by the
//! core columns' codec and the path payload's predictors.

/// The bits of `f` as an integer ordered like the floats (negative floats reversed); branch-free.
#[inline]
fn ord(f: f32) -> i32 {
    let b = f.to_bits() as i32;
    b ^ (((b >> 31) as u32) >> 1) as i32
}

#[inline]
fn unord(i: i32) -> f32 {
    f32::from_bits((i ^ (((i >> 31) as u32) >> 1) as i32) as u32)
}

/// `zz(ord(actual) - ord(pred))` with wrapping arithmetic.
#[inline]
pub(crate) fn residual(actual: f32, pred: f32) -> u32 {
    let d = ord(actual).wrapping_sub(ord(pred));
    ((d << 1) ^ (d >> 31)) as u32
}

/// The value whose [`residual`] against `pred` is `r`.
#[inline]
pub(crate) fn apply(r: u32, pred: f32) -> f32 {
    let d = ((r >> 1) as i32) ^ -((r & 1) as i32);
    unord(ord(pred).wrapping_add(d))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn residuals_are_a_bijection_on_bits() {
        let specials = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::from_bits(0x7fc0_1234),
            f32::from_bits(0xffc0_0001),
            1e-30,
            3e30,
        ];
        for &a in &specials {
            for &p in &specials {
                assert_eq!(apply(residual(a, p), p).to_bits(), a.to_bits(), "{a:e} predicted by {p:e}");
            }
        }
        assert_eq!(residual(1.0, 1.0), 0);
        assert_eq!(residual(f32::from_bits(1.0f32.to_bits() + 1), 1.0), 2);
        assert_eq!(residual(0.0, -0.0), 2, "-0.0 and +0.0 are adjacent");
    }
}
