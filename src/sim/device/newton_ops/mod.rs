//! The device Newton loop's vector operations, reductions and per-node updates
//! (shaders/newton_ops.wgsl): the device side of the CPU's `Stepper`
//! (src/sim/integrator/stepper.rs) around the element terms ([`GpuElements`]), their
//! assembly ([`GpuAssembly`]) and the linear solve's Δx.
//!
//! [`NewtonOps`] owns the accepted iterate x, the start of step xⁿ and the velocity v;
//! [`GpuElements::positions_buffer`] holds the point being evaluated (the iterate or a line
//! search trial). Every method is a few dispatches; a scalar result comes back as a handful
//! of bytes. Reductions are two-pass with a fixed number of workgroups and a fixed tree, so
//! a result does not depend on timing: sums are the same bits on every run, and arg-mins
//! break ties as the CPU's first strict minimum does (smallest node, then plane).
//!
//! f64 only: the loop compares energies to the Armijo condition, which f32 cannot resolve.

#![cfg(feature = "sim")]

use crate::gpu::kernels::{self, Access, Layout};
use crate::gpu::{GpuContext, GpuError, ReadRange};
use crate::sim::device::assembly::GpuAssembly;
use crate::sim::device::elements::{from_bytes, to_bytes, GpuElements, TermKind};
use crate::sim::energy::barrier::{Ccd, HalfSpace};
use crate::sim::scene::{joint_targets, BcShape, Scene};

pub mod conditions;
mod tail;

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/newton_ops.wgsl, shared by all its entry points.
pub const NEWTON_OPS: Layout = Layout {
    file: "newton_ops.wgsl",
    source: include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/shaders/newton_ops.wgsl"
    )),
    bindings: &[
        ("params", U),
        ("scal", R),
        ("x", W),
        ("xn", W),
        ("v", W),
        ("pos", W),
        ("xt", W),
        ("dx", R),
        ("grad", W),
        ("hvals", W),
        ("src", R),
        ("flags", R),
        ("table", R),
        ("index", R),
        ("partials", W),
        ("result", W),
        ("node_vals", W),
    ],
};

/// Uniform parameters of one dispatch (mirrors `OpsParams` in shaders/newton_ops.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct OpsParams {
    count: u32,
    mode: u32,
    slot: u32,
    aux: u32,
}
const _: () = assert!(std::mem::size_of::<OpsParams>() == 16);

/// Reduction modes (`MODE_*` in the shader).
const MODE_ENERGY: u32 = 0;
const MODE_DOT: u32 = 1;
const MODE_MAX_ABS: u32 = 2;
const MODE_CCD: u32 = 3;
const MODE_MIN_DISTANCE: u32 = 4;
const MODE_MOVING_ENERGY: u32 = 5;

/// Slots of the scalar buffer (`S_*` in the shader); half-space j at S_PLANES + 4j.
const S_H: usize = 0;
const S_FRACTION: usize = 1;
const S_INF: usize = 2;
const S_INV_FRACTION: usize = 3;
const S_PLANES: usize = 4;

/// Reals per static projection and per moving term, u32 per moving term (shader).
const PROJ_STRIDE: usize = 12;
const MOVING_STRIDE: usize = 12;
const MOVING_INDEX_STRIDE: usize = 4;

/// "No index" of a result lane (`NO_INDEX` in the shaders of the loop's operations and
/// checks): larger than every node, plane or element index, exact in f32 and f64.
pub(crate) const NO_INDEX: f64 = 4503599627370496.0;

/// Workgroup size of every kernel of the loop's operations and checks.
pub(crate) const WG: u32 = 64;

/// Upper bound of the reduction workgroups.
const MAX_REDUCE_GROUPS: usize = 64;

/// The workgroups of a two-pass reduction over `items`, the same for every dispatch of
/// it (a fixed tree, so the sums keep their bits): the adapter's count, at most 64 and
/// no more than the items fill; refused where the adapter cannot launch them all at once.
pub(crate) fn reduce_groups(ctx: &GpuContext, items: usize, what: &str) -> Result<usize, GpuError> {
    let groups = ctx
        .reduction_groups()
        .min(MAX_REDUCE_GROUPS)
        .min(items.max(1).div_ceil(WG as usize).next_power_of_two())
        .max(1);
    ctx.launch().require_exact(groups as u32, what)?;
    Ok(groups)
}

/// Entry points, in the order of [`Entry`].
const ENTRIES: [&str; 9] = [
    "begin_step",
    "project_static",
    "trial",
    "end_step",
    "gather_nodes",
    "add_moving",
    "reduce",
    "finish",
    "step_bound",
];

#[derive(Clone, Copy)]
enum Entry {
    BeginStep = 0,
    ProjectStatic = 1,
    Trial = 2,
    EndStep = 3,
    GatherNodes = 4,
    AddMoving = 5,
    Reduce = 6,
    Finish = 7,
    StepBound = 8,
}

/// One dispatch built once: pipeline, params and bind group.
struct Op {
    entry: Entry,
    params: wgpu::Buffer,
    group: wgpu::BindGroup,
}

/// A storage buffer that grows (and makes its users' bind groups be rebuilt) on demand.
struct Table {
    buf: wgpu::Buffer,
    bytes: u64,
}

/// The device Newton loop's state vectors and operations for one scene (see the module
/// documentation).
pub struct NewtonOps {
    ctx: GpuContext,
    dim: usize,
    n_nodes: usize,
    n_planes: usize,
    kinds: Vec<TermKind>,
    /// Per element term: item count.
    term_counts: Vec<usize>,
    /// Diagonal block of every node in the assembled pattern.
    /// Per node: its diagonal block as (values chunk, block within the chunk).
    diag: Vec<(u32, u32)>,
    pipelines: Vec<wgpu::ComputePipeline>,
    /// Reduction workgroups (fixed: the sums' order depends on it).
    groups: usize,
    /// The bind group layout and the buffers every op binds.
    binder: Binder,
    begin: Op,
    trial: Op,
    /// The line search's first α from the bounds (`tail`).
    step_bound: Op,
    end: Op,
    /// Per term: its energy reduction; then the finish of them all.
    energy: Vec<Op>,
    energy_finish: Op,
    dot: (Op, Op),
    max_abs: (Op, Op),
    ccd: (Op, Op),
    min_distance: (Op, Op),
    proj: Option<StaticProjections>,
    moving: Option<MovingTerms>,
    nodes: Option<NodeList>,
    /// E's per-term sums and the moving energy at x, kept while a trial's reuse the
    /// result slots (`tail`).
    energy_at_x: wgpu::Buffer,
}

/// The static projections [`NewtonOps::begin_step`] applies.
struct StaticProjections {
    /// How many (one per node).
    count: usize,
    /// Each projection's P and c, and its node: bound by `op`, kept while it is.
    _values: Table,
    _index: Table,
    op: Op,
}

/// The moving terms: their tables and the ops that add them to g and H and sum their
/// energy.
struct MovingTerms {
    count: usize,
    values: Table,
    index: Table,
    /// The H/g update, one per values chunk of H.
    adds: Vec<Op>,
    energy: Op,
    energy_finish: Op,
}

/// The node list [`NewtonOps::read_nodes`] gathers into, grown to powers of two.
struct NodeList {
    /// Capacity in nodes.
    capacity: usize,
    index: Table,
    values: Table,
    gather: Op,
}

/// Builds ops: the layout and the buffers every bind group shares (own state, the
/// element terms' positions and target, Δx, the assembly's gradient and blocks).
struct Binder {
    ctx: GpuContext,
    layout: wgpu::BindGroupLayout,
    scal: wgpu::Buffer,
    x: wgpu::Buffer,
    xn: wgpu::Buffer,
    v: wgpu::Buffer,
    pos: wgpu::Buffer,
    xt: wgpu::Buffer,
    dx: wgpu::Buffer,
    grad: wgpu::Buffer,
    /// H's values chunks ([`GpuAssembly::values_chunks`]); ops bind the first unless
    /// they name another.
    hvals: Vec<wgpu::Buffer>,
    partials: wgpu::Buffer,
    result: wgpu::Buffer,
    dummies: Dummies,
}

impl Binder {
    fn op(&self, label: &str, entry: Entry, p: OpsParams, var: Varying) -> Op {
        let params = self.ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("newton {label} params")),
            contents: bytemuck::bytes_of(&p),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let dm = &self.dummies;
        let bufs: [&wgpu::Buffer; 17] = [
            &params,
            &self.scal,
            &self.x,
            &self.xn,
            &self.v,
            &self.pos,
            &self.xt,
            &self.dx,
            &self.grad,
            var.hvals.unwrap_or(&self.hvals[0]),
            var.src.unwrap_or(&dm.src),
            var.flags.unwrap_or(&dm.flags),
            var.table.unwrap_or(&dm.table),
            var.index.unwrap_or(&dm.index),
            &self.partials,
            &self.result,
            var.node_vals.unwrap_or(&dm.node_vals),
        ];
        let group = kernels::bind_group(
            &self.ctx.device,
            &self.layout,
            &format!("newton {label} bind group"),
            &bufs,
        );
        Op {
            entry,
            params,
            group,
        }
    }
}

/// Stand-ins for the bindings an op does not use (one each, so that no buffer is bound
/// both read-only and writable).
struct Dummies {
    src: wgpu::Buffer,
    flags: wgpu::Buffer,
    table: wgpu::Buffer,
    index: wgpu::Buffer,
    node_vals: wgpu::Buffer,
}

/// What an op binds besides the shared buffers.
#[derive(Default, Clone, Copy)]
struct Varying<'a> {
    src: Option<&'a wgpu::Buffer>,
    flags: Option<&'a wgpu::Buffer>,
    table: Option<&'a wgpu::Buffer>,
    index: Option<&'a wgpu::Buffer>,
    node_vals: Option<&'a wgpu::Buffer>,
    hvals: Option<&'a wgpu::Buffer>,
}

fn slot_count(terms: usize) -> usize {
    terms + 5
}

/// Result slots after this module's, for the loop's checks ([`crate::sim::device::checks`]),
/// so that every scalar result of a Newton iteration lies in one buffer.
pub const CHECK_SLOTS: usize = 2;
/// Result slots after the checks': the line search's first trial's α (`tail`).
const TAIL_SLOTS: usize = 1;

/// What [`NewtonOps::new`] checks and compiles before it allocates: the sizes, every
/// node's diagonal block, the pipelines and the reduction workgroups.
struct OpsPlan {
    ctx: GpuContext,
    d: usize,
    n: usize,
    n_planes: usize,
    /// Per node: its diagonal block as (values chunk, block within the chunk).
    diag: Vec<(u32, u32)>,
    layout: wgpu::BindGroupLayout,
    pipelines: Vec<wgpu::ComputePipeline>,
    kinds: Vec<TermKind>,
    groups: usize,
}

/// The buffers [`NewtonOps`] owns: those every op binds, and E's sums at x.
struct OpsBuffers {
    binder: Binder,
    energy_at_x: wgpu::Buffer,
}

/// The ops built once in [`NewtonOps::new`] (see its fields).
struct FixedOps {
    begin: Op,
    trial: Op,
    step_bound: Op,
    end: Op,
    energy: Vec<Op>,
    term_counts: Vec<usize>,
    energy_finish: Op,
    dot: (Op, Op),
    max_abs: (Op, Op),
    ccd: (Op, Op),
    min_distance: (Op, Op),
}

impl OpsPlan {
    fn new(elements: &GpuElements, asm: &GpuAssembly, dx: &wgpu::Buffer) -> Result<Self, GpuError> {
        let ctx = elements.context().clone();
        if !elements.kernels().is_f64() {
            return Err(GpuError::Unsupported(
                "the device Newton loop runs in f64 only (its line search compares energies that f32 cannot resolve)".into(),
            ));
        }
        let d = elements.kernels().dim();
        let n = elements.n_nodes();
        let nd = (n * d) as u64;
        if dx.size() < nd * 8 {
            return Err(GpuError::Mismatch(format!(
                "the direction buffer has {} bytes, the mesh needs {}",
                dx.size(),
                nd * 8
            )));
        }
        let (row_ptr, col_idx) = asm.pattern();
        if row_ptr.len() != n + 1 {
            return Err(GpuError::Mismatch(format!(
                "the assembly has {} nodes, the element terms {n}",
                row_ptr.len().saturating_sub(1)
            )));
        }
        let diag: Vec<usize> = (0..n)
            .map(|i| {
                (row_ptr[i]..row_ptr[i + 1])
                    .find(|&k| col_idx[k] == i)
                    .ok_or_else(|| GpuError::Mismatch(format!("node {i} has no diagonal block")))
            })
            .collect::<Result<_, _>>()?;
        // Each node's diagonal block as (values chunk, block within it): the moving
        // penalty writes it in its chunk's buffer.
        let diag: Vec<(u32, u32)> = diag
            .iter()
            .map(|&k| {
                asm.values_chunks()
                    .iter()
                    .position(|c| c.blocks.contains(&k))
                    .map(|c| (c as u32, (k - asm.values_chunks()[c].blocks.start) as u32))
                    .ok_or_else(|| GpuError::Mismatch(format!("block {k} in no values chunk")))
            })
            .collect::<Result<_, _>>()?;
        let (layout, pipelines) = NEWTON_OPS.pipelines(
            &ctx,
            ("f64", "f64"),
            &format!("newton ops {d}D"),
            &ENTRIES,
            &[("D", d as f64), ("WG", WG as f64)],
        )?;
        let kinds = elements.kinds();
        let groups = reduce_groups(&ctx, n, "the Newton loop's reductions")?;
        Ok(OpsPlan {
            ctx,
            d,
            n,
            n_planes: elements.n_planes(),
            diag,
            layout,
            pipelines,
            kinds,
            groups,
        })
    }

    /// Allocates the state, scalar and reduction buffers and gathers those of the element
    /// terms, the assembly and Δx that every op binds.
    fn allocate(
        &self,
        elements: &GpuElements,
        asm: &GpuAssembly,
        dx: &wgpu::Buffer,
    ) -> Result<OpsBuffers, GpuError> {
        let ctx = &self.ctx;
        let nd = (self.n * self.d) as u64;
        let t = self.kinds.len();
        let zeroed = |label: &str, bytes: u64| ctx.storage_zeroed(label, bytes);
        let x = zeroed("newton x", nd * 8)?;
        let xn = zeroed("newton xn", nd * 8)?;
        let v = zeroed("newton v", nd * 8)?;
        let mut scal_init = vec![0.0; S_PLANES + 4 * self.n_planes.max(1)];
        scal_init[S_INF] = f64::INFINITY;
        let scal = ctx.storage_with("newton scalars", &to_bytes(true, &scal_init))?;
        let slots = slot_count(t) as u64;
        let partials = zeroed("newton partial reductions", slots * self.groups as u64 * 32)?;
        let all_slots = slots + (CHECK_SLOTS + TAIL_SLOTS) as u64;
        let result = zeroed("newton reductions", all_slots * 32)?;
        let energy_at_x = zeroed("newton energy at x", (t as u64 + 1) * 32)?;
        let dummies = Dummies {
            src: zeroed("newton unused energies", 16)?,
            flags: zeroed("newton unused flags", 16)?,
            table: zeroed("newton unused table", 16)?,
            index: zeroed("newton unused index", 16)?,
            node_vals: zeroed("newton unused node values", 16)?,
        };
        let binder = Binder {
            ctx: ctx.clone(),
            layout: self.layout.clone(),
            scal,
            x,
            xn,
            v,
            pos: elements.positions_buffer().clone(),
            xt: elements.inertia_target_buffer().clone(),
            dx: dx.clone(),
            grad: asm.gradient_buffer().clone(),
            hvals: asm
                .values_chunks()
                .iter()
                .map(|c| c.buffer.clone())
                .collect(),
            partials,
            result,
            dummies,
        };
        Ok(OpsBuffers {
            binder,
            energy_at_x,
        })
    }

    /// Builds the ops of every step: its begin and end, the trial point, the step bound,
    /// the per-term energy reductions and the scalar reductions.
    fn bind(&self, b: &Binder, elements: &GpuElements) -> Result<FixedOps, GpuError> {
        let (n, t, groups) = (self.n, self.kinds.len(), self.groups);
        let ndof = n * self.d;
        let p = |count: usize, mode: u32, slot: usize, aux: u32| OpsParams {
            count: count as u32,
            mode,
            slot: slot as u32,
            aux,
        };
        let none = Varying::default();
        let begin = b.op("begin step", Entry::BeginStep, p(ndof, 0, 0, 0), none);
        let alpha_slot = slot_count(t) + CHECK_SLOTS;
        let trial = b.op("trial", Entry::Trial, p(ndof, 0, alpha_slot, 0), none);
        let step_bound = b.op(
            "step bound",
            Entry::StepBound,
            p(slot_count(t), (t + 2) as u32, alpha_slot, 0),
            none,
        );
        let end = b.op("end step", Entry::EndStep, p(ndof, 0, 0, 0), none);
        let mut energy = Vec::with_capacity(t);
        let mut term_counts = Vec::with_capacity(t);
        for k in 0..t {
            let (buf, count, flags) = elements
                .term_energy(k)
                .ok_or_else(|| GpuError::Mismatch(format!("no element term {k}")))?;
            term_counts.push(count);
            energy.push(b.op(
                &format!("energy of term {k}"),
                Entry::Reduce,
                p(count, MODE_ENERGY, k, flags.is_some() as u32),
                Varying {
                    src: Some(buf),
                    flags,
                    ..none
                },
            ));
        }
        let energy_finish = b.op(
            "energy finish",
            Entry::Finish,
            p(groups, MODE_ENERGY, 0, 0),
            none,
        );
        let pair = |name: &str, count: usize, mode: u32, slot: usize, aux: u32| {
            (
                b.op(name, Entry::Reduce, p(count, mode, slot, aux), none),
                b.op(
                    &format!("{name} finish"),
                    Entry::Finish,
                    p(groups, mode, slot, 0),
                    none,
                ),
            )
        };
        let n_planes = self.n_planes as u32;
        Ok(FixedOps {
            begin,
            trial,
            step_bound,
            end,
            energy,
            term_counts,
            energy_finish,
            dot: pair("g·dx", ndof, MODE_DOT, t, 0),
            max_abs: pair("max |dx|", ndof, MODE_MAX_ABS, t + 1, 0),
            ccd: pair("ccd", n, MODE_CCD, t + 2, n_planes),
            min_distance: pair("min distance", n, MODE_MIN_DISTANCE, t + 3, n_planes),
        })
    }
}

impl NewtonOps {
    /// Builds the pipelines, state buffers and bind groups for the terms of `elements`,
    /// their assembly `asm` and the direction buffer `dx` (n·d f64, world frame).
    pub fn new(
        elements: &GpuElements,
        asm: &GpuAssembly,
        dx: &wgpu::Buffer,
    ) -> Result<Self, GpuError> {
        let plan = OpsPlan::new(elements, asm, dx)?;
        let OpsBuffers {
            binder,
            energy_at_x,
        } = plan.allocate(elements, asm, dx)?;
        let ops = plan.bind(&binder, elements)?;
        plan.ctx.check("building the Newton operations")?;
        Ok(NewtonOps {
            ctx: plan.ctx,
            dim: plan.d,
            n_nodes: plan.n,
            n_planes: plan.n_planes,
            kinds: plan.kinds,
            term_counts: ops.term_counts,
            diag: plan.diag,
            pipelines: plan.pipelines,
            groups: plan.groups,
            binder,
            begin: ops.begin,
            trial: ops.trial,
            step_bound: ops.step_bound,
            end: ops.end,
            energy: ops.energy,
            energy_finish: ops.energy_finish,
            dot: ops.dot,
            max_abs: ops.max_abs,
            ccd: ops.ccd,
            min_distance: ops.min_distance,
            proj: None,
            moving: None,
            nodes: None,
            energy_at_x,
        })
    }

    fn op(&self, label: &str, entry: Entry, p: OpsParams, var: Varying) -> Op {
        self.binder.op(label, entry, p, var)
    }

    fn set_params(&self, op: &Op, p: OpsParams) {
        self.ctx.write_buffer(&op.params, 0, bytemuck::bytes_of(&p));
    }

    /// Records `ops` (with their workgroup counts) in one compute pass, then `after`
    /// (copies), and submits.
    fn run(
        &self,
        label: &str,
        ops: &[(&Op, usize)],
        after: impl FnOnce(&mut wgpu::CommandEncoder),
    ) -> Result<(), GpuError> {
        let launch = self.ctx.launch();
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        {
            let mut cp = self.ctx.compute_pass(&mut enc, label, None);
            for (op, groups) in ops.iter().filter(|(_, g)| *g > 0) {
                cp.set_pipeline(&self.pipelines[op.entry as usize]);
                cp.set_bind_group(0, &op.group);
                // Reductions get exactly their workgroups (checked when built); the
                // grid-stride kernels any layout of about as many.
                cp.dispatch(launch.reduction(*groups as u32, WG));
            }
        }
        after(&mut enc);
        self.ctx.submit(enc);
        self.ctx.check(label)
    }

    /// Workgroups of a grid-stride kernel over `count` items.
    fn grid(count: usize) -> usize {
        count.div_ceil(WG as usize)
    }

    fn nd_bytes(&self) -> u64 {
        (self.n_nodes * self.dim) as u64 * 8
    }

    fn check_len(&self, what: &str, v: &[f64]) -> Result<(), GpuError> {
        let want = self.n_nodes * self.dim;
        if v.len() != want {
            return Err(GpuError::Mismatch(format!(
                "{what} has {} entries, the mesh {want}",
                v.len()
            )));
        }
        Ok(())
    }

    fn write_scalars(&self, slot: usize, v: &[f64]) {
        self.ctx
            .write_buffer(&self.binder.scal, slot as u64 * 8, &to_bytes(true, v));
    }

    fn read_result(&self, slot: usize, lanes: usize) -> Result<Vec<f64>, GpuError> {
        let b = self.ctx.download(
            &self.binder.result,
            slot as u64 * 32,
            lanes as u64 * 8,
            "reading a Newton reduction",
        )?;
        Ok(from_bytes(true, &b))
    }

    /// The state x, v (node-major; full upload at the start of a run); the evaluation
    /// positions become x.
    pub fn set_state(&self, x: &[f64], v: &[f64]) -> Result<(), GpuError> {
        self.check_len("the positions", x)?;
        self.check_len("the velocities", v)?;
        self.ctx.write_buffer(&self.binder.x, 0, &to_bytes(true, x));
        self.ctx.write_buffer(&self.binder.v, 0, &to_bytes(true, v));
        let nb = self.nd_bytes();
        self.run("newton set state", &[], |enc| {
            enc.copy_buffer_to_buffer(&self.binder.x, 0, &self.binder.pos, 0, nb)
        })
    }

    /// The state x, v (full download, for output).
    pub fn read_state(&self) -> Result<(Vec<f64>, Vec<f64>), GpuError> {
        let [x, v] = self.read_whole([&self.binder.x, &self.binder.v], "reading the state")?;
        Ok((x, v))
    }

    /// x, v and the gradient in one read-back (the end of a step's output).
    pub fn read_state_and_gradient(&self) -> Result<[Vec<f64>; 3], GpuError> {
        let b = &self.binder;
        self.read_whole([&b.x, &b.v, &b.grad], "reading the state and the gradient")
    }

    /// Whole n·d f64 vectors, read back with one wait.
    fn read_whole<const K: usize>(
        &self,
        bufs: [&wgpu::Buffer; K],
        what: &str,
    ) -> Result<[Vec<f64>; K], GpuError> {
        let nb = self.nd_bytes();
        let ranges: Vec<ReadRange> = bufs
            .iter()
            .map(|&buffer| ReadRange {
                buffer,
                offset: 0,
                bytes: nb,
            })
            .collect();
        let bytes = self.ctx.download_many(&ranges, what)?;
        let mut out: [Vec<f64>; K] = std::array::from_fn(|_| Vec::new());
        for (o, b) in out.iter_mut().zip(&bytes) {
            *o = from_bytes(true, b);
        }
        Ok(out)
    }

    /// A storage buffer holding `data` (padded to 16 bytes).
    fn table(&self, label: &str, data: &[u8]) -> Result<Table, GpuError> {
        let buf = self.ctx.storage_with(label, data)?;
        Ok(Table {
            bytes: buf.size(),
            buf,
        })
    }

    /// Start of step: x̃ = x + h v and xⁿ = x from the unprojected x (the CPU's
    /// `start_of_step`), then the static projections on x, then the evaluation positions
    /// = x.
    pub fn begin_step(&self, h: f64) -> Result<(), GpuError> {
        self.write_scalars(S_H, &[h]);
        let nd = self.n_nodes * self.dim;
        let mut ops = vec![(&self.begin, Self::grid(nd))];
        if let Some(p) = &self.proj {
            ops.push((&p.op, Self::grid(p.count)));
        }
        let nb = self.nd_bytes();
        self.run("newton begin step", &ops, |enc| {
            enc.copy_buffer_to_buffer(&self.binder.x, 0, &self.binder.pos, 0, nb)
        })
    }

    /// Per element term (in [`GpuElements::kinds`] order), the sum of its per-item
    /// energies at the evaluation positions after [`GpuElements::evaluate_energy`] (or
    /// `evaluate`); +∞ for the barrier when a weighted node touches or crosses a plane.
    /// Unscaled: the caller applies h².
    pub fn energy_terms(&self) -> Result<Vec<f64>, GpuError> {
        let t = self.energy.len();
        let mut ops: Vec<(&Op, usize)> = self.energy.iter().map(|o| (o, self.groups)).collect();
        ops.push((&self.energy_finish, t));
        self.run("newton energy terms", &ops, |_| {})?;
        let r = self.read_result(0, 4 * t)?;
        Ok((0..t)
            .map(|k| {
                if r[4 * k + 1] > 0.0 {
                    f64::INFINITY
                } else {
                    r[4 * k]
                }
            })
            .collect())
    }

    /// The element terms, as [`GpuElements::kinds`].
    pub fn kinds(&self) -> &[TermKind] {
        &self.kinds
    }

    fn reduce_pair(&self, label: &str, pair: &(Op, Op)) -> Result<(), GpuError> {
        self.run(label, &[(&pair.0, self.groups), (&pair.1, 1)], |_| {})
    }

    /// g·Δx with g the assembled gradient.
    pub fn dot_gradient_dx(&self) -> Result<f64, GpuError> {
        self.reduce_pair("newton g·dx", &self.dot)?;
        Ok(self.read_result(slot_count(self.energy.len()) - 5, 1)?[0])
    }

    /// ‖Δx‖∞; NaN when an entry is NaN (where the CPU's `f64::max` fold would skip it,
    /// a device loop must not).
    pub fn max_abs_dx(&self) -> Result<f64, GpuError> {
        self.reduce_pair("newton max |dx|", &self.max_abs)?;
        let r = self.read_result(slot_count(self.energy.len()) - 4, 2)?;
        Ok(if r[1] > 0.0 { f64::NAN } else { r[0] })
    }

    /// Evaluation positions = x + α Δx.
    pub fn set_trial(&self, alpha: f64) -> Result<(), GpuError> {
        self.write_alpha(alpha);
        let nd = self.n_nodes * self.dim;
        self.run("newton trial", &[(&self.trial, Self::grid(nd))], |_| {})
    }

    /// The evaluation positions = x (undoing a trial).
    pub fn reset_trial(&self) -> Result<(), GpuError> {
        let nb = self.nd_bytes();
        self.run("newton reset trial", &[], |enc| {
            enc.copy_buffer_to_buffer(&self.binder.x, 0, &self.binder.pos, 0, nb)
        })
    }

    /// x = the evaluation positions.
    pub fn accept(&self) -> Result<(), GpuError> {
        let nb = self.nd_bytes();
        self.run("newton accept", &[], |enc| {
            enc.copy_buffer_to_buffer(&self.binder.pos, 0, &self.binder.x, 0, nb)
        })
    }

    /// End of step: v = (x − xⁿ)/h.
    pub fn end_step(&self, h: f64) -> Result<(), GpuError> {
        self.write_scalars(S_H, &[h]);
        let nd = self.n_nodes * self.dim;
        self.run("newton end step", &[(&self.end, Self::grid(nd))], |_| {})
    }

    /// The assembled gradient (full download, for the reactions at the end of a step).
    pub fn read_gradient(&self) -> Result<Vec<f64>, GpuError> {
        let b = self.ctx.download(
            &self.binder.grad,
            0,
            self.nd_bytes(),
            "reading the gradient",
        )?;
        Ok(from_bytes(true, &b))
    }

    fn write_planes(
        &self,
        planes: &[HalfSpace],
        op: &Op,
        mode: u32,
        slot: usize,
    ) -> Result<(), GpuError> {
        if planes.len() > self.n_planes.max(1) || (self.n_planes == 0 && !planes.is_empty()) {
            return Err(GpuError::Mismatch(format!(
                "{} half-spaces given, the element terms were built with {}",
                planes.len(),
                self.n_planes
            )));
        }
        let v: Vec<f64> = planes
            .iter()
            .flat_map(|p| [p.normal[0], p.normal[1], p.normal[2], p.offset])
            .collect();
        self.write_scalars(S_PLANES, &v);
        self.set_params(
            op,
            OpsParams {
                count: self.n_nodes as u32,
                mode,
                slot: slot as u32,
                aux: planes.len() as u32,
            },
        );
        Ok(())
    }

    /// The CCD bound of the step Δx from x against `planes`, as `Barrier::ccd` (every
    /// node, weighted or not; the limiting (node, plane) is the first strict minimum in
    /// node-then-plane order).
    pub fn ccd(&self, planes: &[HalfSpace], fraction: f64) -> Result<Ccd, GpuError> {
        let slot = slot_count(self.energy.len()) - 3;
        self.write_planes(planes, &self.ccd.0, MODE_CCD, slot)?;
        self.write_scalars(S_FRACTION, &[fraction]);
        self.reduce_pair("newton ccd", &self.ccd)?;
        let r = self.read_result(slot, 2)?;
        let limit = (r[1] < NO_INDEX).then(|| {
            let k = r[1] as usize;
            (k / planes.len(), k % planes.len())
        });
        Ok(Ccd {
            alpha: r[0].max(0.0),
            limit,
        })
    }

    /// The smallest signed distance of any node to any plane at x, with (node, plane), as
    /// `Barrier::min_distance`: the first NaN distance (in node-then-plane order) when
    /// there is one, (+∞, 0, 0) when there is no finite one.
    pub fn min_distance(&self, planes: &[HalfSpace]) -> Result<(f64, usize, usize), GpuError> {
        let slot = slot_count(self.energy.len()) - 2;
        self.write_planes(planes, &self.min_distance.0, MODE_MIN_DISTANCE, slot)?;
        self.reduce_pair("newton min distance", &self.min_distance)?;
        let r = self.read_result(slot, 3)?;
        let split = |k: f64| {
            let k = k as usize;
            (k / planes.len(), k % planes.len())
        };
        Ok(if r[2] < NO_INDEX {
            let (i, j) = split(r[2]);
            (f64::NAN, i, j)
        } else if r[1] < NO_INDEX {
            let (i, j) = split(r[1]);
            (r[0], i, j)
        } else {
            (f64::INFINITY, 0, 0)
        })
    }

    /// The accepted iterate x (node-major f64) and the Newton direction Δx it was built
    /// with.
    pub fn iterate_buffers(&self) -> (&wgpu::Buffer, &wgpu::Buffer) {
        (&self.binder.x, &self.binder.dx)
    }

    /// Every scalar result of the loop, one `vec4<f64>` (32 bytes) per slot: this module's
    /// (per element term its energy, then g·Δx, ‖Δx‖∞, CCD, smallest distance, moving
    /// energy) and from [`NewtonOps::check_slots`] on the checks'.
    pub fn result_buffer(&self) -> &wgpu::Buffer {
        &self.binder.result
    }

    /// The [`CHECK_SLOTS`] result slots reserved for the checks.
    pub fn check_slots(&self) -> std::ops::Range<usize> {
        let s = slot_count(self.energy.len());
        s..s + CHECK_SLOTS
    }

    /// The context the operations run on.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// Items per element term (as [`GpuElements::term_energy`]).
    pub fn term_counts(&self) -> &[usize] {
        &self.term_counts
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The WGSL declarations of bind group 0 are [`NEWTON_OPS`]' bindings, in order, with
    /// their access; `OpsParams` is four u32 in WGSL as in Rust; every entry point exists.
    #[test]
    fn layout_and_params_match_the_wgsl() {
        let size = std::mem::size_of::<OpsParams>();
        let m = kernels::check::layout(&NEWTON_OPS, "OpsParams", size, &ENTRIES);
        assert_eq!(
            kernels::check::struct_members(&m, "OpsParams"),
            ["count", "mode", "slot", "aux"]
        );
        // The shader's constants are the host's.
        for (name, want) in [
            ("MODE_ENERGY", MODE_ENERGY),
            ("MODE_DOT", MODE_DOT),
            ("MODE_MAX_ABS", MODE_MAX_ABS),
            ("MODE_CCD", MODE_CCD),
            ("MODE_MIN_DISTANCE", MODE_MIN_DISTANCE),
            ("MODE_MOVING_ENERGY", MODE_MOVING_ENERGY),
            ("S_H", S_H as u32),
            ("S_INV_FRACTION", S_INV_FRACTION as u32),
            ("S_FRACTION", S_FRACTION as u32),
            ("S_INF", S_INF as u32),
            ("S_PLANES", S_PLANES as u32),
            ("PROJ_STRIDE", PROJ_STRIDE as u32),
            ("MOVING_STRIDE", MOVING_STRIDE as u32),
            ("MOVING_INDEX_STRIDE", MOVING_INDEX_STRIDE as u32),
        ] {
            let (_, c) = m
                .constants
                .iter()
                .find(|(_, c)| c.name.as_deref() == Some(name))
                .unwrap_or_else(|| panic!("no const {name}"));
            match m.global_expressions[c.init] {
                naga::Expression::Literal(naga::Literal::U32(v)) => assert_eq!(v, want, "{name}"),
                ref e => panic!("{name} = {e:?}"),
            }
        }
    }
}
