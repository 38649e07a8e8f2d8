//! The device-side objects of the solver and their construction: the operator Ĥ in one
//! scalar type (`Operator`), a CG level (`Level`), mixed precision's f64 outer loop
//! (`Refine`), the kernel specialization constants (`Consts`) and the bytes one CG
//! iteration moves.

use super::builder::{plane_buffers, plane_widths, Bind, Builder, Kernel, Real, Shared, STORAGE};
use super::host::{Host, HostOp};
use super::{Consts, LANCZOS_HIST, N_STATE, SCAL_LEN};
use crate::cg::Preconditioner;
use crate::gpu::{kernels, GpuContext, GpuError, MAX_WORKGROUPS};

pub(super) enum OpData {
    Blocks {
        /// Block planes (see `plane_widths`).
        blocks: [wgpu::Buffer; 3],
        rotate: Option<(Kernel, wgpu::BindGroup)>,
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

/// One CG in one scalar type.
pub(super) struct Level {
    pub(super) real: Real,
    pub(super) acc: Real,
    pub(super) op: Operator,
    pub(super) x: wgpu::Buffer,
    pub(super) r: wgpu::Buffer,
    #[allow(dead_code)]
    z: wgpu::Buffer,
    pub(super) p: wgpu::Buffer,
    pub(super) q: wgpu::Buffer,
    pub(super) b: wgpu::Buffer,
    pub(super) minv: wgpu::Buffer,
    pub(super) scal: wgpu::Buffer,
    pub(super) state: wgpu::Buffer,
    /// Coarse correction: E⁺ (k×k, accumulator type) of this level's operator.
    pub(super) einv: Option<wgpu::Buffer>,
    /// Aggregate coarse correction: the restrict and solve kernels (coarse.wgsl), their
    /// bind group.
    pub(super) agg: Option<(Kernel, Kernel, wgpu::BindGroup)>,
    pub(super) k_update_p: Kernel,
    pub(super) k_update_xrz: Kernel,
    pub(super) k_init: Kernel,
    pub(super) bg_cg: wgpu::BindGroup,
    pub(super) bg_mv_p: wgpu::BindGroup,
    pub(super) bg_mv_x: wgpu::BindGroup,
    pub(super) precond: Option<(Kernel, wgpu::BindGroup)>,
    pub(super) status_staging: wgpu::Buffer,
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

pub(super) fn build_operator(
    bld: &mut Builder,
    sh: &Shared,
    host: &Host,
    real: Real,
    acc: Real,
    c: &Consts,
) -> Result<Operator, GpuError> {
    use Bind::*;
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
            let rotate = match (&rotations, &sh.rot_index, &sh.rot_nodes) {
                (Some(rot), Some(ri), Some(rnod)) => {
                    let k = bld.kernel(
                        "rotate_blocks",
                        "rotate_blocks.wgsl",
                        kernels::ROTATE_BLOCKS,
                        real,
                        acc,
                        "rotate_blocks",
                        &[Uniform, Ro, Ro, Ro, Ro, Ro, Rw, Rw, Rw],
                        &[("D", c.d), ("WG", c.wg)],
                    )?;
                    let bg = bld.bind(
                        &k,
                        "rotate_blocks bind group",
                        &[
                            &sh.params,
                            ri,
                            rnod,
                            rot,
                            &sh.row_ptr,
                            &sh.col,
                            &blocks[0],
                            &blocks[1],
                            &blocks[2],
                        ],
                    );
                    Some((k, bg))
                }
                _ => None,
            };
            let mv = bld.kernel(
                "matvec",
                "matvec.wgsl",
                kernels::MATVEC,
                real,
                acc,
                "matvec",
                &[Uniform, Ro, Ro, Ro, Ro, Ro, Ro, Rw, Rw, Ro, Ro, Ro, Ro],
                &[
                    ("D", c.d),
                    ("WG", c.wg),
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
                "springs.wgsl",
                kernels::SPRINGS,
                real,
                acc,
                "spring_matvec",
                &[Uniform, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Rw, Rw, Ro],
                &[
                    ("D", c.d),
                    ("WG", c.wg),
                    ("MASKED", flag(c.masked)),
                    ("ROTATE", flag(c.rotated)),
                ],
            )?;
            (
                OpData::Springs {
                    pos,
                    springs,
                    mass,
                    diag_blocks,
                },
                mv,
            )
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

/// Bind group of the operator kernel with input `p`, output `q`.
#[allow(clippy::too_many_arguments)]
fn bind_operator(
    bld: &Builder,
    sh: &Shared,
    op: &Operator,
    label: &str,
    p: &wgpu::Buffer,
    q: &wgpu::Buffer,
    partials: &wgpu::Buffer,
    state: &wgpu::Buffer,
) -> wgpu::BindGroup {
    let ph = &sh.placeholder;
    let dv = op.dvals.as_ref().unwrap_or(ph);
    match &op.data {
        OpData::Blocks { blocks, .. } => bld.bind(
            &op.matvec,
            label,
            &[
                &sh.params,
                &sh.row_ptr,
                &sh.col,
                &blocks[0],
                sh.mask_or(),
                dv,
                p,
                q,
                partials,
                state,
                &blocks[1],
                &blocks[2],
                op.rowsum.as_ref().unwrap_or(ph),
            ],
        ),
        OpData::Springs {
            pos, springs, mass, ..
        } => bld.bind(
            &op.matvec,
            label,
            &[
                &sh.params,
                &sh.row_ptr,
                &sh.col,
                pos,
                springs,
                mass,
                sh.rot_index.as_ref().unwrap_or(ph),
                op.rotations.as_ref().unwrap_or(ph),
                sh.mask_or(),
                dv,
                p,
                q,
                partials,
                state,
            ],
        ),
    }
}

pub(super) fn build_level(
    bld: &mut Builder,
    sh: &Shared,
    op: Operator,
    host: &Host,
    acc: Real,
    c: &Consts,
    pc: Preconditioner,
) -> Result<Level, GpuError> {
    use Bind::*;
    let real = op.real;
    let rn = real.name();
    let nd = host.ndof() as u64;
    let vb = nd * real.size();
    let x = bld.buffer(&format!("x_{rn}"), vb, STORAGE)?;
    let r = bld.buffer(&format!("r_{rn}"), vb, STORAGE)?;
    let z = bld.buffer(&format!("z_{rn}"), vb, STORAGE)?;
    let p = bld.buffer(&format!("p_{rn}"), vb, STORAGE)?;
    let q = bld.buffer(&format!("q_{rn}"), vb, STORAGE)?;
    let b = bld.buffer(&format!("b_{rn}"), vb, STORAGE)?;
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
    let slots = if c.coarse { 3 + d } else { 3 };
    let g = u64::from(MAX_WORKGROUPS);
    let partials = bld.buffer("partials", slots * g * acc.size(), STORAGE)?;
    let kc = d * u64::from(c.agg.max(1));
    let einv = if c.coarse || c.agg > 0 {
        Some(bld.buffer("coarse_einv", kc * kc * acc.size(), STORAGE)?)
    } else {
        None
    };
    // Aggregates: w = Zᵀr and c = E⁺w.
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
    let cg_consts = [
        ("D", c.d),
        ("WG", c.wg),
        ("PRECOND", c.precond),
        ("HIST", LANCZOS_HIST as f64),
        ("COARSE", flag(c.coarse)),
        ("AGG", flag(c.agg > 0)),
        ("N_AGG", f64::from(c.agg.max(1))),
        ("MASKED", flag(c.masked)),
        ("ROTATED", flag(c.rotated)),
    ];
    let cg_binds = [
        Uniform, Rw, Rw, Rw, Rw, Ro, Ro, Ro, Rw, Rw, Rw, Ro, Ro, Ro, Ro, Ro, Ro,
    ];
    let k_update_p = bld.kernel(
        "update_p",
        "cg.wgsl",
        kernels::CG,
        real,
        acc,
        "update_p",
        &cg_binds,
        &cg_consts,
    )?;
    let k_update_xrz = bld.kernel(
        "update_xrz",
        "cg.wgsl",
        kernels::CG,
        real,
        acc,
        "update_xrz",
        &cg_binds,
        &cg_consts,
    )?;
    let k_init = bld.kernel(
        "init",
        "cg.wgsl",
        kernels::CG,
        real,
        acc,
        "init",
        &cg_binds,
        &cg_consts,
    )?;
    let minv_b = minv.as_ref().unwrap_or(&sh.placeholder);
    let bg_cg = bld.bind(
        &k_update_p,
        "cg bind group",
        &[
            &sh.params,
            &x,
            &r,
            &z,
            &p,
            &q,
            &b,
            minv_b,
            &partials,
            &scal,
            &state,
            sh.mask_or(),
            sh.rot_index.as_ref().unwrap_or(&sh.placeholder),
            op.rotations.as_ref().unwrap_or(&sh.placeholder),
            einv.as_ref().unwrap_or(&sh.placeholder),
            sh.agg.as_ref().map_or(&sh.placeholder, |a| &a.of_node),
            wc.as_ref().unwrap_or(&sh.placeholder),
        ],
    );
    let agg = match (&sh.agg, &wc, &einv) {
        (Some(ab), Some(wc), Some(einv)) => {
            let consts = [
                ("D", c.d),
                ("WG", c.wg),
                ("MASKED", flag(c.masked)),
                ("ROTATED", flag(c.rotated)),
                ("N_AGG", f64::from(c.agg)),
            ];
            let binds = [Uniform, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Rw];
            let k_restrict = bld.kernel(
                "coarse_restrict",
                "coarse.wgsl",
                kernels::COARSE,
                real,
                acc,
                "restrict_r",
                &binds,
                &consts,
            )?;
            let k_solve = bld.kernel(
                "coarse_solve",
                "coarse.wgsl",
                kernels::COARSE,
                real,
                acc,
                "solve",
                &binds,
                &consts,
            )?;
            let bg = bld.bind(
                &k_restrict,
                "coarse bind group",
                &[
                    &sh.params,
                    &r,
                    &state,
                    sh.mask_or(),
                    sh.rot_index.as_ref().unwrap_or(&sh.placeholder),
                    op.rotations.as_ref().unwrap_or(&sh.placeholder),
                    &ab.ptr,
                    &ab.nodes,
                    einv,
                    wc,
                ],
            );
            Some((k_restrict, k_solve, bg))
        }
        _ => None,
    };
    let bg_mv_p = bind_operator(
        bld,
        sh,
        &op,
        "matvec p->q bind group",
        &p,
        &q,
        &partials,
        &state,
    );
    let bg_mv_x = bind_operator(
        bld,
        sh,
        &op,
        "matvec x->q bind group",
        &x,
        &q,
        &partials,
        &state,
    );
    let precond = match &minv {
        None => None,
        Some(mb) => {
            let k = bld.kernel(
                "precond_build",
                "precond.wgsl",
                kernels::PRECOND,
                real,
                acc,
                "build",
                &[Uniform, Ro, Ro, Ro, Ro, Ro, Rw, Ro, Ro],
                &[
                    ("D", c.d),
                    ("WG", c.wg),
                    ("MASKED", flag(c.masked)),
                    ("PRECOND", c.precond),
                ],
            )?;
            let dv = op.dvals.as_ref().unwrap_or(&sh.placeholder);
            let bg = match &op.data {
                OpData::Blocks { blocks, .. } => bld.bind(
                    &k,
                    "precond bind group",
                    &[
                        &sh.params,
                        &sh.row_ptr,
                        &sh.col,
                        &blocks[0],
                        sh.mask_or(),
                        dv,
                        mb,
                        &blocks[1],
                        &blocks[2],
                    ],
                ),
                OpData::Springs { diag_blocks, .. } => bld.bind(
                    &k,
                    "precond bind group",
                    &[
                        &sh.params,
                        sh.diag_row_ptr
                            .as_ref()
                            .expect("springs have a diagonal pattern"),
                        sh.diag_col
                            .as_ref()
                            .expect("springs have a diagonal pattern"),
                        &diag_blocks[0],
                        sh.mask_or(),
                        dv,
                        mb,
                        &diag_blocks[1],
                        &diag_blocks[2],
                    ],
                ),
            };
            Some((k, bg))
        }
    };
    Ok(Level {
        real,
        acc,
        op,
        x,
        r,
        z,
        p,
        q,
        b,
        minv: minv.unwrap_or_else(|| sh.placeholder.clone()),
        scal,
        state,
        einv,
        agg,
        k_update_p,
        k_update_xrz,
        k_init,
        bg_cg,
        bg_mv_p,
        bg_mv_x,
        precond,
        status_staging,
    })
}

pub(super) fn build_refine(
    bld: &mut Builder,
    sh: &Shared,
    op: Option<Operator>,
    level: &Level,
    host: &Host,
    c: &Consts,
) -> Result<Refine, GpuError> {
    use Bind::*;
    let nd = host.ndof() as u64;
    let b64 = bld.buffer("b_f64", nd * 8, STORAGE)?;
    let y64 = bld.buffer("y_f64", nd * 8, STORAGE)?;
    let q64 = bld.buffer("q_f64", nd * 8, STORAGE)?;
    let partials64 = bld.buffer("partials_f64", u64::from(MAX_WORKGROUPS) * 8, STORAGE)?;
    let zero_state = bld.buffer("refine_state", 4 * N_STATE as u64, STORAGE)?;
    let staging = bld.staging("refine_staging", u64::from(MAX_WORKGROUPS) * 8)?;
    let factors = bld.buffer("refine_factors_f64", 2 * 8, STORAGE)?;
    let consts = [("D", c.d), ("WG", c.wg)];
    let binds = [Uniform, Ro, Rw, Rw, Rw, Ro, Rw, Ro];
    let k_residual = bld.kernel(
        "residual",
        "refine.wgsl",
        kernels::REFINE,
        Real::F64,
        Real::F64,
        "residual",
        &binds,
        &consts,
    )?;
    let k_scale_rhs = bld.kernel(
        "scale_rhs",
        "refine.wgsl",
        kernels::REFINE,
        Real::F64,
        Real::F64,
        "scale_rhs",
        &binds,
        &consts,
    )?;
    let k_accumulate = bld.kernel(
        "accumulate",
        "refine.wgsl",
        kernels::REFINE,
        Real::F64,
        Real::F64,
        "accumulate",
        &binds,
        &consts,
    )?;
    let bg_refine = bld.bind(
        &k_residual,
        "refine bind group",
        &[
            &sh.params,
            &b64,
            &q64,
            &level.b,
            &partials64,
            &level.x,
            &y64,
            &factors,
        ],
    );
    let bg_mv = op.as_ref().map(|op| {
        bind_operator(
            bld,
            sh,
            op,
            "matvec f64 y->q bind group",
            &y64,
            &q64,
            &partials64,
            &zero_state,
        )
    });
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
