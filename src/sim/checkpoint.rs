//! Checkpoints of a run: everything the next step depends on, written atomically, so a
//! killed or interrupted `run` continues (`run --resume DIR`) with the same bits as a run
//! that was never stopped.
//!
//! One file, `checkpoint.bin` in the run's folder, replaced atomically (written to a
//! temporary name, then renamed over the previous one, which stays whole until then):
//!
//! ```text
//! magic "stickslip-checkpoint\n" | u64 LE: header length | header (JSON)
//! | the arrays named in the header, f64 little-endian, in order | u64 LE: FNV-1a of all before
//! ```
//!
//! The header holds the format version, the stickslip version, the fingerprint of the
//! resolved scene (every resolved value but the number of steps), the run's identity (an
//! id that its summary.json repeats, and the digest of its steps.csv up to the
//! checkpoint's step: a checkpoint copied into another run's folder does not fit it), the
//! options the run was started with (so a resume rebuilds the same scene and writes the
//! same outputs), the stepper's scalars and the run's tallies. f64 values in the JSON
//! header round-trip exactly.

use crate::error::InputError;
use crate::sim::integrator::{ContactCounters, Snapshot};
use crate::sim::scene::Scene;
use std::path::Path;

/// The file name of a run's checkpoint, in its output folder.
pub const FILE_NAME: &str = "checkpoint.bin";

/// The format this build writes and reads.
pub const FORMAT_VERSION: u32 = 3;

const MAGIC: &[u8] = b"stickslip-checkpoint\n";

/// Largest header accepted (a corrupt length must not make us allocate terabytes).
const MAX_HEADER_BYTES: u64 = 1 << 30;

/// The options a run was started with that shape its scene and its outputs (what
/// `--resume` reuses).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StartOptions {
    /// The scene file (an absolute path, so that a resume from another working directory
    /// finds it) or built-in name.
    pub scene: String,
    pub size: f64,
    pub solver: Option<crate::sim::scene::LinearKind>,
    pub ordering: Option<crate::CholeskyOrdering>,
    pub newton: Option<crate::sim::scene::NewtonLoop>,
    pub cg_tolerance: Option<crate::sim::scene::CgTolerance>,
    /// `--preconditioner` (absent from checkpoints written before the option existed).
    #[serde(default)]
    pub preconditioner: Option<crate::sim::scene::PreconditionerChoice>,
    /// The steps whose Newton systems the run dumps (`--dump-systems`).
    pub dump_systems: Option<crate::sim::integrator::StepSelection>,
}

/// The run's tallies at the checkpoint (what summary.json adds up over the steps).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Tallies {
    pub newton_iterations: usize,
    pub linear_iterations: usize,
    pub linear_seconds: f64,
    /// Systems solved again to the convergence tolerance (inexact Newton).
    #[serde(default)]
    pub linear_resolves: usize,
    /// Newton systems whose multilevel levels were built, and that kept earlier ones.
    #[serde(default)]
    pub multilevel_built: usize,
    #[serde(default)]
    pub multilevel_kept: usize,
    pub frames: usize,
    pub ccd_limited: usize,
    /// Smallest node–obstacle distance over the steps so far (contact scenes).
    pub min_distance: Option<f64>,
    /// (step, k_M) at every step where k_M changed, and the doublings.
    pub k_m_history: Vec<(usize, f64)>,
    pub k_m_doublings: usize,
    pub eliminated_at_iteration: Vec<usize>,
    pub first_step_eliminated_at_start: Option<usize>,
    pub all_eliminated_every_step: bool,
    /// Bytes the device Newton loop moved host → device and back over the run's
    /// invocations so far (zero for the CPU loop).
    pub host_to_device_bytes: u64,
    pub device_to_host_bytes: u64,
    /// Wall time of the run's invocations so far, and of their checkpoint writes.
    pub wall_seconds: f64,
    pub checkpoint_seconds: f64,
    /// Per neo-Hookean law (by its scene name): the steps that ended with an inverted
    /// element.
    #[serde(default)]
    pub inverted_steps: std::collections::BTreeMap<String, usize>,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Header {
    format: u32,
    stickslip: String,
    fingerprint: String,
    /// The run's id (summary.json's `run_id`).
    run_id: String,
    /// The digest of steps.csv's bytes up to the checkpoint's step.
    steps_digest: String,
    options: StartOptions,
    /// Steps the run was asked for.
    steps: usize,
    step: usize,
    t: f64,
    k_m: f64,
    lambda: Vec<[f64; 3]>,
    counters: ContactCounters,
    /// The inexact Newton sequence's memory across steps.
    #[serde(default)]
    forcing_first_step: Option<f64>,
    tallies: Tallies,
    /// (name, length) of the arrays after the header, in order.
    arrays: Vec<(String, usize)>,
}

/// A checkpoint read back.
#[derive(Debug, Clone, PartialEq)]
pub struct Checkpoint {
    pub fingerprint: String,
    pub identity: RunIdentity,
    pub options: StartOptions,
    pub steps: usize,
    pub snapshot: Snapshot,
    pub tallies: Tallies,
}

/// What ties a checkpoint to its run: the run's id, which its summary.json repeats, and
/// the digest of its steps.csv up to the checkpoint's step ([`Fnv::hex`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunIdentity {
    pub run_id: String,
    pub steps_digest: String,
}

/// FNV-1a, 64 bits: the checksum of the file, the scene's fingerprint (its bulk arrays
/// word by word, [`Fnv::update_words`]) and the digest of steps.csv.
#[derive(Debug, Clone, Copy)]
pub struct Fnv(u64);

/// The 64-bit FNV prime.
const FNV_PRIME: u64 = 0x0000_0100_0000_01b3;

impl Default for Fnv {
    fn default() -> Self {
        Self::new()
    }
}

impl Fnv {
    pub fn new() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    /// The digest so far, as 16 hex digits.
    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
    pub fn update(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= b as u64;
            self.0 = self.0.wrapping_mul(FNV_PRIME);
        }
    }

    /// Folds `bytes` in as 8-byte little-endian words (a trailing part word byte by byte,
    /// as [`Fnv::update`]): an eighth of the multiplications, for the bulk arrays of a
    /// fingerprint. Each word is xor-ed in, multiplied by the FNV prime and rotated: the
    /// multiplication carries a difference only upwards, the rotation brings the high bits
    /// (an f64's sign and exponent) down into what later words multiply.
    pub fn update_words(&mut self, bytes: &[u8]) {
        let mut words = bytes.chunks_exact(8);
        for w in &mut words {
            let mut word = [0u8; 8];
            word.copy_from_slice(w);
            self.0 = (self.0 ^ u64::from_le_bytes(word))
                .wrapping_mul(FNV_PRIME)
                .rotate_left(23);
        }
        self.update(words.remainder());
    }
}

impl std::fmt::Write for Fnv {
    fn write_str(&mut self, s: &str) -> std::fmt::Result {
        self.update(s.as_bytes());
        Ok(())
    }
}

/// The fingerprint of a resolved scene: every value the run depends on except the number
/// of steps (a resume may go further than the run was first asked to). Settings by their
/// Debug text, arrays (positions, velocities, cells, the model) by their values' bits.
pub fn fingerprint(scene: &Scene) -> String {
    use crate::sim::energy::{digest_f64s, digest_usizes};
    use std::fmt::Write as _;
    let mut h = Fnv::new();
    let s = scene;
    // Debug prints every f64 in its shortest round-trip form: equal values, equal text.
    let _ = write!(
        h,
        "{:?}|{}|{:?}|{:?}|{:?}|{:?}|",
        s.name, s.dim, s.time_step, s.output, s.solver, s.moving
    );
    let mut out = |b: &[u8]| h.update_words(b);
    s.model.digest(&mut out);
    digest_f64s(&mut out, &s.x0);
    digest_f64s(&mut out, &s.v0);
    // Each array after its length: no two different splits give the same bytes.
    for c in &s.cells {
        out(&[c.kind.vtk_type()]);
        digest_usizes(&mut out, &[c.nodes.len()]);
        digest_usizes(&mut out, &c.nodes);
    }
    digest_usizes(&mut out, &[s.contact_weight.len()]);
    digest_f64s(&mut out, &s.contact_weight);
    let _ = write!(
        h,
        "|{:?}|{:?}|{:?}|{:?}",
        s.bcs, s.characteristic_length, s.gravity, s.obstacles
    );
    format!("{:016x}", h.0)
}

/// A new run's id: distinct for runs started at different times or by different
/// processes (the time in nanoseconds and the process id, digested).
pub fn new_run_id(fingerprint: &str) -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let mut h = Fnv::new();
    h.update(&nanos.to_le_bytes());
    h.update(&std::process::id().to_le_bytes());
    h.update(fingerprint.as_bytes());
    h.hex()
}

/// Writes the checkpoint of `snap` into `dir` atomically.
pub fn write(
    dir: &Path,
    fingerprint: &str,
    identity: &RunIdentity,
    options: &StartOptions,
    steps: usize,
    snap: &Snapshot,
    tallies: &Tallies,
) -> std::io::Result<()> {
    let arrays: [(&str, &[f64]); 4] = [
        ("x", &snap.x),
        ("v", &snap.v),
        ("reactions", &snap.reactions),
        ("contact_forces", &snap.contact_forces),
    ];
    let header = Header {
        format: FORMAT_VERSION,
        stickslip: env!("CARGO_PKG_VERSION").to_string(),
        fingerprint: fingerprint.to_string(),
        run_id: identity.run_id.clone(),
        steps_digest: identity.steps_digest.clone(),
        options: options.clone(),
        steps,
        step: snap.step,
        t: snap.t,
        k_m: snap.k_m,
        lambda: snap.lambda.clone(),
        counters: snap.counters,
        forcing_first_step: snap.forcing_first_step,
        tallies: tallies.clone(),
        arrays: arrays
            .iter()
            .map(|(n, a)| (n.to_string(), a.len()))
            .collect(),
    };
    let json = serde_json::to_vec(&header).map_err(std::io::Error::other)?;
    let len: usize = arrays.iter().map(|(_, a)| a.len()).sum();
    let mut bytes = Vec::with_capacity(MAGIC.len() + 16 + json.len() + 8 * len);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&(json.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&json);
    for (_, a) in arrays {
        for v in a {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    let mut sum = Fnv::new();
    sum.update(&bytes);
    bytes.extend_from_slice(&sum.0.to_le_bytes());
    crate::io::files::write_atomic_bytes(dir.join(FILE_NAME), &bytes)
}

/// Reads the checkpoint in `dir`. Every fault is one line naming the file: no
/// checkpoint, not a checkpoint, truncated or corrupt (checksum), another format version.
pub fn read(dir: &Path) -> Result<Checkpoint, InputError> {
    let path = dir.join(FILE_NAME);
    let shown = path.display().to_string();
    let fail = |problem: String| InputError::new(&shown, "", problem);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(fail(
                "no checkpoint here: this folder holds no run that can be resumed".into(),
            ))
        }
        Err(e) => return Err(fail(format!("cannot be read: {e}"))),
    };
    if !bytes.starts_with(MAGIC) {
        return Err(fail("is not a stickslip checkpoint".into()));
    }
    let corrupt = || fail("is truncated or corrupt (its checksum does not match)".into());
    if bytes.len() < MAGIC.len() + 16 {
        return Err(corrupt());
    }
    let (body, tail) = bytes.split_at(bytes.len() - 8);
    let mut sum = Fnv::new();
    sum.update(body);
    if sum.0.to_le_bytes() != tail {
        return Err(corrupt());
    }
    let mut at = MAGIC.len();
    let hlen = u64::from_le_bytes(body[at..at + 8].try_into().map_err(|_| corrupt())?);
    at += 8;
    if hlen > MAX_HEADER_BYTES || at as u64 + hlen > body.len() as u64 {
        return Err(corrupt());
    }
    let hjson = &body[at..at + hlen as usize];
    at += hlen as usize;
    // The format version first, so that a future header still says which version it is.
    let version: serde_json::Value = serde_json::from_slice(hjson).map_err(|_| corrupt())?;
    let format = version.get("format").and_then(|f| f.as_u64());
    if format != Some(FORMAT_VERSION as u64) {
        return Err(fail(format!(
            "was written in checkpoint format {}, this stickslip ({}) reads format {FORMAT_VERSION}",
            format.map_or("unknown".to_string(), |f| f.to_string()),
            env!("CARGO_PKG_VERSION")
        )));
    }
    let header: Header = serde_json::from_value(version)
        .map_err(|e| fail(format!("has a header this stickslip cannot read: {e}")))?;
    let mut arrays = Vec::new();
    for (name, len) in &header.arrays {
        let end = len
            .checked_mul(8)
            .and_then(|b| b.checked_add(at))
            .filter(|&e| e <= body.len())
            .ok_or_else(corrupt)?;
        let a: Vec<f64> = body[at..end]
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect();
        at = end;
        arrays.push((name.as_str(), a));
    }
    if at != body.len() {
        return Err(corrupt());
    }
    let mut take = |name: &str| -> Result<Vec<f64>, InputError> {
        let k = arrays
            .iter()
            .position(|(n, _)| *n == name)
            .ok_or_else(|| fail(format!("holds no array '{name}'")))?;
        Ok(std::mem::take(&mut arrays[k].1))
    };
    let snapshot = Snapshot {
        step: header.step,
        t: header.t,
        x: take("x")?,
        v: take("v")?,
        k_m: header.k_m,
        lambda: header.lambda,
        reactions: take("reactions")?,
        contact_forces: take("contact_forces")?,
        counters: header.counters,
        forcing_first_step: header.forcing_first_step,
    };
    Ok(Checkpoint {
        fingerprint: header.fingerprint,
        identity: RunIdentity {
            run_id: header.run_id,
            steps_digest: header.steps_digest,
        },
        options: header.options,
        steps: header.steps,
        snapshot,
        tallies: header.tallies,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn snap() -> Snapshot {
        Snapshot {
            step: 7,
            t: 0.1 + 0.2,
            x: vec![1.0, -0.0, f64::MIN_POSITIVE, 1e300],
            v: vec![0.1, 0.2, 0.3, 1.0 / 3.0],
            k_m: 1e3,
            lambda: vec![[0.5, -1e-300, 3.0]],
            reactions: vec![0.0; 4],
            contact_forces: Vec::new(),
            counters: ContactCounters {
                barrier_evaluations: 3,
                ccd_calls: 2,
                pushed_nodes: 1,
            },
            forcing_first_step: Some(1.0 / 7.0),
        }
    }

    fn options() -> StartOptions {
        StartOptions {
            scene: "twist".into(),
            size: 1.0,
            solver: Some(crate::sim::scene::LinearKind::Cg),
            ordering: None,
            newton: None,
            cg_tolerance: None,
            preconditioner: None,
            dump_systems: Some(crate::sim::integrator::StepSelection::All),
        }
    }

    fn identity() -> RunIdentity {
        RunIdentity {
            run_id: "0123456789abcdef".into(),
            steps_digest: "fedcba9876543210".into(),
        }
    }

    fn tmp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("stickslip-ckpt-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("temp dir");
        d
    }

    /// The fingerprint is the same for a scene built twice, and changes with one bit of a
    /// position, one node of a cell or one bit of a node's mass.
    #[test]
    fn the_fingerprint_follows_every_array_of_the_scene() {
        let text = crate::sim::scene::BUILTIN
            .iter()
            .find(|(n, _)| *n == "twist")
            .map(|(_, t)| *t)
            .expect("the twist scene");
        let scene = || crate::sim::scene::parse(text, "twist", 1.0).expect("twist parses");
        let base = fingerprint(&scene());
        assert_eq!(fingerprint(&scene()), base);
        let mut moved = scene();
        moved.x0[7] = f64::from_bits(moved.x0[7].to_bits() + 1);
        let mut recut = scene();
        recut.cells[0].nodes.swap(0, 1);
        let mut softer = scene();
        let n = softer.model.n_nodes;
        softer.model.mass[n - 1] *= 1.0 + f64::EPSILON;
        for (what, s) in [("position", moved), ("cell", recut), ("mass", softer)] {
            assert_ne!(fingerprint(&s), base, "{what}");
        }
    }

    #[test]
    fn a_checkpoint_reads_back_to_the_bit() {
        let d = tmp("roundtrip");
        let tallies = Tallies {
            linear_seconds: 0.1 + 0.7,
            min_distance: Some(1e-9 / 3.0),
            ..Tallies::default()
        };
        write(&d, "abc", &identity(), &options(), 20, &snap(), &tallies).expect("write");
        let c = read(&d).expect("read");
        assert_eq!(c.snapshot, snap());
        assert_eq!(c.tallies, tallies);
        assert_eq!((c.fingerprint.as_str(), c.steps), ("abc", 20));
        assert_eq!(c.options, options());
        assert_eq!(c.identity, identity());
        // Bitwise, -0.0 included (PartialEq would take 0.0 for it).
        assert_eq!(c.snapshot.x[1].to_bits(), (-0.0f64).to_bits());
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn truncated_corrupt_foreign_and_missing_checkpoints_are_one_line_errors() {
        let d = tmp("faults");
        let e = read(&d).expect_err("none");
        assert!(e.to_string().contains("no checkpoint here"), "{e}");
        write(
            &d,
            "abc",
            &identity(),
            &options(),
            20,
            &snap(),
            &Tallies::default(),
        )
        .expect("write");
        let p = d.join(FILE_NAME);
        let good = std::fs::read(&p).expect("bytes");
        for (what, bytes) in [
            ("truncated", good[..good.len() / 2].to_vec()),
            ("one bit", {
                let mut b = good.clone();
                let k = b.len() - 20;
                b[k] ^= 1;
                b
            }),
            ("empty", Vec::new()),
        ] {
            std::fs::write(&p, &bytes).expect("write");
            let e = read(&d).expect_err(what).to_string();
            assert!(!e.contains('\n'), "{e}");
            assert!(
                e.contains("truncated or corrupt") || e.contains("not a stickslip checkpoint"),
                "{what}: {e}"
            );
        }
        // Another format version, with a valid checksum.
        let mut b = good.clone();
        let key = format!("\"format\":{FORMAT_VERSION}");
        let key = key.as_bytes();
        let k = b
            .windows(key.len())
            .position(|w| w == key)
            .expect("the header names its format");
        b[k + key.len() - 1] = b'9';
        b.truncate(b.len() - 8);
        let mut sum = Fnv::new();
        sum.update(&b);
        b.extend_from_slice(&sum.0.to_le_bytes());
        std::fs::write(&p, &b).expect("write");
        let e = read(&d).expect_err("version").to_string();
        assert!(e.contains("checkpoint format 9"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }
}
