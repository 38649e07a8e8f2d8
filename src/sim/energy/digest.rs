//! Arrays fed to a digest as the bytes of their values' bits: a run's fingerprint
//! ([`crate::sim::checkpoint::fingerprint`]) without formatting a number.

/// Feeds `v` to `out` as the little-endian bytes of each value's bits (a digest's input:
/// equal values, equal bytes; no formatting).
pub fn digest_f64s(out: &mut dyn FnMut(&[u8]), v: &[f64]) {
    let mut buf = [0u8; 8 * 256];
    for chunk in v.chunks(256) {
        for (b, x) in buf.chunks_exact_mut(8).zip(chunk) {
            b.copy_from_slice(&x.to_bits().to_le_bytes());
        }
        out(&buf[..8 * chunk.len()]);
    }
}

/// [`digest_f64s`] for indices (as u64).
pub fn digest_usizes(out: &mut dyn FnMut(&[u8]), v: &[usize]) {
    let mut buf = [0u8; 8 * 256];
    for chunk in v.chunks(256) {
        for (b, &x) in buf.chunks_exact_mut(8).zip(chunk) {
            b.copy_from_slice(&(x as u64).to_le_bytes());
        }
        out(&buf[..8 * chunk.len()]);
    }
}
