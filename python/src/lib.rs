//! The compiled part of the `stickslip` Python package (`stickslip._stickslip`): array
//! and constraint conversion, the solver, and the mapping of the library's errors to
//! Python exceptions. `stickslip/__init__.py` turns SciPy matrices into the arrays these
//! functions take; users call that module, not this one.

use numpy::{PyArray1, PyReadonlyArray1, PyReadonlyArray3};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use serde_json::{json, Value};
use std::sync::Mutex;
use std::time::Instant;
use stickslip::core::constraints::node_rows;
use stickslip::core::sparse::BlockCsr;
use stickslip::gpu::{GpuContext, GpuError, GpuOptions};
use stickslip::io::{bcjson, mtx, one_line};
use stickslip::{
    CoarseSpace, ConstrainedDiagonal, Constraint, Error, InputError, MultilevelSetup, Precision,
    Preconditioner, Problem, SolveDetails, Solver, SolverConfig, SolverKind,
};

pyo3::create_exception!(
    stickslip,
    SolveError,
    PyRuntimeError,
    "The system cannot be solved as posed: H is not positive definite on the free \
     subspace, CG did not reach its tolerance, or f64 overflowed."
);
pyo3::create_exception!(
    stickslip,
    DeviceError,
    PyRuntimeError,
    "The GPU cannot run the solve: no adapter, no SHADER_F64 for f64 or mixed precision, \
     a system larger than the device allows, or a device failure."
);

/// Messages on one line, as the command line prints them.
fn to_py(e: Error) -> PyErr {
    match e {
        Error::Input(e) => PyValueError::new_err(e.to_string()),
        Error::Solve(e) => SolveError::new_err(one_line(&e.to_string(), 2000)),
        Error::Gpu(e) => DeviceError::new_err(one_line(&e.to_string(), 2000)),
    }
}

fn input(file: &str, entry: impl Into<String>, problem: impl Into<String>) -> PyErr {
    to_py(InputError::new(file, entry, problem).into())
}

/// A checked constraint list: from bc.json-style JSON or from the global form B Δx = p.
#[pyclass(frozen, module = "stickslip._stickslip")]
struct Constraints {
    dim: usize,
    list: Vec<Constraint>,
}

#[pymethods]
impl Constraints {
    /// Parses `{"dim": d, "constraints": [...]}` JSON text with the command line's bc.json
    /// reader (messages name `constraints[k].key`).
    #[staticmethod]
    fn from_json(text: &str, dim: usize) -> PyResult<Self> {
        let f = bcjson::parse("constraints", text, Some(dim)).map_err(|e| to_py(e.into()))?;
        Ok(Constraints {
            dim,
            list: f.constraints,
        })
    }

    /// B (m × d·n, as COO arrays, every row on one node) and p (m values), one rows
    /// constraint per row of B, as the command line reads B.mtx and p.mtx (rows named
    /// from 1 in messages).
    #[staticmethod]
    #[pyo3(signature = (rows, cols, vals, nrows, ncols, p, dim, n_nodes))]
    #[allow(clippy::too_many_arguments)]
    fn from_matrix(
        rows: PyReadonlyArray1<'_, i64>,
        cols: PyReadonlyArray1<'_, i64>,
        vals: PyReadonlyArray1<'_, f64>,
        nrows: usize,
        ncols: usize,
        p: Option<PyReadonlyArray1<'_, f64>>,
        dim: usize,
        n_nodes: usize,
    ) -> PyResult<Self> {
        let (rows, cols, vals) = (slice(&rows, "B")?, slice(&cols, "B")?, slice(&vals, "B")?);
        let nd = dim * n_nodes;
        if ncols != nd {
            return Err(input(
                "B",
                "",
                format!("B has {ncols} columns, expected {nd} = {dim} × {n_nodes} nodes"),
            ));
        }
        if rows.len() != cols.len() || rows.len() != vals.len() {
            return Err(input(
                "B",
                "",
                "row, column and value arrays differ in length",
            ));
        }
        let mut entries = Vec::with_capacity(vals.len());
        for ((&r, &c), &v) in rows.iter().zip(cols).zip(vals) {
            // Rows and columns counted from 1, as in B.mtx and the messages below.
            let at = format!("entry ({}, {})", r + 1, c + 1);
            if r < 0 || r as usize >= nrows || c < 0 || c as usize >= ncols {
                return Err(input("B", at, format!("outside B ({nrows} × {ncols})")));
            }
            if !v.is_finite() {
                return Err(input("B", at, format!("value {v} is not finite")));
            }
            entries.push((r as usize, c as usize, v));
        }
        let b = mtx::Coo {
            nrows,
            ncols,
            symmetric: false,
            entries,
            size_line: 0,
        };
        let p = p.as_ref().map(|p| slice(p, "p")).transpose()?;
        let list = bcjson::constraints_from_matrix("B", &b, p.map(|p| ("p", p)), dim, n_nodes)
            .map_err(|e| to_py(e.into()))?;
        Ok(Constraints { dim, list })
    }

    fn __len__(&self) -> usize {
        self.list.len()
    }
}

fn slice<'a, T: numpy::Element>(a: &'a PyReadonlyArray1<'_, T>, what: &str) -> PyResult<&'a [T]> {
    a.as_slice()
        .map_err(|_| input(what, "", "the array is not contiguous"))
}

/// The arrays of H: scalar CSR (i32 or i64 indices) or BSR with d×d blocks.
enum Hessian<'py> {
    Csr32(
        PyReadonlyArray1<'py, i32>,
        PyReadonlyArray1<'py, i32>,
        PyReadonlyArray1<'py, f64>,
    ),
    Csr64(
        PyReadonlyArray1<'py, i64>,
        PyReadonlyArray1<'py, i64>,
        PyReadonlyArray1<'py, f64>,
    ),
    Bsr(
        PyReadonlyArray1<'py, i64>,
        PyReadonlyArray1<'py, i64>,
        PyReadonlyArray3<'py, f64>,
    ),
}

impl<'py> Hessian<'py> {
    fn extract(
        format: &str,
        indptr: &Bound<'py, PyAny>,
        indices: &Bound<'py, PyAny>,
        data: &Bound<'py, PyAny>,
    ) -> PyResult<Self> {
        Ok(match format {
            "csr" => match (indptr.extract(), indices.extract()) {
                (Ok(p), Ok(i)) => Hessian::Csr32(p, i, data.extract()?),
                _ => Hessian::Csr64(indptr.extract()?, indices.extract()?, data.extract()?),
            },
            "bsr" => Hessian::Bsr(indptr.extract()?, indices.extract()?, data.extract()?),
            other => {
                return Err(PyValueError::new_err(format!(
                    "H: unknown array format '{other}' (expected csr or bsr)"
                )))
            }
        })
    }

    /// Slices of the arrays, which stay borrowed (not copied) while the GIL is released.
    fn view(&self) -> PyResult<View<'_>> {
        Ok(match self {
            Hessian::Csr32(p, i, d) => View::Csr32(slice(p, "H")?, slice(i, "H")?, slice(d, "H")?),
            Hessian::Csr64(p, i, d) => View::Csr64(slice(p, "H")?, slice(i, "H")?, slice(d, "H")?),
            Hessian::Bsr(p, i, d) => View::Bsr(
                slice(p, "H")?,
                slice(i, "H")?,
                d.as_slice()
                    .map_err(|_| input("H", "", "the array is not contiguous"))?,
            ),
        })
    }
}

enum View<'a> {
    Csr32(&'a [i32], &'a [i32], &'a [f64]),
    Csr64(&'a [i64], &'a [i64], &'a [f64]),
    Bsr(&'a [i64], &'a [i64], &'a [f64]),
}

impl View<'_> {
    /// The BSR arrays as the solver's block matrix (one copy of the values, in the
    /// layout they already have).
    fn blocks(&self, dim: usize, n: usize) -> Result<Option<BlockCsr>, Error> {
        let View::Bsr(p, i, d) = *self else {
            return Ok(None);
        };
        let index = |what: &str, k: usize, v: i64| {
            usize::try_from(v).map_err(|_| {
                Error::from(InputError::new(
                    "H",
                    format!("{what}[{k}]"),
                    format!("{v} is negative"),
                ))
            })
        };
        let row_ptr = p
            .iter()
            .enumerate()
            .map(|(k, &v)| index("indptr", k, v))
            .collect::<Result<Vec<_>, _>>()?;
        let col_idx = i
            .iter()
            .enumerate()
            .map(|(k, &v)| index("indices", k, v))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Some(BlockCsr {
            dim,
            n,
            row_ptr,
            col_idx,
            values: d.to_vec(),
        }))
    }

    fn build(&self, dim: usize, n: usize, g: &[f64], c: &[Constraint]) -> Result<Problem, Error> {
        match *self {
            View::Csr32(p, i, d) => Problem::from_csr(dim, n, p, i, d, g, c),
            View::Csr64(p, i, d) => Problem::from_csr(dim, n, p, i, d, g, c),
            View::Bsr(..) => match self.blocks(dim, n)? {
                Some(h) => Problem::from_blocks(h, g.to_vec(), c),
                None => unreachable!("a BSR view has blocks"),
            },
        }
    }

    fn update(&self, problem: &mut Problem, g: &[f64]) -> Result<(), Error> {
        match *self {
            View::Csr32(p, i, d) => problem.update_csr_values(p, i, d, g),
            View::Csr64(p, i, d) => problem.update_csr_values(p, i, d, g),
            View::Bsr(..) => match self.blocks(problem.dim(), problem.n_nodes())? {
                Some(h) => problem.update_blocks(h, g),
                None => unreachable!("a BSR view has blocks"),
            },
        }
    }
}

/// Δx, the reactions, and the report as JSON text.
type Answer<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>, String);

struct State {
    solver: Solver,
    /// The last problem and its constraints: a solve with the same constraints updates
    /// its values, keeping its layout (and the solver's analysis or device buffers) while
    /// the pattern is unchanged.
    last: Option<(Vec<Constraint>, Problem)>,
}

/// The default adapter's device, opened by the first GPU solver of the process and
/// shared by the later ones (opening a device costs far more than a small solve).
fn shared_gpu() -> Result<GpuContext, Error> {
    static GPU: Mutex<Option<GpuContext>> = Mutex::new(None);
    let mut slot = GPU
        .lock()
        .map_err(|_| {
            Error::Gpu(GpuError::Poisoned {
                lock: "the shared GPU device",
            })
        })?;
    if let Some(ctx) = slot.as_ref() {
        return Ok(ctx.clone());
    }
    let ctx = GpuContext::new(&GpuOptions::default())
        .map_err(|e| Error::Gpu(e.cannot_start("GPU solver")))?;
    *slot = Some(ctx.clone());
    Ok(ctx)
}

/// A configured solver that keeps what it can reuse between solves.
#[pyclass(frozen, module = "stickslip._stickslip")]
struct Engine {
    state: Mutex<State>,
    preconditioner: Preconditioner,
    coarse: CoarseSpace,
    constrained_diagonal: ConstrainedDiagonal,
    tol: f64,
    max_iters: usize,
}

fn parse<T: std::str::FromStr<Err = String>>(entry: &str, s: &str) -> PyResult<T> {
    s.parse()
        .map_err(|e: String| input("solver config", entry, e))
}

fn diagonal_name(d: ConstrainedDiagonal) -> &'static str {
    match d {
        ConstrainedDiagonal::Identity => "identity",
        ConstrainedDiagonal::Hessian => "hessian",
    }
}

/// max over constraint rows of |aᵀΔx_i − c| / ‖a‖ (report.json's constraint_violation).
fn constraint_violation(dim: usize, cs: &[Constraint], dx: &[f64]) -> f64 {
    let mut worst = 0.0f64;
    for c in cs {
        let (rows, vals) = node_rows(dim, c);
        let xi = &dx[c.node * dim..c.node * dim + dim];
        for (r, v) in rows.iter().zip(vals) {
            let len = r.iter().map(|a| a * a).sum::<f64>().sqrt();
            let s: f64 = r.iter().zip(xi).map(|(a, b)| a * b).sum();
            worst = worst.max((s - v).abs() / len);
        }
    }
    worst
}

#[pymethods]
impl Engine {
    #[new]
    #[pyo3(signature = (solver, precision, tol, max_iters, preconditioner, coarse, error_tol, constrained_diagonal, multilevel_setup))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        solver: &str,
        precision: Option<&str>,
        tol: f64,
        max_iters: usize,
        preconditioner: &str,
        coarse: &str,
        error_tol: Option<f64>,
        constrained_diagonal: &str,
        multilevel_setup: &str,
    ) -> PyResult<Self> {
        let kind: SolverKind = parse("solver", solver)?;
        let precision: Precision = match precision {
            Some(p) => parse("precision", p)?,
            None => Precision::F64,
        };
        let preconditioner: Preconditioner = parse("preconditioner", preconditioner)?;
        let coarse: CoarseSpace = parse("coarse", coarse)?;
        let multilevel_setup: MultilevelSetup = parse("multilevel_setup", multilevel_setup)?;
        let constrained_diagonal = match constrained_diagonal {
            "identity" => ConstrainedDiagonal::Identity,
            "hessian" => ConstrainedDiagonal::Hessian,
            other => {
                return Err(input(
                    "solver config",
                    "constrained_diagonal",
                    format!("unknown value '{other}' (expected identity or hessian)"),
                ))
            }
        };
        let mut config = match kind {
            SolverKind::Cholesky => SolverConfig::cholesky(),
            SolverKind::Cg => SolverConfig::cg(),
            SolverKind::Gpu => SolverConfig::gpu(precision),
        }
        .tol(tol)
        .max_iters(max_iters)
        .preconditioner(preconditioner)
        .coarse(coarse)
        .multilevel_setup(multilevel_setup)
        .constrained_diagonal(constrained_diagonal);
        // Checked by Solver::new: a precision other than f64 needs the gpu solver.
        config.precision = precision;
        config.error_tol = error_tol;
        // Opening a device can take a while: other Python threads run meanwhile.
        let solver = py
            .detach(|| {
                if kind == SolverKind::Gpu {
                    config = config.gpu_context(shared_gpu()?);
                }
                Solver::new(config)
            })
            .map_err(to_py)?;
        Ok(Engine {
            state: Mutex::new(State { solver, last: None }),
            preconditioner,
            coarse,
            constrained_diagonal,
            tol,
            max_iters,
        })
    }

    /// The GPU adapter's name, for the gpu solver.
    fn adapter(&self) -> PyResult<Option<String>> {
        let state = self.lock()?;
        Ok(state.solver.adapter().map(str::to_string))
    }

    /// Solves one system: (dx, reactions, info as JSON text).
    #[pyo3(signature = (format, indptr, indices, data, g, constraints, n_nodes))]
    #[allow(clippy::too_many_arguments)]
    fn solve<'py>(
        &self,
        py: Python<'py>,
        format: &str,
        indptr: &Bound<'py, PyAny>,
        indices: &Bound<'py, PyAny>,
        data: &Bound<'py, PyAny>,
        g: PyReadonlyArray1<'py, f64>,
        constraints: &Constraints,
        n_nodes: usize,
    ) -> PyResult<Answer<'py>> {
        let h = Hessian::extract(format, indptr, indices, data)?;
        let view = h.view()?;
        let g = slice(&g, "g")?;
        let (dx, reactions, info) = py.detach(|| self.run(&view, g, constraints, n_nodes))?;
        Ok((
            PyArray1::from_vec(py, dx),
            PyArray1::from_vec(py, reactions),
            info,
        ))
    }
}

impl Engine {
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, State>> {
        self.state
            .lock()
            .map_err(|_| PyRuntimeError::new_err("the solver failed in another thread"))
    }

    /// Builds or updates the problem and solves it; runs without the GIL.
    fn run(
        &self,
        view: &View<'_>,
        g: &[f64],
        constraints: &Constraints,
        n_nodes: usize,
    ) -> PyResult<(Vec<f64>, Vec<f64>, String)> {
        let t_start = Instant::now();
        let dim = constraints.dim;
        let mut state = self.lock()?;
        let State { solver, last } = &mut *state;
        let same = matches!(last, Some((c, p)) if *c == constraints.list
            && p.dim() == dim && p.n_nodes() == n_nodes);
        let problem = match last {
            Some((_, p)) if same => {
                view.update(p, g).map_err(to_py)?;
                p
            }
            _ => {
                *last = None;
                let p = view
                    .build(dim, n_nodes, g, &constraints.list)
                    .map_err(to_py)?;
                &mut last.insert((constraints.list.clone(), p)).1
            }
        };
        let read = t_start.elapsed().as_secs_f64();
        let sol = solver.solve(problem).map_err(to_py)?;
        let st = &sol.stats;
        let frames = problem.frames();
        let mut info = json!({
            "solver": st.solver.name(),
            "precision": st.precision.to_string(),
            "adapter": st.adapter,
            "iterations": st.iterations,
            "relative_residual": st.relative_residual,
            "reused": st.reused,
            "seconds": {
                "read": read,
                "setup": st.seconds.setup,
                "solve": st.seconds.solve,
                "recover": st.seconds.recover,
                "total": t_start.elapsed().as_secs_f64(),
            },
            "dim": dim,
            "nodes": n_nodes,
            "free_dofs": problem.free_dofs(),
            "constrained_dofs": problem.constrained_dofs(),
            "rotated_nodes": frames.rot_nodes.len(),
            "constraints": problem.constraints().len(),
            "prescribed": !frames.homogeneous,
            "constrained_diagonal": diagonal_name(self.constrained_diagonal),
            "constraint_violation": constraint_violation(dim, problem.constraints(), &sol.dx),
        });
        match &st.details {
            SolveDetails::Cholesky(o) => {
                info["seconds"]["symbolic"] = json!(o.symbolic_seconds);
                info["seconds"]["numeric"] = json!(o.numeric_seconds);
                info["seconds"]["triangular"] = json!(o.solve_seconds);
                info["cholesky"] = json!({
                    "matrix_nnz": o.matrix_nnz,
                    "factor_nnz": o.factor_nnz,
                    "reused_symbolic": o.reused_symbolic,
                    "factor_nnz_exact": o.factor_nnz_exact,
                    "ordering": o.ordering.name(),
                    "ordering_seconds": o.ordering_seconds,
                    "scaled_residual": o.scaled_residual,
                    "refinements": o.refinements,
                    "condition_estimate": o.condition_estimate,
                });
            }
            SolveDetails::Cg(c) => {
                info["cg"] = json!({
                    "preconditioner": self.preconditioner.name(),
                    "coarse": self.coarse.name(),
                    "tol": self.tol,
                    "max_iters": self.max_iters,
                    "restarts": c.restarts,
                    "condition_estimate": c.condition_estimate,
                });
            }
            SolveDetails::Gpu(gi) => {
                info["gpu"] = serde_json::to_value(gi).unwrap_or(Value::Null);
            }
        }
        Ok((sol.dx, sol.reactions, info.to_string()))
    }
}

/// The GPU adapters wgpu sees, as `stickslip info` lists them (JSON text).
#[pyfunction]
fn adapters(py: Python<'_>) -> String {
    let list = py.detach(stickslip::gpu::list_adapters);
    serde_json::to_string(&list).unwrap_or_else(|_| "[]".into())
}

/// The compiled part of the stickslip package; use `import stickslip`.
#[pymodule]
mod _stickslip {
    use pyo3::prelude::*;

    #[pymodule_export]
    use super::{adapters, Constraints, DeviceError, Engine, SolveError};

    #[pymodule_init]
    fn init(m: &Bound<'_, PyModule>) -> PyResult<()> {
        // The package's version (the wheel's, kept equal to the stickslip crate's).
        m.add("__version__", env!("CARGO_PKG_VERSION"))
    }
}
