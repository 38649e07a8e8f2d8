//! The device Newton loop's per-iteration checks, reduced to scalars on the device
//! (shaders/newton_checks.wgsl): the inversion bound of the classical neo-Hookean elements
//! (`Model::inversion_bound`) and the force balance (`force_balance_of`). Both read what
//! the loop already holds on the device (x, Δx, x̃, ∇E, the element terms' connectivity,
//! rest data and gradients, the assembly's node gather lists), so that nothing of size n
//! crosses the bus for them.
//!
//! Each check comes in three parts, so that a caller can batch several into one submit and
//! one download: `record_*` records its dispatches into the caller's command encoder (its
//! scalar inputs are written through the queue, so they take effect at the caller's next
//! submit; two records of one check in one submit share the last value), leaving its result
//! in a fixed slot of the loop's result buffer ([`NewtonOps::result_buffer`]); `decode_*`
//! turns the four f64 of that slot into the host's type; and the one-call form (records,
//! submits, reads the one slot, decodes) is what the loop uses.
//!
//! Result slots, one `vec4<f64>` (32 bytes) each, from [`NewtonOps::check_slots`]`.start`:
//!
//! | slot | lanes                                                                  |
//! |------|------------------------------------------------------------------------|
//! | +0   | inversion bound: α, its element, the first inverted element, its J      |
//! | +1   | force balance: residual, its node, scale, x_max                        |
//!
//! Element indices are global over the model's element sets (set k's element e is
//! Σ_{j<k} len_j + e), and `NO_INDEX` (2⁵²) stands for none.
//!
//! The host's functions are reproduced operation by operation in the same order (the root
//! search of every element, the per-node sums in the host's element order); every
//! combine is a minimum, a maximum or a comparison, which round nothing, so a result does
//! not depend on the workgroups and ties go to the first index, as on the host. What can
//! differ is a driver's own arithmetic: multiply-adds it contracts, its square root, and
//! the device's logarithm (a series, shaders/common.wgsl) in the barrier's forces; the
//! element gradients the force scale sums are the device's (tests/gpu_newton_checks.rs
//! measures both against the host).

#![cfg(feature = "sim")]

use crate::core::constraints::Frames;
use crate::gpu::gate::Dispatch;
use crate::gpu::kernels::{self, Access, Layout};
use crate::gpu::pcg::frame_words;
use crate::gpu::{GpuContext, GpuError};
use crate::sim::device::assembly::GpuAssembly;
use crate::sim::device::elements::{from_bytes, to_bytes, GpuElements, TermKind};
use crate::sim::device::newton_ops::{reduce_groups, NewtonOps, NO_INDEX, WG};
use crate::sim::energy::{ElementSet, InversionLimit, Inverted, Law, Model};
use crate::sim::integrator::ForceBalance;
use std::sync::atomic::{AtomicU64, Ordering};

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/newton_checks.wgsl, shared by all its entry points.
pub const NEWTON_CHECKS: Layout = Layout {
    file: "newton_checks.wgsl",
    source: include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/shaders/newton_checks.wgsl"
    )),
    bindings: &[
        ("params", U),
        ("scal", R),
        ("consts", R),
        ("node_data", R),
        ("x", R),
        ("xt", R),
        ("dx", R),
        ("grad", R),
        ("nodes", R),
        ("rest", R),
        ("egrad", R),
        ("offsets", R),
        ("entries", R),
        ("frame", R),
        ("rotations", R),
        ("sizes", W),
        ("partials", W),
        ("result", W),
    ],
};

/// Uniform parameters of one dispatch (mirrors `CheckParams` in shaders/newton_checks.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct CheckParams {
    count: u32,
    mode: u32,
    slot: u32,
    row: u32,
    first: u32,
    n_planes: u32,
    pad: [u32; 2],
}
const _: () = assert!(std::mem::size_of::<CheckParams>() == 32);

/// Reduction modes (`MODE_*` in the shader).
const MODE_INVERSION: u32 = 0;
const MODE_BALANCE: u32 = 1;

/// Slots of the scalar buffer (`S_*` in the shader).
const S_MAX: usize = 0;
const S_H2: usize = 1;
const S_GNORM: usize = 2;
const S_INF: usize = 3;
const N_SCAL: usize = 4;

/// Entry points, in the order of [`Entry`].
const ENTRIES: [&str; 4] = ["sizes_init", "sizes_add", "reduce", "finish"];

#[derive(Clone, Copy, PartialEq)]
enum Entry {
    SizesInit = 0,
    SizesAdd = 1,
    Reduce = 2,
    Finish = 3,
}

/// Identity of a [`NewtonChecks`], so that frames are used with the checks that built them.
static NEXT_ID: AtomicU64 = AtomicU64::new(0);

/// One dispatch built once: its entry point, item count, params and bind group.
struct Op {
    entry: Entry,
    count: usize,
    _params: wgpu::Buffer,
    group: wgpu::BindGroup,
}

/// What an op binds besides the shared buffers (a dummy where None).
#[derive(Default, Clone, Copy)]
struct Varying<'a> {
    nodes: Option<&'a wgpu::Buffer>,
    rest: Option<&'a wgpu::Buffer>,
    egrad: Option<&'a wgpu::Buffer>,
    offsets: Option<&'a wgpu::Buffer>,
    entries: Option<&'a wgpu::Buffer>,
    frame: Option<&'a wgpu::Buffer>,
    rotations: Option<&'a wgpu::Buffer>,
}

/// The layout and the buffers every bind group shares.
struct Binder {
    ctx: GpuContext,
    layout: wgpu::BindGroupLayout,
    scal: wgpu::Buffer,
    consts: wgpu::Buffer,
    node_data: wgpu::Buffer,
    x: wgpu::Buffer,
    xt: wgpu::Buffer,
    dx: wgpu::Buffer,
    grad: wgpu::Buffer,
    sizes: wgpu::Buffer,
    partials: wgpu::Buffer,
    result: wgpu::Buffer,
    /// Stands in for every read-only binding an op does not use.
    dummy: wgpu::Buffer,
}

impl Binder {
    fn op(&self, label: &str, entry: Entry, p: CheckParams, count: usize, var: Varying) -> Op {
        let params = self.ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("newton checks {label} params")),
            contents: bytemuck::bytes_of(&p),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let d = &self.dummy;
        let bufs: [&wgpu::Buffer; 18] = [
            &params,
            &self.scal,
            &self.consts,
            &self.node_data,
            &self.x,
            &self.xt,
            &self.dx,
            &self.grad,
            var.nodes.unwrap_or(d),
            var.rest.unwrap_or(d),
            var.egrad.unwrap_or(d),
            var.offsets.unwrap_or(d),
            var.entries.unwrap_or(d),
            var.frame.unwrap_or(d),
            var.rotations.unwrap_or(d),
            &self.sizes,
            &self.partials,
            &self.result,
        ];
        let group = kernels::bind_group(
            &self.ctx.device,
            &self.layout,
            &format!("newton checks {label} bind group"),
            &bufs,
        );
        Op {
            entry,
            count,
            _params: params,
            group,
        }
    }
}

/// A constraint set's masks and rotations on the device, for [`NewtonChecks::record_force_balance`]
/// (built once per constraint set by [`NewtonChecks::frames`]).
pub struct BalanceFrames {
    owner: u64,
    reduce: Op,
    _frame: wgpu::Buffer,
    _rotations: wgpu::Buffer,
}

/// The inversion bound and the force balance of a scene on the device (see the module
/// documentation).
pub struct NewtonChecks {
    ctx: GpuContext,
    id: u64,
    dim: usize,
    n_nodes: usize,
    n_planes: usize,
    pipelines: Vec<wgpu::ComputePipeline>,
    /// Reduction workgroups (one partial each).
    groups: usize,
    binder: Binder,
    /// Per element set of the model, in order.
    sets: Vec<SetSpan>,
    /// One reduction per chunk of classical neo-Hookean elements, then their finish.
    inversion: Vec<Op>,
    inversion_finish: Op,
    sizes_init: Op,
    /// One per element chunk (either law, springs), in the model's element order.
    sizes_add: Vec<Op>,
    balance_finish: Op,
    /// The first of the two result slots.
    slot: usize,
}

/// An element chunk's term and the index of its set.
type TermSet = (usize, usize);

/// Where one element set of the model lies among all the model's elements.
#[derive(Debug, Clone, Copy)]
struct SetSpan {
    /// The global index of the set's element 0.
    first: usize,
    /// Its element count.
    len: usize,
    /// Whether it follows the classical neo-Hookean law (the inversion bound's sets).
    classical: bool,
}

/// Per element chunk of `elements` (built from `model`) its term and set, and per element
/// set of `model` its span.
fn element_sets(
    elements: &GpuElements,
    model: &Model,
) -> Result<(Vec<TermSet>, Vec<SetSpan>), GpuError> {
    let mut chunks = Vec::new();
    let mut set: Option<usize> = None;
    for (t, kind) in elements.kinds().iter().enumerate() {
        if !matches!(kind, TermKind::NeoHookean | TermKind::Springs) {
            continue;
        }
        let r = elements
            .term_range(t)
            .ok_or_else(|| GpuError::Mismatch(format!("no element term {t}")))?;
        // A set's first chunk starts at element 0; its other chunks follow it.
        if r.start == 0 {
            set = Some(set.map_or(0, |k| k + 1));
        }
        let k = set.ok_or_else(|| {
            GpuError::Mismatch(format!("element term {t} starts at element {}", r.start))
        })?;
        chunks.push((t, k));
    }
    if chunks.last().map_or(0, |c| c.1 + 1) != model.sets.len() {
        return Err(GpuError::Mismatch(format!(
            "{} element sets in the model, others on the device",
            model.sets.len()
        )));
    }
    let mut sets = Vec::with_capacity(model.sets.len());
    let mut base = 0usize;
    for s in &model.sets {
        let classical = matches!(s, ElementSet::NeoHookean(nh) if nh.law == Law::NeoHookean);
        sets.push(SetSpan {
            first: base,
            len: s.len(),
            classical,
        });
        base += s.len();
    }
    if u32::try_from(base).is_err() {
        return Err(GpuError::Unsupported(format!(
            "{base} elements exceed the checks' u32 indices"
        )));
    }
    Ok((chunks, sets))
}

impl CheckParams {
    fn new(count: usize, mode: u32, slot: usize, row: usize, first: usize, planes: usize) -> Self {
        CheckParams {
            count: count as u32,
            mode,
            slot: slot as u32,
            row: row as u32,
            first: first as u32,
            n_planes: planes as u32,
            pad: [0; 2],
        }
    }
}

impl NewtonChecks {
    /// Builds the pipelines, buffers and bind groups for the terms of `elements` (built
    /// from `model`), their assembly `asm` and the loop's operations `ops` (whose result
    /// buffer receives the results).
    pub fn new(
        elements: &GpuElements,
        asm: &GpuAssembly,
        ops: &NewtonOps,
        model: &Model,
    ) -> Result<Self, GpuError> {
        let ctx = elements.context().clone();
        if !elements.kernels().is_f64() {
            return Err(GpuError::Unsupported(
                "the device Newton loop's checks run in f64 only".into(),
            ));
        }
        let d = elements.kernels().dim();
        let n = elements.n_nodes();
        if model.dim != d || model.n_nodes != n {
            return Err(GpuError::Mismatch(format!(
                "the model has {} nodes in {}D, the element terms {n} in {d}D",
                model.n_nodes, model.dim
            )));
        }
        let (chunks, sets) = element_sets(elements, model)?;
        let (layout, pipelines) = NEWTON_CHECKS.pipelines(
            &ctx,
            ("f64", "f64"),
            &format!("newton checks {d}D"),
            &ENTRIES,
            &[("D", d as f64), ("WG", WG as f64)],
        )?;
        let largest = chunks
            .iter()
            .filter_map(|&(t, _)| elements.term_range(t).map(|r| r.len()))
            .fold(n, usize::max);
        let groups = reduce_groups(&ctx, largest, "the Newton loop's checks")?;
        let inv_chunks: Vec<(usize, usize)> = chunks
            .iter()
            .copied()
            .filter(|c| sets[c.1].classical)
            .collect();
        // Partials: a row per classical chunk, then the force balance's.
        let rows = inv_chunks.len() + 1;
        let gnorm = model
            .gravity
            .as_ref()
            .map_or(0.0, |g| g.iter().map(|v| v * v).sum::<f64>().sqrt());
        let mut scal = vec![0.0; N_SCAL];
        scal[S_GNORM] = gnorm;
        scal[S_INF] = f64::INFINITY;
        let (x, dx) = ops.iterate_buffers();
        let slot = ops.check_slots().start;
        let binder = Binder {
            ctx: ctx.clone(),
            layout,
            scal: ctx.storage_with("newton checks scalars", &to_bytes(true, &scal))?,
            consts: elements.constants_buffer().clone(),
            node_data: elements.node_data_buffer().clone(),
            x: x.clone(),
            xt: elements.inertia_target_buffer().clone(),
            dx: dx.clone(),
            grad: asm.gradient_buffer().clone(),
            sizes: ctx.storage_zeroed("newton checks force sizes", n as u64 * 8)?,
            partials: ctx.storage_zeroed(
                "newton checks partial reductions",
                (rows * groups) as u64 * 32,
            )?,
            result: ops.result_buffer().clone(),
            dummy: ctx.storage_zeroed("newton checks unused input", 16)?,
        };
        let planes = elements.n_planes();
        let inversion = Self::inversion_ops(&binder, elements, &inv_chunks, &sets, (groups, slot))?;
        let inv_partials = inv_chunks.len() * groups;
        let inversion_finish = binder.op(
            "inversion finish",
            Entry::Finish,
            CheckParams::new(inv_partials, MODE_INVERSION, slot, 0, 0, planes),
            1,
            Varying::default(),
        );
        let sizes_init = binder.op(
            "sizes init",
            Entry::SizesInit,
            CheckParams::new(n, 0, 0, 0, 0, planes),
            n,
            Varying::default(),
        );
        let sizes_add = Self::sizes_ops(&binder, elements, asm, &chunks)?;
        let balance_finish = binder.op(
            "balance finish",
            Entry::Finish,
            CheckParams::new(groups, MODE_BALANCE, slot + 1, inv_partials, 0, planes),
            1,
            Varying::default(),
        );
        ctx.check("building the Newton loop's checks")?;
        Ok(NewtonChecks {
            ctx,
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            dim: d,
            n_nodes: n,
            n_planes: planes,
            pipelines,
            groups,
            binder,
            sets,
            inversion,
            inversion_finish,
            sizes_init,
            sizes_add,
            balance_finish,
            slot,
        })
    }

    /// One reduction per chunk of classical elements (`chunks`: term and set), each
    /// writing its row of partials (`groups` of them); results go to `slot`.
    fn inversion_ops(
        binder: &Binder,
        elements: &GpuElements,
        chunks: &[(usize, usize)],
        sets: &[SetSpan],
        (groups, slot): (usize, usize),
    ) -> Result<Vec<Op>, GpuError> {
        let mut out = Vec::with_capacity(chunks.len());
        for (row, &(t, k)) in chunks.iter().enumerate() {
            let r = elements
                .term_range(t)
                .ok_or_else(|| GpuError::Mismatch(format!("no element term {t}")))?;
            let (nodes, rest) = elements
                .term_mesh(t)
                .ok_or_else(|| GpuError::Mismatch(format!("element term {t} has no mesh")))?;
            let first = sets[k].first + r.start;
            let p = CheckParams::new(r.len(), MODE_INVERSION, slot, row, first, 0);
            out.push(binder.op(
                &format!("inversion of term {t}"),
                Entry::Reduce,
                p,
                groups,
                Varying {
                    nodes: Some(nodes),
                    rest: Some(rest),
                    ..Varying::default()
                },
            ));
        }
        Ok(out)
    }

    /// One force-size sum per element chunk (`chunks`: term and set), in element order.
    fn sizes_ops(
        binder: &Binder,
        elements: &GpuElements,
        asm: &GpuAssembly,
        chunks: &[(usize, usize)],
    ) -> Result<Vec<Op>, GpuError> {
        let n = elements.n_nodes();
        let mut out = Vec::with_capacity(chunks.len());
        for &(t, _) in chunks {
            let g = asm
                .node_gathers()
                .iter()
                .find(|g| g.term == t)
                .ok_or_else(|| GpuError::Mismatch(format!("element term {t} has no gathers")))?;
            let (egrad, _) = elements
                .term_buffers(t)
                .ok_or_else(|| GpuError::Mismatch(format!("no element term {t}")))?;
            out.push(binder.op(
                &format!("sizes of term {t}"),
                Entry::SizesAdd,
                CheckParams::new(n, 0, 0, 0, 0, 0),
                n,
                Varying {
                    egrad: Some(egrad),
                    offsets: Some(&g.offsets),
                    entries: Some(&g.entries),
                    ..Varying::default()
                },
            ));
        }
        Ok(out)
    }

    /// The result slot of the inversion bound: (α, element, first inverted element, J).
    pub fn inversion_slot(&self) -> usize {
        self.slot
    }

    /// The result slot of the force balance: (residual, node, scale, x_max).
    pub fn balance_slot(&self) -> usize {
        self.slot + 1
    }

    /// `ops` as dispatches, in order.
    fn dispatches(&self, ops: &[&Op]) -> Vec<Dispatch> {
        let launch = self.ctx.launch();
        ops.iter()
            .map(|op| Dispatch {
                pipeline: self.pipelines[op.entry as usize].clone(),
                group: op.group.clone(),
                launch: match op.entry {
                    // Reductions get exactly their workgroups (checked when built).
                    Entry::Reduce => launch.reduction(self.groups as u32, WG),
                    Entry::Finish => launch.reduction(1, WG),
                    Entry::SizesInit | Entry::SizesAdd => launch.grid(op.count as u64, WG),
                },
            })
            .collect()
    }

    /// Records `ops` in one compute pass of `enc`.
    fn record(&self, enc: &mut wgpu::CommandEncoder, label: &str, ops: &[&Op]) {
        let mut cp = self.ctx.compute_pass(enc, label, None);
        for d in self.dispatches(ops) {
            cp.set_pipeline(&d.pipeline);
            cp.set_bind_group(0, &d.group);
            cp.dispatch(d.launch);
        }
    }

    fn write_scalar(&self, slot: usize, v: f64) {
        self.ctx
            .write_buffer(&self.binder.scal, slot as u64 * 8, &to_bytes(true, &[v]));
    }

    /// Records the inversion bound of the step Δx from the accepted iterate x over
    /// (0, `max`] (as `Model::inversion_bound`) into [`NewtonChecks::inversion_slot`].
    pub fn record_inversion_bound(&self, enc: &mut wgpu::CommandEncoder, max: f64) {
        let mut ops: Vec<&Op> = self.inversion.iter().collect();
        ops.push(&self.inversion_finish);
        self.write_scalar(S_MAX, max);
        self.record(enc, "newton inversion bound", &ops);
    }

    /// The dispatches of [`NewtonChecks::record_inversion_bound`] (its bound `max`
    /// written for the next submit), for a caller that records them itself.
    pub fn inversion_dispatches(&self, max: f64) -> Vec<Dispatch> {
        let mut ops: Vec<&Op> = self.inversion.iter().collect();
        ops.push(&self.inversion_finish);
        self.write_scalar(S_MAX, max);
        self.dispatches(&ops)
    }

    /// (set, element) of a global element index lane.
    fn element(&self, lane: f64) -> Result<(usize, usize), GpuError> {
        let bad = || GpuError::Internal(format!("the inversion bound names element {lane}"));
        if !(lane >= 0.0 && lane.fract() == 0.0 && lane < NO_INDEX) {
            return Err(bad());
        }
        let g = lane as usize;
        let k = self.sets.partition_point(|s| s.first <= g).checked_sub(1);
        match k.map(|k| (k, self.sets[k])) {
            Some((k, s)) if s.classical && g - s.first < s.len => Ok((k, g - s.first)),
            _ => Err(bad()),
        }
    }

    /// The inversion bound from the four f64 of its result slot, as `Model::inversion_bound`
    /// returns it; an error when the slot names no classical element.
    pub fn decode_inversion_bound(
        &self,
        lanes: &[f64],
    ) -> Result<Result<Option<InversionLimit>, Inverted>, GpuError> {
        let &[alpha, elem, inverted, j] = lanes else {
            return Err(GpuError::Mismatch(format!(
                "{} values for the inversion bound's four",
                lanes.len()
            )));
        };
        if inverted < NO_INDEX {
            let (set, element) = self.element(inverted)?;
            return Ok(Err(Inverted { set, element, j }));
        }
        if elem < NO_INDEX {
            let (set, element) = self.element(elem)?;
            return Ok(Ok(Some(InversionLimit {
                alpha,
                set,
                element,
            })));
        }
        Ok(Ok(None))
    }

    /// The four f64 of result slot `slot` (one 32-byte download).
    fn read_slot(&self, slot: usize, what: &str) -> Result<Vec<f64>, GpuError> {
        let b = self
            .ctx
            .download(&self.binder.result, slot as u64 * 32, 32, what)?;
        Ok(from_bytes(true, &b))
    }

    fn submit(
        &self,
        label: &str,
        rec: impl FnOnce(&mut wgpu::CommandEncoder),
    ) -> Result<(), GpuError> {
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        rec(&mut enc);
        self.ctx.submit(enc);
        self.ctx.check(label)
    }

    /// [`NewtonChecks::record_inversion_bound`], submitted, read back (32 bytes) and
    /// decoded.
    pub fn inversion_bound(
        &self,
        max: f64,
    ) -> Result<Result<Option<InversionLimit>, Inverted>, GpuError> {
        let label = "newton inversion bound";
        self.submit(label, |enc| self.record_inversion_bound(enc, max))?;
        self.decode_inversion_bound(&self.read_slot(self.inversion_slot(), label)?)
    }

    /// The constraint set `f` on the device (masks, rotation indices and rotations), for
    /// the force balance under it.
    pub fn frames(&self, f: &Frames) -> Result<BalanceFrames, GpuError> {
        let (n, d) = (self.n_nodes, self.dim);
        if f.dim != d || f.n_nodes != n {
            return Err(GpuError::Mismatch(format!(
                "the constraint frames are for {} nodes in {}D, the mesh has {n} in {d}D",
                f.n_nodes, f.dim
            )));
        }
        let frame = frame_words(f)?;
        let frame_buf = self
            .ctx
            .storage_with("newton checks frames", bytemuck::cast_slice(&frame))?;
        let rot_buf = self
            .ctx
            .storage_with("newton checks rotations", &to_bytes(true, &f.rotations))?;
        self.frames_from(&frame_buf, &rot_buf)
    }

    /// [`NewtonChecks::frames`] on buffers already on the device in its layout (the
    /// device PCG's: [`crate::gpu::pcg::DeviceFrames::buffers`], f64 rotations), so a
    /// constraint set is uploaded once for both.
    pub fn frames_from(
        &self,
        frame_buf: &wgpu::Buffer,
        rot_buf: &wgpu::Buffer,
    ) -> Result<BalanceFrames, GpuError> {
        let n = self.n_nodes;
        let reduce = self.binder.op(
            "balance",
            Entry::Reduce,
            CheckParams::new(
                n,
                MODE_BALANCE,
                self.balance_slot(),
                self.inversion.len(),
                0,
                self.n_planes,
            ),
            self.groups,
            Varying {
                frame: Some(frame_buf),
                rotations: Some(rot_buf),
                ..Varying::default()
            },
        );
        self.ctx.check("binding the constraint frames")?;
        Ok(BalanceFrames {
            owner: self.id,
            reduce,
            _frame: frame_buf.clone(),
            _rotations: rot_buf.clone(),
        })
    }

    /// Records the force balance of the accepted iterate x under `frames` in a step of
    /// length `h` (as `force_balance_of`, with x̃ and ∇E as the device holds them and the
    /// element gradients of the last element evaluation, which must be at x) into
    /// [`NewtonChecks::balance_slot`].
    pub fn record_force_balance(
        &self,
        enc: &mut wgpu::CommandEncoder,
        frames: &BalanceFrames,
        h: f64,
    ) -> Result<(), GpuError> {
        let d = self.balance_dispatches(frames, h)?;
        let mut cp = self.ctx.compute_pass(enc, "newton force balance", None);
        for d in d {
            cp.set_pipeline(&d.pipeline);
            cp.set_bind_group(0, &d.group);
            cp.dispatch(d.launch);
        }
        Ok(())
    }

    /// The dispatches of [`NewtonChecks::record_force_balance`] (its h² written for the
    /// next submit), for a caller that records them itself.
    pub fn balance_dispatches(
        &self,
        frames: &BalanceFrames,
        h: f64,
    ) -> Result<Vec<Dispatch>, GpuError> {
        if frames.owner != self.id {
            return Err(GpuError::Mismatch(
                "constraint frames built for other Newton checks".into(),
            ));
        }
        self.write_scalar(S_H2, h * h);
        let mut ops = vec![&self.sizes_init];
        ops.extend(self.sizes_add.iter());
        ops.extend([&frames.reduce, &self.balance_finish]);
        Ok(self.dispatches(&ops))
    }

    /// The force balance from the four f64 of its result slot.
    pub fn decode_force_balance(&self, lanes: &[f64]) -> Result<ForceBalance, GpuError> {
        let &[residual, node, scale, x_max] = lanes else {
            return Err(GpuError::Mismatch(format!(
                "{} values for the force balance's four",
                lanes.len()
            )));
        };
        let node = if node < NO_INDEX {
            if !(node >= 0.0 && node.fract() == 0.0 && (node as usize) < self.n_nodes) {
                return Err(GpuError::Internal(format!(
                    "the force balance names node {node}"
                )));
            }
            node as usize
        } else {
            0
        };
        Ok(ForceBalance {
            residual,
            node,
            scale,
            x_max,
        })
    }

    /// [`NewtonChecks::record_force_balance`], submitted, read back (32 bytes) and
    /// decoded.
    pub fn force_balance(&self, frames: &BalanceFrames, h: f64) -> Result<ForceBalance, GpuError> {
        let label = "newton force balance";
        let mut recorded = Ok(());
        self.submit(label, |enc| {
            recorded = self.record_force_balance(enc, frames, h)
        })?;
        recorded?;
        self.decode_force_balance(&self.read_slot(self.balance_slot(), label)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::device::elements;

    /// The WGSL declarations of bind group 0 are [`NEWTON_CHECKS`]' bindings, in order,
    /// with their access; `CheckParams` is eight u32 in WGSL as in Rust; every entry point
    /// exists; the shader's constants are the host's.
    #[test]
    fn layout_and_params_match_the_wgsl() {
        let size = std::mem::size_of::<CheckParams>();
        let m = kernels::check::layout(&NEWTON_CHECKS, "CheckParams", size, &ENTRIES);
        assert_eq!(
            kernels::check::struct_members(&m, "CheckParams"),
            ["count", "mode", "slot", "row", "first", "n_planes", "_pad0", "_pad1"]
        );
        for (name, want) in [
            ("MODE_INVERSION", MODE_INVERSION),
            ("MODE_BALANCE", MODE_BALANCE),
            ("S_MAX", S_MAX as u32),
            ("S_H2", S_H2 as u32),
            ("S_GNORM", S_GNORM as u32),
            ("S_INF", S_INF as u32),
            // The element terms' layouts these kernels read.
            ("REST_EXTRA", elements::NH_REST_EXTRA as u32),
            ("PLANE_STRIDE", elements::PLANE_STRIDE as u32),
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
        let (_, c) = m
            .constants
            .iter()
            .find(|(_, c)| c.name.as_deref() == Some("NO_INDEX"))
            .expect("no const NO_INDEX");
        match m.global_expressions[c.init] {
            naga::Expression::Literal(naga::Literal::F32(v)) => assert_eq!(v as f64, NO_INDEX),
            ref e => panic!("NO_INDEX = {e:?}"),
        }
    }
}
