//! The device-side objects of the solver and their construction: the operator Ĥ in one
//! scalar type (`Operator`), a CG level (`Level`: its buffers `CgBuffers` and compiled
//! kernels `CgKernels`), mixed precision's f64 outer loop (`Refine`), the kernel
//! specialization constants (`Consts`) and the bytes one CG iteration moves.

use super::builder::{
    piece, plane_buffers, plane_widths, Builder, Chunk, Chunked, Kernel, Real, Shared, STORAGE,
};
use super::host::{Host, HostOp};
use crate::gpu::kernels::{self, slots};
use crate::gpu::{GpuContext, GpuError, LaunchLimits, MAX_WORKGROUPS};
use crate::solve::cg::Preconditioner;

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
    /// Workgroups of the grid-stride kernels (`Device::n_partials`).
    pub(super) n_partials: u32,
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
        /// Row chunks whose pieces of the planes and columns fit one storage binding each.
        chunks: Vec<Chunk>,
        /// Ĥ_ij = V_iᵀ H_ij V_j in place on the planes (slip nodes only).
        rotate: Option<Chunked>,
    },
    Springs {
        pos: wgpu::Buffer,
        springs: wgpu::Buffer,
        mass: wgpu::Buffer,
        /// Host-rotated diagonal blocks of VᵀHV (as planes), for the preconditioner build.
        diag_blocks: [wgpu::Buffer; 3],
        /// Row chunks of the diagonal pattern (as for `OpData::Blocks`).
        diag_chunks: Vec<Chunk>,
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
    /// Chunked products: each invocation's p·q sum between the chunks' dispatches.
    pub(super) carry: Option<wgpu::Buffer>,
}

impl Operator {
    /// Records q = Ĥp with the operator bound by `groups` (one bind group per row chunk):
    /// one dispatch of exactly `g` workgroups (its partial sums) per chunk, in row order.
    pub(super) fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        groups: &[wgpu::BindGroup],
        g: u32,
        launch: &LaunchLimits,
        wg: u32,
    ) {
        pass.set_pipeline(&self.matvec.pipeline);
        let d = launch.reduction(g, wg);
        for bg in groups {
            pass.set_bind_group(0, bg, &[]);
            d.dispatch(pass);
        }
    }
}

impl Chunked {
    /// One dispatch per row chunk, one invocation per row up to the dispatch limits
    /// (grid-stride beyond).
    pub(super) fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        wg: u32,
        launch: &LaunchLimits,
    ) {
        pass.set_pipeline(&self.kernel.pipeline);
        for (bg, rows) in &self.groups {
            pass.set_bind_group(0, bg, &[]);
            launch.grid(*rows as u64, wg).dispatch(pass);
        }
    }
}

/// Bytes per row of the per-row arrays bound per chunk: the difference form's row sums
/// (d² values a node), else none.
pub(super) fn row_elem(host: &Host, real: Real, diff: bool) -> u64 {
    if diff {
        (host.frames.dim * host.frames.dim) as u64 * real.size()
    } else {
        0
    }
}

/// Bytes per block of the widest per-block array of an operator in `real`: plane a
/// (4 values; the columns take 4 bytes, plane c one value).
pub(super) fn block_elem(real: Real) -> u64 {
    4 * real.size()
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
    /// The operator's kernel bound to p → q and to x → q (one group per row chunk).
    pub(super) matvec_p: Vec<wgpu::BindGroup>,
    pub(super) matvec_x: Vec<wgpu::BindGroup>,
    pub(super) agg: Option<AggKernels>,
    pub(super) precond: Option<Chunked>,
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
    /// The f64 operator; `None` when its blocks exceed the adapter's buffer size limit (or
    /// the host residual is asked for), and then the outer residual is computed on the
    /// host from the downloaded y.
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
    /// The f64 operator bound to y → q (one group per row chunk).
    pub(super) bg_mv: Option<Vec<wgpu::BindGroup>>,
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
            let rp: Vec<u32> = h.row_ptr.iter().map(|&v| v as u32).collect();
            let chunks = bld.chunks(
                &format!("blocks_{rn}"),
                &rp,
                block_elem(real),
                row_elem(host, real, diff),
            )?;
            let rotate = block_rotation(
                bld,
                sh,
                rotations.as_ref(),
                &blocks,
                &chunks,
                h.dim,
                real,
                acc,
                c,
            )?;
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
            (
                OpData::Blocks {
                    blocks,
                    chunks,
                    rotate,
                },
                mv,
            )
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
            let identity: Vec<u32> = (0..=n as u32).collect();
            let diag_chunks =
                bld.chunks(&format!("diag_blocks_{rn}"), &identity, block_elem(real), 0)?;
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
                diag_chunks,
            };
            (data, mv)
        }
    };
    // One value per invocation of a product; one chunk never touches it, but a read-write
    // binding cannot share the read-only placeholder.
    let carry = match &data {
        OpData::Blocks { chunks, .. } => {
            let bytes = if chunks.len() > 1 {
                u64::from(c.n_partials) * c.wg as u64 * acc.size()
            } else {
                16
            };
            Some(bld.buffer(&format!("matvec_carry_{rn}"), bytes, STORAGE)?)
        }
        OpData::Springs { .. } => None,
    };
    Ok(Operator {
        real,
        data,
        dvals,
        rotations,
        rowsum,
        matvec,
        carry,
    })
}

/// The bindings of the per-block arrays in chunk `ch`: the columns and the three planes
/// (an unused plane whole), with the chunk's uniform.
fn block_pieces<'b>(
    col: &'b wgpu::Buffer,
    blocks: &'b [wgpu::Buffer; 3],
    chunks: &[Chunk],
    ch: &'b Chunk,
    d: usize,
    real: Real,
) -> [(&'static str, wgpu::BufferBinding<'b>); 5] {
    let one = chunks.len() == 1;
    let w = plane_widths(d);
    let s = real.size();
    [
        ("col", piece(col, ch, 4, one)),
        (
            "blk_a",
            piece(&blocks[0], ch, w[0] as u64 * s, one || w[0] == 0),
        ),
        (
            "blk_b",
            piece(&blocks[1], ch, w[1] as u64 * s, one || w[1] == 0),
        ),
        (
            "blk_c",
            piece(&blocks[2], ch, w[2] as u64 * s, one || w[2] == 0),
        ),
        ("chunk", ch.uniform.as_entire_buffer_binding()),
    ]
}

/// The setup kernel that rotates the blocks touching a slip node (none without one).
#[allow(clippy::too_many_arguments)]
fn block_rotation(
    bld: &mut Builder,
    sh: &Shared,
    rotations: Option<&wgpu::Buffer>,
    blocks: &[wgpu::Buffer; 3],
    chunks: &[Chunk],
    d: usize,
    real: Real,
    acc: Real,
    c: &Consts,
) -> Result<Option<Chunked>, GpuError> {
    let (Some(rot), Some(ri), Some(rnod)) = (rotations, &sh.rot_index, &sh.rot_nodes) else {
        return Ok(None);
    };
    let kernel = bld.kernel(
        "rotate_blocks",
        &kernels::ROTATE_BLOCKS,
        real,
        acc,
        "rotate_blocks",
        &[("D", c.d), ("WG", c.wg)],
    )?;
    let mut groups = Vec::with_capacity(chunks.len());
    for (i, ch) in chunks.iter().enumerate() {
        let whole = [
            ("params", sh.params.as_entire_buffer_binding()),
            ("rot_index", ri.as_entire_buffer_binding()),
            ("rot_nodes", rnod.as_entire_buffer_binding()),
            ("rotations", rot.as_entire_buffer_binding()),
            ("row_ptr", sh.row_ptr.as_entire_buffer_binding()),
        ];
        let pieces = block_pieces(&sh.col, blocks, chunks, ch, d, real);
        let bg = bld.bind_ranges(
            &kernel,
            &format!("rotate_blocks bind group (chunk {i})"),
            &[&whole[..], &pieces[..]].concat(),
        )?;
        groups.push((bg, ch.row1 - ch.row0));
    }
    Ok(Some(Chunked { kernel, groups }))
}

/// Whether the block planes of an assembled operator in `real` fit the adapter's buffer
/// size limit (they are bound in row-chunk pieces, so the binding limit does not apply).
pub(super) fn blocks_fit(ctx: &GpuContext, host: &Host, real: Real) -> bool {
    let HostOp::Blocks(h) = &host.op else {
        return true;
    };
    let limit = ctx.limits.max_buffer_size;
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

/// Bind groups of the operator kernel, one per row chunk.
fn bind_operator(
    bld: &Builder,
    sh: &Shared,
    op: &Operator,
    label: &str,
    io: MatvecIo,
) -> Result<Vec<wgpu::BindGroup>, GpuError> {
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
        OpData::Blocks { blocks, chunks, .. } => {
            let whole: Vec<(&str, wgpu::BufferBinding)> = io_binds
                .iter()
                .chain(&[
                    ("row_ptr", &sh.row_ptr),
                    ("carry", op.carry.as_ref().unwrap_or(ph)),
                ])
                .map(|&(n, b)| (n, b.as_entire_buffer_binding()))
                .collect();
            chunks
                .iter()
                .enumerate()
                .map(|(i, ch)| {
                    let pieces = block_pieces(&sh.col, blocks, chunks, ch, sh.dim, op.real);
                    let rowsum = match &op.rowsum {
                        Some(rs) if chunks.len() > 1 => {
                            let e = (sh.dim * sh.dim) as u64 * op.real.size();
                            wgpu::BufferBinding {
                                buffer: rs,
                                offset: u64::from(ch.row0) * e,
                                size: std::num::NonZeroU64::new(u64::from(ch.row1 - ch.row0) * e),
                            }
                        }
                        Some(rs) => rs.as_entire_buffer_binding(),
                        None => ph.as_entire_buffer_binding(),
                    };
                    let pieces = [&pieces[..], &[("rowsum", rowsum)]].concat();
                    let lbl = if chunks.len() == 1 {
                        label.to_string()
                    } else {
                        format!("{label} (chunk {i})")
                    };
                    bld.bind_ranges(&op.matvec, &lbl, &[&whole[..], &pieces[..]].concat())
                })
                .collect()
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
            Ok(vec![bld.bind(
                &op.matvec,
                label,
                &[&io_binds[..], &data[..]].concat(),
            )?])
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
        // Multilevel is refused by GpuSolver::build.
        Preconditioner::None | Preconditioner::Multilevel => None,
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
) -> Result<Option<Chunked>, GpuError> {
    let Some(minv) = &buf.minv else {
        return Ok(None);
    };
    // Springs: the host-computed diagonal blocks with an identity pattern.
    let (row_ptr, col, blocks, chunks) = match &op.data {
        OpData::Blocks { blocks, chunks, .. } => (&sh.row_ptr, &sh.col, blocks, chunks),
        OpData::Springs {
            diag_blocks,
            diag_chunks,
            ..
        } => match (&sh.diag_row_ptr, &sh.diag_col) {
            (Some(p), Some(c)) => (p, c, diag_blocks, diag_chunks),
            _ => {
                return Err(GpuError::Device(
                    "the spring operator has no diagonal pattern".into(),
                ))
            }
        },
    };
    let kernel = bld.kernel(
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
    )?;
    let mut groups = Vec::with_capacity(chunks.len());
    for (i, ch) in chunks.iter().enumerate() {
        let whole = [
            ("params", sh.params.as_entire_buffer_binding()),
            ("row_ptr", row_ptr.as_entire_buffer_binding()),
            ("mask", sh.mask_or().as_entire_buffer_binding()),
            (
                "dvals",
                op.dvals
                    .as_ref()
                    .unwrap_or(&sh.placeholder)
                    .as_entire_buffer_binding(),
            ),
            ("minv", minv.as_entire_buffer_binding()),
        ];
        let pieces = block_pieces(col, blocks, chunks, ch, sh.dim, op.real);
        let bg = bld.bind_ranges(
            &kernel,
            &format!("precond_build bind group (chunk {i})"),
            &[&whole[..], &pieces[..]].concat(),
        )?;
        groups.push((bg, ch.row1 - ch.row0));
    }
    Ok(Some(Chunked { kernel, groups }))
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
        Preconditioner::None | Preconditioner::Multilevel => 0,
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
