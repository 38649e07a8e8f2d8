//! The device-side objects of the solver and their construction: the operator Ĥ in one
//! scalar type (`Operator`), a CG level (`Level`: its buffers `CgBuffers` and compiled
//! kernels `CgKernels`), mixed precision's f64 outer loop (`Refine`), the kernel
//! specialization constants (`Consts`) and the bytes one CG iteration moves.

use super::builder::{plane_buffers, plane_widths, Bound, Builder, Kernel, Real, Shared, STORAGE};
use super::host::{Host, HostOp};
use crate::cg::Preconditioner;
use crate::gpu::kernels::{self, slots};
use crate::gpu::{GpuContext, GpuError, MAX_WORKGROUPS};

/// Length of the CG's scalars before the coefficient history (see cg.wgsl).
pub(super) const N_SCAL: usize = slots::SCAL_HIST as usize;
/// Length of the CG's state array.
pub(super) const N_STATE: usize = slots::N_STATE as usize;
/// Lanczos coefficients (α, β pairs) recorded per CG run after the scalars (cg.wgsl).
pub(super) const LANCZOS_HIST: usize = 1024;
/// Length of the `scal` array: the scalars, then the coefficient history.
pub(super) const SCAL_LEN: usize = N_SCAL + 2 * LANCZOS_HIST;

/// The specialization constants of the kernels (WGSL overrides), fixed per solver.
#[derive(Clone, Copy)]
pub(super) struct Consts {
    pub(super) d: f64,
    pub(super) wg: f64,
    pub(super) masked: bool,
    pub(super) rotated: bool,
    pub(super) precond: f64,
    /// Coarse correction on the rigid translations in every CG level (fused into the
    /// CG reductions).
    pub(super) coarse: bool,
    /// Coarse correction on the translations of this many aggregates (coarse.wgsl); 0: off.
    pub(super) agg: u32,
    /// Difference form of f32 block operators.
    pub(super) diff: bool,
}

pub(super) enum OpData {
    Blocks {
        /// Block planes (see `plane_widths`).
        blocks: [wgpu::Buffer; 3],
        /// Ĥ_ij = V_iᵀ H_ij V_j in place on the planes (slip nodes only).
        rotate: Option<Bound>,
    },
    Springs {
        pos: wgpu::Buffer,
        springs: wgpu::Buffer,
        mass: wgpu::Buffer,
        /// Host-rotated diagonal blocks of VᵀHV (as planes), for the preconditioner build.
        diag_blocks: [wgpu::Buffer; 3],
    },
}

/// Ĥ in one scalar type.
pub(super) struct Operator {
    pub(super) real: Real,
    pub(super) data: OpData,
    pub(super) dvals: Option<wgpu::Buffer>,
    pub(super) rotations: Option<wgpu::Buffer>,
    /// Difference form (f32 blocks): S_i = Σ_j Ĥ_ij per node, d·d row-major.
    pub(super) rowsum: Option<wgpu::Buffer>,
    pub(super) matvec: Kernel,
}

/// The vectors, partial sums and scalars of one CG.
pub(super) struct CgBuffers {
    pub(super) x: wgpu::Buffer,
    pub(super) r: wgpu::Buffer,
    pub(super) z: wgpu::Buffer,
    pub(super) p: wgpu::Buffer,
    pub(super) q: wgpu::Buffer,
    pub(super) b: wgpu::Buffer,
    /// The preconditioner's data (none without one).
    pub(super) minv: Option<wgpu::Buffer>,
    pub(super) partials: wgpu::Buffer,
    pub(super) scal: wgpu::Buffer,
    pub(super) state: wgpu::Buffer,
    /// Coarse correction: E⁺ (k×k, accumulator type) of this level's operator.
    pub(super) einv: Option<wgpu::Buffer>,
    /// Aggregate coarse correction: w = Zᵀr and c = E⁺w.
    pub(super) wc: Option<wgpu::Buffer>,
    pub(super) status_staging: wgpu::Buffer,
}

/// The aggregate coarse correction's kernels (coarse.wgsl) and their bind group.
pub(super) struct AggKernels {
    pub(super) restrict: Kernel,
    pub(super) solve: Kernel,
    pub(super) group: wgpu::BindGroup,
}

/// The compiled kernels of one CG with their bind groups, built once per solver.
pub(super) struct CgKernels {
    pub(super) update_p: Kernel,
    pub(super) update_xrz: Kernel,
    pub(super) init: Kernel,
    /// The bind group of the three kernels above (cg.wgsl).
    pub(super) cg_group: wgpu::BindGroup,
    /// The operator's kernel bound to p → q and to x → q.
    pub(super) matvec_p: wgpu::BindGroup,
    pub(super) matvec_x: wgpu::BindGroup,
    pub(super) agg: Option<AggKernels>,
    pub(super) precond: Option<Bound>,
}

/// One CG in one scalar type.
pub(super) struct Level {
    pub(super) real: Real,
    pub(super) acc: Real,
    pub(super) op: Operator,
    pub(super) buf: CgBuffers,
    pub(super) k: CgKernels,
}

/// Mixed precision: the f64 outer loop.
pub(super) struct Refine {
    /// The f64 operator; `None` when its blocks exceed the storage binding limit, and then
    /// the outer residual is computed on the host from the downloaded y.
    pub(super) op: Option<Operator>,
    pub(super) b64: wgpu::Buffer,
    pub(super) y64: wgpu::Buffer,
    pub(super) partials64: wgpu::Buffer,
    /// [1/‖r‖, 2^s·‖r‖]: the inner right-hand side's normalization and the correction's
    /// scale back (see refine.wgsl).
    pub(super) factors: wgpu::Buffer,
    pub(super) k_residual: Kernel,
    pub(super) k_scale_rhs: Kernel,
    pub(super) k_accumulate: Kernel,
    /// The f64 operator bound to y → q.
    pub(super) bg_mv: Option<wgpu::BindGroup>,
    pub(super) bg_refine: wgpu::BindGroup,
    pub(super) staging: wgpu::Buffer,
}

pub(super) struct Timestamps {
    pub(super) set: wgpu::QuerySet,
    pub(super) resolve: wgpu::Buffer,
    pub(super) period_ns: f64,
}

fn flag(b: bool) -> f64 {
    if b {
        1.0
    } else {
        0.0
    }
}

/// Ĥ in `real`: its buffers (values written later by `GpuSolver::write_operator`), the
/// block rotation of an assembled operator and the matvec kernel.
pub(super) fn build_operator(
    bld: &mut Builder,
    sh: &Shared,
    host: &Host,
    real: Real,
    acc: Real,
    c: &Consts,
) -> Result<Operator, GpuError> {
    let f = &host.frames;
    let nd = host.ndof() as u64;
    let rn = real.name();
    let dvals = if c.masked {
        Some(bld.buffer(&format!("dvals_{rn}"), nd * real.size(), STORAGE)?)
    } else {
        None
    };
    let rotations = if c.rotated {
        Some(bld.buffer(
            &format!("rotations_{rn}"),
            f.rotations.len() as u64 * real.size(),
            STORAGE,
        )?)
    } else {
        None
    };
    let diff = c.diff && real == Real::F32 && matches!(host.op, HostOp::Blocks(_));
    let rowsum = if diff {
        Some(bld.buffer(
            &format!("rowsum_{rn}"),
            nd * f.dim as u64 * real.size(),
            STORAGE,
        )?)
    } else {
        None
    };
    let (data, matvec) = match &host.op {
        HostOp::Blocks(h) => {
            let blocks = plane_buffers(bld, &format!("blocks_{rn}"), h.dim, h.nnz_blocks(), real)?;
            let rotate = block_rotation(bld, sh, rotations.as_ref(), &blocks, real, acc, c)?;
            let mv = bld.kernel(
                "matvec",
                &kernels::MATVEC,
                real,
                acc,
                "matvec",
                &[
                    ("D", c.d),
                    ("WG", c.wg),
                    ("SUM_LANES", 1.0),
                    ("MASKED", flag(c.masked)),
                    ("DIFF", flag(diff)),
                ],
            )?;
            (OpData::Blocks { blocks, rotate }, mv)
        }
        HostOp::Springs(ms) => {
            let n = ms.n_nodes() as u64;
            let pos = bld.buffer(&format!("positions_{rn}"), nd * real.size(), STORAGE)?;
            let springs = bld.buffer(
                &format!("springs_{rn}"),
                2 * ms.edges.len() as u64 * real.size(),
                STORAGE,
            )?;
            let mass = bld.buffer(&format!("masses_{rn}"), n * real.size(), STORAGE)?;
            let diag_blocks =
                plane_buffers(bld, &format!("diag_blocks_{rn}"), ms.dim, n as usize, real)?;
            let mv = bld.kernel(
                "spring_matvec",
                &kernels::SPRINGS,
                real,
                acc,
                "spring_matvec",
                &[
                    ("D", c.d),
                    ("WG", c.wg),
                    ("SUM_LANES", 1.0),
                    ("MASKED", flag(c.masked)),
                    ("ROTATE", flag(c.rotated)),
                ],
            )?;
            let data = OpData::Springs {
                pos,
                springs,
                mass,
                diag_blocks,
            };
            (data, mv)
        }
    };
    Ok(Operator {
        real,
        data,
        dvals,
        rotations,
        rowsum,
        matvec,
    })
}

/// The setup kernel that rotates the blocks touching a slip node (none without one).
fn block_rotation(
    bld: &mut Builder,
    sh: &Shared,
    rotations: Option<&wgpu::Buffer>,
    blocks: &[wgpu::Buffer; 3],
    real: Real,
    acc: Real,
    c: &Consts,
) -> Result<Option<Bound>, GpuError> {
    let (Some(rot), Some(ri), Some(rnod)) = (rotations, &sh.rot_index, &sh.rot_nodes) else {
        return Ok(None);
    };
    let bound = bld.bound(
        "rotate_blocks",
        &kernels::ROTATE_BLOCKS,
        real,
        acc,
        "rotate_blocks",
        &[("D", c.d), ("WG", c.wg)],
        &[
            ("params", &sh.params),
            ("rot_index", ri),
            ("rot_nodes", rnod),
            ("rotations", rot),
            ("row_ptr", &sh.row_ptr),
            ("col", &sh.col),
            ("blk_a", &blocks[0]),
            ("blk_b", &blocks[1]),
            ("blk_c", &blocks[2]),
        ],
    )?;
    Ok(Some(bound))
}

/// Whether the block planes of an assembled operator in `real` fit the adapter's limits.
pub(super) fn blocks_fit(ctx: &GpuContext, host: &Host, real: Real) -> bool {
    let HostOp::Blocks(h) = &host.op else {
        return true;
    };
    let limit = ctx
        .limits
        .max_storage_buffer_binding_size
        .min(ctx.limits.max_buffer_size);
    plane_widths(h.dim)
        .iter()
        .all(|&w| (h.nnz_blocks() * w) as u64 * real.size() <= limit)
}

/// The vectors an operator's matvec binds: input `p`, output `q`, its partial sums and
/// the CG state whose done flag makes it a no-op.
pub(super) struct MatvecIo<'a> {
    pub(super) p: &'a wgpu::Buffer,
    pub(super) q: &'a wgpu::Buffer,
    pub(super) partials: &'a wgpu::Buffer,
    pub(super) state: &'a wgpu::Buffer,
}

/// Bind group of the operator kernel.
fn bind_operator(
    bld: &Builder,
    sh: &Shared,
    op: &Operator,
    label: &str,
    io: MatvecIo,
) -> Result<wgpu::BindGroup, GpuError> {
    let ph = &sh.placeholder;
    let dv = op.dvals.as_ref().unwrap_or(ph);
    let io_binds = [
        ("p", io.p),
        ("q", io.q),
        ("partials", io.partials),
        ("state", io.state),
        ("params", &sh.params),
        ("mask", sh.mask_or()),
        ("dvals", dv),
    ];
    match &op.data {
        OpData::Blocks { blocks, .. } => {
            let data = [
                ("row_ptr", &sh.row_ptr),
                ("col", &sh.col),
                ("blk_a", &blocks[0]),
                ("blk_b", &blocks[1]),
                ("blk_c", &blocks[2]),
                ("rowsum", op.rowsum.as_ref().unwrap_or(ph)),
            ];
            bld.bind(&op.matvec, label, &[&io_binds[..], &data[..]].concat())
        }
        OpData::Springs {
            pos, springs, mass, ..
        } => {
            let data = [
                ("adj_ptr", &sh.row_ptr),
                ("adj", &sh.col),
                ("pos", pos),
                ("springs", springs),
                ("mass", mass),
                ("rot_index", sh.rot_index.as_ref().unwrap_or(ph)),
                ("rotations", op.rotations.as_ref().unwrap_or(ph)),
            ];
            bld.bind(&op.matvec, label, &[&io_binds[..], &data[..]].concat())
        }
    }
}

/// A CG level on `op`: its buffers, then its kernels.
pub(super) fn build_level(
    bld: &mut Builder,
    sh: &Shared,
    op: Operator,
    host: &Host,
    acc: Real,
    c: &Consts,
    pc: Preconditioner,
) -> Result<Level, GpuError> {
    let buf = cg_buffers(bld, host, op.real, acc, c, pc)?;
    let k = cg_kernels(bld, sh, &op, &buf, acc, c)?;
    Ok(Level {
        real: op.real,
        acc,
        op,
        buf,
        k,
    })
}

/// The vectors, the preconditioner's and coarse correction's data, the partial sums and
/// the scalars of one CG.
fn cg_buffers(
    bld: &mut Builder,
    host: &Host,
    real: Real,
    acc: Real,
    c: &Consts,
    pc: Preconditioner,
) -> Result<CgBuffers, GpuError> {
    let rn = real.name();
    let vb = host.ndof() as u64 * real.size();
    let mut vector = |name: &str| bld.buffer(&format!("{name}_{rn}"), vb, STORAGE);
    let (x, r, z, p, q, b) = (
        vector("x")?,
        vector("r")?,
        vector("z")?,
        vector("p")?,
        vector("q")?,
        vector("b")?,
    );
    let n = host.frames.n_nodes as u64;
    let d = host.frames.dim as u64;
    let minv = match pc {
        Preconditioner::None => None,
        Preconditioner::Jacobi => Some(bld.buffer(
            &format!("precond_jacobi_{rn}"),
            n * d * real.size(),
            STORAGE,
        )?),
        Preconditioner::BlockJacobi => Some(bld.buffer(
            &format!("precond_block_{rn}"),
            n * d * d * real.size(),
            STORAGE,
        )?),
    };
    // One partial per workgroup and slot, sized for the most workgroups. Slots: p·q, r·z,
    // r·r, and with the coarse correction d more for Zᵀr.
    let slots = u64::from(slots::PART_ZR) + if c.coarse { d } else { 0 };
    let g = u64::from(MAX_WORKGROUPS);
    let partials = bld.buffer("partials", slots * g * acc.size(), STORAGE)?;
    let kc = d * u64::from(c.agg.max(1));
    let einv = if c.coarse || c.agg > 0 {
        Some(bld.buffer("coarse_einv", kc * kc * acc.size(), STORAGE)?)
    } else {
        None
    };
    let wc = if c.agg > 0 {
        Some(bld.buffer("coarse_wc", 2 * kc * acc.size(), STORAGE)?)
    } else {
        None
    };
    let scal = bld.buffer("cg_scalars", SCAL_LEN as u64 * acc.size(), STORAGE)?;
    let state = bld.buffer("cg_state", 4 * N_STATE as u64, STORAGE)?;
    let status_staging = bld.staging(
        "status_staging",
        SCAL_LEN as u64 * acc.size() + 4 * N_STATE as u64 + 16,
    )?;
    Ok(CgBuffers {
        x,
        r,
        z,
        p,
        q,
        b,
        minv,
        partials,
        scal,
        state,
        einv,
        wc,
        status_staging,
    })
}

/// The kernels of one CG with their bind groups: the three CG updates, the operator bound
/// to p and to x, the aggregate coarse correction and the preconditioner build.
fn cg_kernels(
    bld: &mut Builder,
    sh: &Shared,
    op: &Operator,
    buf: &CgBuffers,
    acc: Real,
    c: &Consts,
) -> Result<CgKernels, GpuError> {
    let real = op.real;
    let cg_consts = [
        ("D", c.d),
        ("WG", c.wg),
        // r·z and r·r, and with COARSE the D entries of Zᵀr (cg.wgsl write_partials).
        ("SUM_LANES", if c.coarse { 2.0 + c.d } else { 2.0 }),
        ("PRECOND", c.precond),
        ("HIST", LANCZOS_HIST as f64),
        ("COARSE", flag(c.coarse)),
        ("AGG", flag(c.agg > 0)),
        ("N_AGG", f64::from(c.agg.max(1))),
        ("MASKED", flag(c.masked)),
        ("ROTATED", flag(c.rotated)),
    ];
    let mut cg =
        |entry: &'static str| bld.kernel(entry, &kernels::CG, real, acc, entry, &cg_consts);
    let (update_p, update_xrz, init) = (cg("update_p")?, cg("update_xrz")?, cg("init")?);
    let ph = &sh.placeholder;
    let cg_group = bld.bind(
        &update_p,
        "cg bind group",
        &[
            ("params", &sh.params),
            ("x", &buf.x),
            ("r", &buf.r),
            ("z", &buf.z),
            ("p", &buf.p),
            ("q", &buf.q),
            ("b", &buf.b),
            ("minv", buf.minv.as_ref().unwrap_or(ph)),
            ("partials", &buf.partials),
            ("scal", &buf.scal),
            ("state", &buf.state),
            ("cmask", sh.mask_or()),
            ("rot_index", sh.rot_index.as_ref().unwrap_or(ph)),
            ("rotations", op.rotations.as_ref().unwrap_or(ph)),
            ("einv", buf.einv.as_ref().unwrap_or(ph)),
            ("agg_of", sh.agg.as_ref().map_or(ph, |a| &a.of_node)),
            ("wc", buf.wc.as_ref().unwrap_or(ph)),
        ],
    )?;
    let io = |p| MatvecIo {
        p,
        q: &buf.q,
        partials: &buf.partials,
        state: &buf.state,
    };
    Ok(CgKernels {
        matvec_p: bind_operator(bld, sh, op, "matvec p->q bind group", io(&buf.p))?,
        matvec_x: bind_operator(bld, sh, op, "matvec x->q bind group", io(&buf.x))?,
        agg: aggregate_kernels(bld, sh, op, buf, acc, c)?,
        precond: precond_kernel(bld, sh, op, buf, acc, c)?,
        update_p,
        update_xrz,
        init,
        cg_group,
    })
}

/// The restrict and solve kernels of the aggregate coarse correction (none without it).
fn aggregate_kernels(
    bld: &mut Builder,
    sh: &Shared,
    op: &Operator,
    buf: &CgBuffers,
    acc: Real,
    c: &Consts,
) -> Result<Option<AggKernels>, GpuError> {
    let (Some(ab), Some(wc), Some(einv)) = (&sh.agg, &buf.wc, &buf.einv) else {
        return Ok(None);
    };
    let consts = [
        ("D", c.d),
        ("WG", c.wg),
        // One aggregate's D translations (coarse.wgsl restrict_r).
        ("SUM_LANES", c.d),
        ("MASKED", flag(c.masked)),
        ("ROTATED", flag(c.rotated)),
        ("N_AGG", f64::from(c.agg)),
    ];
    let real = op.real;
    let restrict = bld.kernel(
        "coarse_restrict",
        &kernels::COARSE,
        real,
        acc,
        "restrict_r",
        &consts,
    )?;
    let solve = bld.kernel(
        "coarse_solve",
        &kernels::COARSE,
        real,
        acc,
        "solve",
        &consts,
    )?;
    let ph = &sh.placeholder;
    let group = bld.bind(
        &restrict,
        "coarse bind group",
        &[
            ("params", &sh.params),
            ("r", &buf.r),
            ("state", &buf.state),
            ("cmask", sh.mask_or()),
            ("rot_index", sh.rot_index.as_ref().unwrap_or(ph)),
            ("rotations", op.rotations.as_ref().unwrap_or(ph)),
            ("agg_ptr", &ab.ptr),
            ("agg_nodes", &ab.nodes),
            ("einv", einv),
            ("wc", wc),
        ],
    )?;
    Ok(Some(AggKernels {
        restrict,
        solve,
        group,
    }))
}

/// The setup kernel that builds the preconditioner from the operator's diagonal blocks
/// (none without a preconditioner).
fn precond_kernel(
    bld: &mut Builder,
    sh: &Shared,
    op: &Operator,
    buf: &CgBuffers,
    acc: Real,
    c: &Consts,
) -> Result<Option<Bound>, GpuError> {
    let Some(minv) = &buf.minv else {
        return Ok(None);
    };
    // Springs: the host-computed diagonal blocks with an identity pattern.
    let (row_ptr, col, blocks) = match &op.data {
        OpData::Blocks { blocks, .. } => (&sh.row_ptr, &sh.col, blocks),
        OpData::Springs { diag_blocks, .. } => match (&sh.diag_row_ptr, &sh.diag_col) {
            (Some(p), Some(c)) => (p, c, diag_blocks),
            _ => {
                return Err(GpuError::Device(
                    "the spring operator has no diagonal pattern".into(),
                ))
            }
        },
    };
    let bound = bld.bound(
        "precond_build",
        &kernels::PRECOND,
        op.real,
        acc,
        "build",
        &[
            ("D", c.d),
            ("WG", c.wg),
            ("MASKED", flag(c.masked)),
            ("PRECOND", c.precond),
        ],
        &[
            ("params", &sh.params),
            ("row_ptr", row_ptr),
            ("col", col),
            ("blk_a", &blocks[0]),
            ("mask", sh.mask_or()),
            ("dvals", op.dvals.as_ref().unwrap_or(&sh.placeholder)),
            ("minv", minv),
            ("blk_b", &blocks[1]),
            ("blk_c", &blocks[2]),
        ],
    )?;
    Ok(Some(bound))
}

/// Mixed precision's f64 outer loop: the f64 iterate, residual and right-hand side, and
/// the refine.wgsl kernels over them and the CG level's f32 vectors.
pub(super) fn build_refine(
    bld: &mut Builder,
    sh: &Shared,
    op: Option<Operator>,
    level: &Level,
    host: &Host,
    c: &Consts,
) -> Result<Refine, GpuError> {
    let nd = host.ndof() as u64;
    let b64 = bld.buffer("b_f64", nd * 8, STORAGE)?;
    let y64 = bld.buffer("y_f64", nd * 8, STORAGE)?;
    let q64 = bld.buffer("q_f64", nd * 8, STORAGE)?;
    let partials64 = bld.buffer("partials_f64", u64::from(MAX_WORKGROUPS) * 8, STORAGE)?;
    let zero_state = bld.buffer("refine_state", 4 * N_STATE as u64, STORAGE)?;
    let staging = bld.staging("refine_staging", u64::from(MAX_WORKGROUPS) * 8)?;
    let factors = bld.buffer("refine_factors_f64", 2 * 8, STORAGE)?;
    let consts = [("D", c.d), ("WG", c.wg), ("SUM_LANES", 1.0)];
    let mut refine = |name: &'static str| {
        bld.kernel(name, &kernels::REFINE, Real::F64, Real::F64, name, &consts)
    };
    let (k_residual, k_scale_rhs, k_accumulate) = (
        refine("residual")?,
        refine("scale_rhs")?,
        refine("accumulate")?,
    );
    let bg_refine = bld.bind(
        &k_residual,
        "refine bind group",
        &[
            ("params", &sh.params),
            ("b64", &b64),
            ("q64", &q64),
            ("rhs32", &level.buf.b),
            ("partials64", &partials64),
            ("x32", &level.buf.x),
            ("y64", &y64),
            ("factors", &factors),
        ],
    )?;
    let io = MatvecIo {
        p: &y64,
        q: &q64,
        partials: &partials64,
        state: &zero_state,
    };
    let bg_mv = match &op {
        Some(op) => Some(bind_operator(
            bld,
            sh,
            op,
            "matvec f64 y->q bind group",
            io,
        )?),
        None => None,
    };
    Ok(Refine {
        op,
        b64,
        y64,
        partials64,
        factors,
        k_residual,
        k_scale_rhs,
        k_accumulate,
        bg_mv,
        bg_refine,
        staging,
    })
}

/// Bytes one CG iteration must move (each array once): operator data and indices, the
/// vectors read and written by the three kernels, and the preconditioner.
pub(super) fn bytes_per_iteration(
    host: &Host,
    level: &Level,
    c: &Consts,
    pc: Preconditioner,
) -> u64 {
    let s = level.real.size();
    let nd = host.ndof() as u64;
    let n = host.frames.n_nodes as u64;
    let d = c.d as u64;
    let mut op = match &host.op {
        HostOp::Blocks(h) => h.values.len() as u64 * s + h.col_idx.len() as u64 * 4 + (n + 1) * 4,
        HostOp::Springs(ms) => {
            // adjacency (2 u32 per spring end), positions, spring data, masses
            (n + 1) * 4
                + 4 * 4 * ms.edges.len() as u64
                + nd * s
                + 2 * ms.edges.len() as u64 * s
                + n * s
        }
    };
    op += 2 * nd * s; // p read, q written
    if c.masked {
        op += n * 4 + nd * s; // mask, D
    }
    if c.rotated {
        if let HostOp::Springs(_) = host.op {
            op += n * 4 + host.frames.rotations.len() as u64 * s;
        }
    }
    // update_xrz: x rw, p r, r rw, q r, z w; update_p: z r, p rw.
    let vec = (2 + 1 + 2 + 1 + 1 + 1 + 2) * nd * s;
    let pre = match pc {
        Preconditioner::None => 0,
        Preconditioner::Jacobi => nd * s,
        Preconditioner::BlockJacobi => n * d * d * s,
    };
    // The difference form reads each node's row sum S_i.
    if level.op.rowsum.is_some() {
        op += n * d * d * s;
    }
    // The coarse correction reads the mask (update_xrz and update_p) and the rotations
    // of the rotated nodes, where there are any.
    let mut coarse = 0;
    if c.coarse {
        if c.masked {
            coarse += 2 * n * 4;
        }
        if c.rotated {
            coarse += 2 * (n * 4 + host.frames.rotations.len() as u64 * s);
        }
    }
    // Aggregates: restrict reads r, the node lists, the mask and rotations; solve reads
    // E⁺ (k² values); update_p reads each node's aggregate and the mask again.
    if c.agg > 0 {
        let kc = d * u64::from(c.agg);
        coarse += nd * s + 2 * n * 4 + kc * kc * level.acc.size() + n * 4;
        if c.masked {
            coarse += 2 * n * 4;
        }
        if c.rotated {
            coarse += 2 * (n * 4 + host.frames.rotations.len() as u64 * s);
        }
    }
    op + vec + pre + coarse
}
