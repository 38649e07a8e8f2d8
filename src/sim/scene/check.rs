//! Checks of a scene file's values, each error naming the file and the key path.

use crate::core::constraints::MIN_LENGTH;
use crate::core::linalg::norm2;
use crate::error::InputError;

pub(super) struct Ctx<'a> {
    pub(super) file: &'a str,
}

impl Ctx<'_> {
    pub(super) fn err(&self, key: impl Into<String>, problem: impl Into<String>) -> InputError {
        InputError::new(self.file, key, problem)
    }

    pub(super) fn positive(&self, key: &str, v: f64) -> Result<f64, InputError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(self.err(key, format!("must be positive and finite, got {v}")))
        }
    }

    pub(super) fn vector(&self, key: &str, v: &[f64], dim: usize) -> Result<[f64; 3], InputError> {
        if v.len() != dim {
            return Err(self.err(key, format!("must have {dim} components, got {}", v.len())));
        }
        let mut out = [0.0; 3];
        for (a, &x) in v.iter().enumerate() {
            if !x.is_finite() {
                return Err(self.err(format!("{key}[{a}]"), "must be finite"));
            }
            out[a] = x;
        }
        Ok(out)
    }

    /// The vector scaled to unit length. Its length (computed scaled, so entries near
    /// 1e±200 neither overflow nor underflow) must be finite and at least
    /// [`MIN_LENGTH`]: a subnormal length has lost its digits.
    pub(super) fn unit(&self, key: &str, v: &[f64], dim: usize) -> Result<[f64; 3], InputError> {
        let mut u = self.vector(key, v, dim)?;
        let n = self.length(key, &u[..dim])?;
        for x in u.iter_mut() {
            *x /= n;
        }
        Ok(u)
    }

    /// The (scaled) length of a vector that is to be normalized: finite and at least
    /// [`MIN_LENGTH`], else an error on `key`.
    pub(super) fn length(&self, key: &str, v: &[f64]) -> Result<f64, InputError> {
        let n = norm2(v);
        if n == 0.0 {
            return Err(self.err(key, "must be a nonzero vector"));
        }
        if !n.is_finite() || n < MIN_LENGTH {
            return Err(self.err(
                key,
                format!(
                    "must be a nonzero vector of length between {MIN_LENGTH:.1e} and the largest f64, got length {n:e}"
                ),
            ));
        }
        Ok(n)
    }

    /// `offset / len` (a plane's offset along its unit normal), which must be finite.
    pub(super) fn along(&self, key: &str, offset: f64, len: f64) -> Result<f64, InputError> {
        if !offset.is_finite() {
            return Err(self.err(key, "must be finite"));
        }
        let a = offset / len;
        if !a.is_finite() {
            return Err(self.err(
                key,
                format!("offset / |normal| = {offset:e} / {len:e} overflows f64"),
            ));
        }
        Ok(a)
    }
}
