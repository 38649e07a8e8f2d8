//! Simulation output: VTK legacy ASCII frames (ParaView), `steps.csv`, `summary.json`.
//!
//! steps.csv, one row per step (row 0 is the initial state, with zero iteration counts and
//! zero reaction):
//! `step,time,newton_iterations,linear_iterations,linear_seconds,energy,com_x,com_y[,com_z],
//! p_x,p_y[,p_z],f_x,f_y[,f_z]`; for scenes with obstacles `,min_distance,c_x,c_y[,c_z]`;
//! for scenes with moving conditions, `,k_m,eliminated_at_iteration`; for scenes with
//! neo-Hookean (solid) bodies, `,min_j`: the smallest element volume ratio J = det F of the
//! step's end state (row 0: of the initial state), ≤ 0 when an element is inverted; then,
//! always, `,cg_tol_loosest,cg_tol_tightest,linear_resolves`: the loosest and tightest
//! relative residual tolerance of the step's iterative solves (0 for direct solves;
//! see `[solver] cg_tolerance`) and the systems solved again to the convergence tolerance.
//! `min_distance` is the smallest signed distance of any node to any obstacle over every
//! Newton iterate of the step (row 0: at t = 0) and `c` the summed contact force (newtons,
//! −∇P_b, an external force apart from the reactions `f`). `energy` is the mechanical energy (kinetic + elastic +
//! gravitational, joules); `f` is the summed reaction force in newtons (the constrained
//! components of −∇E / h², see [`crate::sim::integrator`]); `linear_iterations` counts CG
//! iterations, one per direct solve; `k_m` is the penalty stiffness at the end of the step
//! and `eliminated_at_iteration` the Newton iteration at which the last moving node was
//! snapped and eliminated (0: at the start of the step). Numbers are written with 17
//! significant digits so differences of momenta keep their precision.

use crate::sim::checkpoint::Fnv;
use crate::sim::scene::Scene;
use std::fmt::Write as _;
use std::fs::File;
use std::io::Write;
use std::path::Path;

/// One VTK legacy ASCII unstructured grid: points, cells, point data (velocity,
/// reaction_force, and contact_force when `c` is given). 2D scenes are written with z = 0.
pub fn write_vtk(
    path: &Path,
    scene: &Scene,
    title: &str,
    x: &[f64],
    v: &[f64],
    f: &[f64],
    c: Option<&[f64]>,
) -> std::io::Result<()> {
    let d = scene.dim;
    let n = x.len() / d;
    // Each section is formatted (in parallel chunks) and written before the next, so a
    // frame never holds more than one section's text in memory.
    crate::io::files::write_atomic(path, |w| {
        let mut s = String::new();
        let _ = writeln!(s, "# vtk DataFile Version 3.0");
        let _ = writeln!(s, "{}", title.replace('\n', " "));
        let _ = writeln!(s, "ASCII\nDATASET UNSTRUCTURED_GRID");
        let _ = writeln!(s, "POINTS {n} double");
        w.write_all(s.as_bytes())?;
        let vectors = |w: &mut dyn Write, a: &[f64]| {
            par_lines(w, n, |s, i| {
                let z = if d == 3 { a[i * 3 + 2] } else { 0.0 };
                let _ = writeln!(s, "{:e} {:e} {:e}", a[i * d], a[i * d + 1], z);
            })
        };
        vectors(w, x)?;
        let ncells: usize = scene.cells.iter().map(|b| b.len()).sum();
        let size: usize = scene
            .cells
            .iter()
            .map(|b| b.len() * (b.kind.nodes() + 1))
            .sum();
        writeln!(w, "CELLS {ncells} {size}")?;
        for b in &scene.cells {
            let k = b.kind.nodes();
            par_lines(w, b.len(), |s, e| {
                let c = &b.nodes[e * k..(e + 1) * k];
                let _ = write!(s, "{}", c.len());
                for i in c {
                    let _ = write!(s, " {i}");
                }
                s.push('\n');
            })?;
        }
        writeln!(w, "CELL_TYPES {ncells}")?;
        for b in &scene.cells {
            let line = format!("{}\n", b.kind.vtk_type());
            w.write_all(line.repeat(b.len()).as_bytes())?;
        }
        writeln!(w, "POINT_DATA {n}")?;
        writeln!(w, "VECTORS velocity double")?;
        vectors(w, v)?;
        writeln!(w, "VECTORS reaction_force double")?;
        vectors(w, f)?;
        if let Some(c) = c {
            writeln!(w, "VECTORS contact_force double")?;
            vectors(w, c)?;
        }
        Ok(())
    })
}

/// Lines per task of [`par_lines`]: enough to amortise a task, few enough to share.
const LINES_PER_TASK: usize = 8192;

/// Writes the lines `line(·, i)` for i in 0..n to `w`, in order: formatted in parallel
/// chunks (float formatting is most of a frame's cost) and written in order, so the text
/// is the same on any number of threads.
fn par_lines(
    w: &mut dyn Write,
    n: usize,
    line: impl Fn(&mut String, usize) + Sync,
) -> std::io::Result<()> {
    use rayon::prelude::*;
    let chunks: Vec<String> = (0..n.div_ceil(LINES_PER_TASK))
        .into_par_iter()
        .map(|c| {
            let mut t = String::with_capacity(64 * LINES_PER_TASK);
            for i in c * LINES_PER_TASK..((c + 1) * LINES_PER_TASK).min(n) {
                line(&mut t, i);
            }
            t
        })
        .collect();
    chunks.iter().try_for_each(|t| w.write_all(t.as_bytes()))
}

/// The ParaView collection of a run's frames, in its output folder: each frame with its
/// simulated time, so that ParaView's time slider shows seconds.
pub const FRAMES_COLLECTION: &str = "frames.pvd";

/// Writes a ParaView collection (PVD) of `frames`: (file relative to the collection,
/// simulated time in seconds), each time in its shortest round-trip form.
pub fn write_pvd(w: &mut impl Write, frames: &[(String, f64)]) -> std::io::Result<()> {
    let mut s = String::from(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n  <Collection>\n",
    );
    for (file, t) in frames {
        let file = file
            .replace('&', "&amp;")
            .replace('"', "&quot;")
            .replace('<', "&lt;");
        let _ = writeln!(s, "    <DataSet timestep=\"{t:?}\" file=\"{file}\"/>");
    }
    s.push_str("  </Collection>\n</VTKFile>\n");
    w.write_all(s.as_bytes())
}

/// The simulated time in a frame's title line (`stickslip NAME step S t = T`, the second
/// line of the file), None when it has none.
pub fn frame_time(path: &Path) -> Option<f64> {
    use std::io::BufRead as _;
    let f = File::open(path).ok()?;
    let title = std::io::BufReader::new(f).lines().nth(1)?.ok()?;
    title.rsplit_once(" t = ")?.1.trim().parse().ok()
}

/// One row of steps.csv.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct StepRecord {
    pub step: usize,
    pub time: f64,
    pub newton_iterations: usize,
    pub linear_iterations: usize,
    pub linear_seconds: f64,
    /// The loosest and tightest CG tolerance of the step's solves (None: direct only).
    pub cg_tol_loosest: Option<f64>,
    pub cg_tol_tightest: Option<f64>,
    /// Systems solved again to the convergence tolerance in the step.
    pub linear_resolves: usize,
    pub energy: f64,
    pub com: Vec<f64>,
    pub momentum: Vec<f64>,
    pub reaction: Vec<f64>,
    pub k_m: f64,
    pub eliminated_at_iteration: Option<usize>,
    /// Contact only: smallest node–obstacle signed distance over the step's iterates.
    pub min_distance: Option<f64>,
    /// Summed contact force (empty without obstacles).
    pub contact: Vec<f64>,
    /// Largest gᵀΔx over the step's line-searched Newton iterates (None: no line search).
    pub max_slope: Option<f64>,
    /// Line-searched iterates whose step was not a descent direction.
    pub ascent_directions: usize,
    /// Solid bodies only: the smallest element volume ratio J of the state.
    pub min_j: Option<f64>,
    /// The step's end iterate: its largest unbalanced free force over its force scale
    /// (None: row 0).
    pub force_residual: Option<f64>,
}

/// The steps.csv writer: unbuffered, one `write` per row, so a killed run leaves every
/// completed step on disk and no partial row. It keeps the digest of the bytes written
/// (the file's, from its first byte), which a checkpoint records as the run's identity.
pub struct StepsCsv {
    w: File,
    moving: bool,
    contact: bool,
    solid: bool,
    digest: Fnv,
}

impl StepsCsv {
    pub fn create(
        path: &Path,
        dim: usize,
        moving: bool,
        contact: bool,
        solid: bool,
    ) -> std::io::Result<Self> {
        let mut w = File::create(path)?;
        let axes = &["x", "y", "z"][..dim];
        let mut h =
            String::from("step,time,newton_iterations,linear_iterations,linear_seconds,energy");
        for pre in ["com", "p", "f"] {
            for a in axes {
                let _ = write!(h, ",{pre}_{a}");
            }
        }
        if contact {
            h.push_str(",min_distance");
            for a in axes {
                let _ = write!(h, ",c_{a}");
            }
        }
        if moving {
            h.push_str(",k_m,eliminated_at_iteration");
        }
        if solid {
            h.push_str(",min_j");
        }
        h.push_str(",cg_tol_loosest,cg_tol_tightest,linear_resolves,force_residual");
        h.push('\n');
        w.write_all(h.as_bytes())?;
        let mut digest = Fnv::new();
        digest.update(h.as_bytes());
        Ok(StepsCsv {
            w,
            moving,
            contact,
            solid,
            digest,
        })
    }

    /// Continues a steps.csv that holds the header and the rows so far (a resumed run),
    /// its whole text read back for the digest.
    pub fn append(path: &Path, moving: bool, contact: bool, solid: bool) -> std::io::Result<Self> {
        let mut digest = Fnv::new();
        digest.update(&std::fs::read(path)?);
        let w = std::fs::OpenOptions::new().append(true).open(path)?;
        Ok(StepsCsv {
            w,
            moving,
            contact,
            solid,
            digest,
        })
    }

    /// The digest of the file's bytes so far.
    pub fn digest(&self) -> String {
        self.digest.hex()
    }

    pub fn row(&mut self, r: &StepRecord) -> std::io::Result<()> {
        let mut s = format!(
            "{},{:.17e},{},{},{:.6e},{:.17e}",
            r.step, r.time, r.newton_iterations, r.linear_iterations, r.linear_seconds, r.energy
        );
        for v in r.com.iter().chain(&r.momentum).chain(&r.reaction) {
            let _ = write!(s, ",{v:.17e}");
        }
        if self.contact {
            let _ = write!(s, ",{:.17e}", r.min_distance.unwrap_or(f64::NAN));
            for v in &r.contact {
                let _ = write!(s, ",{v:.17e}");
            }
        }
        if self.moving {
            let _ = write!(s, ",{:e},", r.k_m);
            if let Some(k) = r.eliminated_at_iteration {
                let _ = write!(s, "{k}");
            }
        }
        if self.solid {
            let _ = write!(s, ",{:.17e}", r.min_j.unwrap_or(f64::NAN));
        }
        // 0 where the step made no iterative solve (row 0, a direct solver): every field
        // stays a finite number.
        for t in [r.cg_tol_loosest, r.cg_tol_tightest] {
            let _ = write!(s, ",{:.6e}", t.unwrap_or(0.0));
        }
        let _ = write!(s, ",{}", r.linear_resolves);
        let _ = write!(s, ",{:.3e}", r.force_residual.unwrap_or(0.0));
        s.push('\n');
        self.w.write_all(s.as_bytes())?;
        self.digest.update(s.as_bytes());
        Ok(())
    }

    pub fn finish(mut self) -> std::io::Result<()> {
        self.w.flush()
    }
}

/// The digest of a steps.csv's text, as [`StepsCsv::digest`] gives it.
pub fn steps_digest(text: &str) -> String {
    let mut d = Fnv::new();
    d.update(text.as_bytes());
    d.hex()
}

/// The header and the whole rows of a steps.csv up to step `last` (rows after it, and a
/// partial row that a killed run or a full disk left, are dropped); None when the row of
/// step `last` is missing.
pub fn rows_up_to(text: &str, last: usize) -> Option<String> {
    let mut lines = text.split_inclusive('\n');
    let header = lines.next().filter(|h| h.ends_with('\n'))?;
    let columns = header.split(',').count();
    let mut out = String::from(header);
    let mut reached = false;
    for line in lines {
        if !line.ends_with('\n') || line.split(',').count() != columns {
            break;
        }
        let step: usize = line.split(',').next()?.parse().ok()?;
        if step > last {
            break;
        }
        reached |= step == last;
        out.push_str(line);
    }
    reached.then_some(out)
}

#[cfg(test)]
mod resume_tests {
    use super::rows_up_to;

    /// Rows after the checkpoint's step and a partial last row go; a missing row of the
    /// checkpoint's step is None.
    #[test]
    fn rows_up_to_keeps_whole_rows_to_the_step() {
        let csv = "step,time\n0,0.0\n1,0.1\n2,0.2\n3,0.";
        assert_eq!(
            rows_up_to(csv, 1).as_deref(),
            Some("step,time\n0,0.0\n1,0.1\n")
        );
        assert_eq!(
            rows_up_to(csv, 2).as_deref(),
            Some("step,time\n0,0.0\n1,0.1\n2,0.2\n")
        );
        assert_eq!(rows_up_to(csv, 3), None, "step 3's row is partial");
        assert_eq!(rows_up_to("step,time\n0,0.0\n2,0.", 1), None);
        assert_eq!(rows_up_to("step,ti", 0), None);
    }
}
