//! The device PCG's kernels, one family per shader file (all four share
//! shaders/pcg_common.wgsl and one bind group): the product (`pcg_product.wgsl`), the
//! updates and their scalars (`pcg_update.wgsl`) and the coarse spaces
//! (`pcg_coarse.wgsl`). Each family owns its pipelines, specialized by the preconditioner
//! ([`Pre`]), the coarse space ([`Co`]) and the [`Mode`] (WGSL overrides), compiled the
//! first time a solve asks for them: a solve with Jacobi and the aggregates compiles the
//! dozen it runs, not every combination.

use crate::gpu::kernels::{self, Access, Layout, Real};
use crate::gpu::{GpuContext, GpuError, Phase};
use std::sync::OnceLock;

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Uniform parameters of every kernel (mirrors `PcgParams` in the WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct PcgParams {
    pub(super) n_nodes: u32,
    pub(super) n_partials: u32,
    pub(super) col_at: u32,
    pub(super) diag_at: u32,
    /// The values chunk of the dispatch: rows, first block, index.
    pub(super) row_begin: u32,
    pub(super) row_end: u32,
    pub(super) block_first: u32,
    pub(super) chunk: u32,
}
const _: () = assert!(std::mem::size_of::<PcgParams>() == 32);

/// Workgroup size of every kernel.
pub(super) const WORKGROUP: u32 = 64;

/// The scalar types of one PCG: `real` for H, the frames and the vectors (H's own),
/// `acc` for every sum and scalar (f64 wherever the device has SHADER_F64), and whether
/// the product takes the difference form (f32 only; see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Scalars {
    pub real: Real,
    pub acc: Real,
    pub difference: bool,
}

impl Scalars {
    /// f64 throughout: the Newton loop's.
    pub const F64: Scalars = Scalars {
        real: Real::F64,
        acc: Real::F64,
        difference: false,
    };

    /// `real` vectors on `ctx`: f64 sums where it has SHADER_F64, else f32 (refused for
    /// f64 vectors).
    pub fn on(ctx: &GpuContext, real: Real, difference: bool) -> Result<Self, GpuError> {
        let acc = if ctx.has_f64() { Real::F64 } else { Real::F32 };
        if real == Real::F64 && acc == Real::F32 {
            return Err(GpuError::Unsupported(format!(
                "{} has no SHADER_F64: the device PCG cannot run in f64 there",
                ctx.adapter_name()
            )));
        }
        Ok(Scalars {
            real,
            acc,
            difference: difference && real == Real::F32,
        })
    }
}

/// Bind group 0 of every PCG shader file (shaders/pcg_common.wgsl declares it).
const BINDINGS: &[(&str, Access)] = &[
    ("params", U),
    ("pattern", R),
    ("hvals", R),
    ("grad", R),
    ("frame", R),
    ("rotations", R),
    ("y", W),
    ("r", W),
    ("z", W),
    ("p", W),
    ("q", W),
    ("b", W),
    ("minv", W),
    ("dx", W),
    ("partials", W),
    ("scal", W),
    ("state", W),
    ("aggregates", R),
    ("coarse", W),
    ("pw", W),
    ("rowsum", R),
];

macro_rules! pcg_source {
    ($file:literal) => {
        concat!(
            include_str!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/shaders/pcg_common.wgsl"
            )),
            include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/", $file))
        )
    };
}

/// The product q = Ĥp with its p·q, the world-frame copies and the recovery of Δx.
pub const PCG_PRODUCT: Layout = Layout {
    file: "pcg_product.wgsl",
    source: pcg_source!("pcg_product.wgsl"),
    bindings: BINDINGS,
};

/// b̂, the preconditioners, the (re)starts and the iteration's updates with their scalars.
pub const PCG_UPDATE: Layout = Layout {
    file: "pcg_update.wgsl",
    source: pcg_source!("pcg_update.wgsl"),
    bindings: BINDINGS,
};

/// The coarse spaces: E of the translations, the aggregates' E, Zᵀr and E⁺w.
pub const PCG_COARSE: Layout = Layout {
    file: "pcg_coarse.wgsl",
    source: pcg_source!("pcg_coarse.wgsl"),
    bindings: BINDINGS,
};

/// The preconditioner a kernel applies (the PRECOND override).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pre {
    None,
    Jacobi,
    BlockJacobi,
    Multilevel,
}

/// The coarse correction added to it (the COARSE override).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Co {
    None,
    Translations,
    Aggregates,
}

/// When a kernel runs (the VERIFY override): in the iterations, until the stop flag is
/// set; or in a chunk's verification, only once the recurrence has met the tolerance and
/// before its true residual has been checked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Iterate,
    Verify,
}

impl Pre {
    fn code(self) -> u32 {
        self as u32
    }
}

impl Co {
    fn code(self) -> u32 {
        self as u32
    }
}

/// Specializations of one entry point: preconditioner × coarse space × mode.
const VARIANTS: usize = 4 * 3 * 2;

fn variant(pre: Pre, co: Co, mode: Mode) -> usize {
    (pre.code() as usize * 3 + co.code() as usize) * 2 + mode as usize
}

/// One shader file compiled for one scalar specialization, its entry points' pipelines
/// made on first use.
pub(super) struct Family {
    layout: &'static Layout,
    module: wgpu::ShaderModule,
    pipeline_layout: wgpu::PipelineLayout,
    dim: usize,
    items: u32,
    hist: u32,
    difference: bool,
    entries: Vec<(&'static str, [OnceLock<wgpu::ComputePipeline>; VARIANTS])>,
}

impl Family {
    fn new(
        dev: &wgpu::Device,
        layout: &'static Layout,
        pl: wgpu::PipelineLayout,
        spec: &Spec,
        entries: &[&'static str],
    ) -> Self {
        Family {
            layout,
            module: layout.module(dev, spec.ty.real.name(), spec.ty.acc.name()),
            pipeline_layout: pl,
            dim: spec.dim,
            items: spec.items,
            hist: spec.hist,
            difference: spec.ty.difference,
            entries: entries
                .iter()
                .map(|&e| (e, std::array::from_fn(|_| OnceLock::new())))
                .collect(),
        }
    }

    /// The pipeline of `entry` for (pre, co, mode), compiled the first time.
    fn get(
        &self,
        ctx: &GpuContext,
        entry: &'static str,
        pre: Pre,
        co: Co,
        mode: Mode,
    ) -> wgpu::ComputePipeline {
        let cells = &self
            .entries
            .iter()
            .find(|(e, _)| *e == entry)
            .unwrap_or_else(|| panic!("{} has no entry point {entry}", self.layout.file))
            .1;
        cells[variant(pre, co, mode)]
            .get_or_init(|| {
                let _compiling = ctx.phase(Phase::PipelineCreation);
                self.build(&ctx.device, entry, pre, co, mode)
            })
            .clone()
    }

    fn build(
        &self,
        dev: &wgpu::Device,
        entry: &str,
        pre: Pre,
        co: Co,
        mode: Mode,
    ) -> wgpu::ComputePipeline {
        // SUM_LANES: a start sums three values in one tree, no kernel more; the
        // translations' correction sums r·z, r·r and Zᵀr (2 + D) in one, coarse_e E's D²
        // in trees of five.
        let wide = co == Co::Translations || entry.starts_with("coarse_e");
        let lanes = match (wide, self.dim) {
            (false, _) => 3.0,
            (true, 3) => 5.0,
            (true, _) => 4.0,
        };
        let constants = [
            ("D", self.dim as f64),
            ("WG", WORKGROUP as f64),
            ("SUM_LANES", lanes),
            ("PRECOND", pre.code() as f64),
            ("COARSE", co.code() as f64),
            ("ITEMS", self.items as f64),
            ("HIST", self.hist as f64),
            ("DIFF", f64::from(u8::from(self.difference))),
            ("VERIFY", f64::from(u8::from(mode == Mode::Verify))),
        ];
        let label = format!(
            "pcg {entry} ({}D, {pre:?}, coarse {co:?}, {mode:?})",
            self.dim
        );
        kernels::pipeline(
            dev,
            &self.pipeline_layout,
            &self.module,
            entry,
            &label,
            &constants,
        )
    }
}

/// What the pipelines of one PCG are specialized for.
pub(super) struct Spec {
    pub ty: Scalars,
    pub dim: usize,
    pub items: u32,
    pub hist: u32,
}

const PRODUCT_ENTRIES: &[&str] = &["matvec", "world_y", "world_z", "recover"];
const UPDATE_ENTRIES: &[&str] = &[
    "rhs",
    "rhs_given",
    "precond",
    "init",
    "scalar_start",
    "update_yr",
    "update_p",
    "start_p",
    "ml_dot",
    "ml_start",
    "verified",
];
const COARSE_ENTRIES: &[&str] = &[
    "coarse_e",
    "coarse_e_sum",
    "agg_rows",
    "agg_e",
    "agg_restrict",
    "agg_solve",
];

/// The product family: matvec (q = Ĥp, the p·q partials), world_y (p = y, pw = V P y:
/// the true residual's product), world_z (pw = V P z: the V-cycle's level-0 product),
/// recover (Δx = V P y).
pub(super) struct ProductKernels(Family);

/// The updates family: rhs and rhs_given (b̂ and ‖b̂‖²), precond, init and scalar_start
/// (a start), update_yr and update_p (an iteration), start_p, ml_dot and ml_start (the
/// multilevel preconditioner's r·z), verified (a verification's end).
pub(super) struct UpdateKernels(Family);

/// The coarse family: coarse_e and coarse_e_sum (E of the translations), agg_rows and
/// agg_e (the aggregates' E), agg_restrict (w = Zᵀr) and agg_solve (c = E⁺w).
pub(super) struct CoarseKernels(Family);

/// The bind group layout of the PCG's files and their families: what
/// [`super::DeviceCg::new`] takes from the device's cache ([`crate::gpu::GpuContext::cached`]).
pub(super) struct Kernels {
    pub layout: wgpu::BindGroupLayout,
    pub product: ProductKernels,
    pub update: UpdateKernels,
    pub coarse: CoarseKernels,
}

impl Kernels {
    pub(super) fn build(dev: &wgpu::Device, spec: &Spec) -> Kernels {
        let (layout, pl) = PCG_UPDATE.layouts(dev, "pcg");
        let product = ProductKernels(Family::new(
            dev,
            &PCG_PRODUCT,
            pl.clone(),
            spec,
            PRODUCT_ENTRIES,
        ));
        let update = UpdateKernels(Family::new(
            dev,
            &PCG_UPDATE,
            pl.clone(),
            spec,
            UPDATE_ENTRIES,
        ));
        let coarse = CoarseKernels(Family::new(dev, &PCG_COARSE, pl, spec, COARSE_ENTRIES));
        Kernels {
            layout,
            product,
            update,
            coarse,
        }
    }
}

use Mode::Iterate;

impl ProductKernels {
    pub fn matvec(&self, ctx: &GpuContext, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "matvec", Pre::None, Co::None, mode)
    }
    pub fn world_y(&self, ctx: &GpuContext, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "world_y", Pre::None, Co::None, mode)
    }
    pub fn world_z(&self, ctx: &GpuContext, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "world_z", Pre::None, Co::None, mode)
    }
    /// `Verify`: only where the last verification met the tolerance.
    pub fn recover(&self, ctx: &GpuContext, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "recover", Pre::None, Co::None, mode)
    }
}

impl UpdateKernels {
    pub fn rhs(&self, ctx: &GpuContext, given: bool) -> wgpu::ComputePipeline {
        let entry = if given { "rhs_given" } else { "rhs" };
        self.0.get(ctx, entry, Pre::None, Co::None, Iterate)
    }
    pub fn precond(&self, ctx: &GpuContext) -> wgpu::ComputePipeline {
        self.0.get(ctx, "precond", Pre::None, Co::None, Iterate)
    }
    pub fn init(&self, ctx: &GpuContext, pre: Pre, co: Co, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "init", pre, co, mode)
    }
    pub fn scalar_start(&self, ctx: &GpuContext, co: Co, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "scalar_start", Pre::None, co, mode)
    }
    pub fn update_yr(&self, ctx: &GpuContext, pre: Pre, co: Co) -> wgpu::ComputePipeline {
        self.0.get(ctx, "update_yr", pre, co, Iterate)
    }
    pub fn update_p(&self, ctx: &GpuContext, co: Co) -> wgpu::ComputePipeline {
        self.0.get(ctx, "update_p", Pre::None, co, Iterate)
    }
    pub fn start_p(&self, ctx: &GpuContext, co: Co, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "start_p", Pre::None, co, mode)
    }
    pub fn ml_dot(&self, ctx: &GpuContext) -> wgpu::ComputePipeline {
        self.0
            .get(ctx, "ml_dot", Pre::Multilevel, Co::None, Iterate)
    }
    pub fn ml_start(&self, ctx: &GpuContext, mode: Mode) -> wgpu::ComputePipeline {
        self.0.get(ctx, "ml_start", Pre::Multilevel, Co::None, mode)
    }
    pub fn verified(&self, ctx: &GpuContext) -> wgpu::ComputePipeline {
        self.0
            .get(ctx, "verified", Pre::None, Co::None, Mode::Verify)
    }
}

impl CoarseKernels {
    pub fn coarse_e(&self, ctx: &GpuContext) -> wgpu::ComputePipeline {
        self.0.get(ctx, "coarse_e", Pre::None, Co::None, Iterate)
    }
    pub fn coarse_e_sum(&self, ctx: &GpuContext) -> wgpu::ComputePipeline {
        self.0
            .get(ctx, "coarse_e_sum", Pre::None, Co::None, Iterate)
    }
    pub fn agg_rows(&self, ctx: &GpuContext) -> wgpu::ComputePipeline {
        self.0
            .get(ctx, "agg_rows", Pre::None, Co::Aggregates, Iterate)
    }
    pub fn agg_e(&self, ctx: &GpuContext) -> wgpu::ComputePipeline {
        self.0.get(ctx, "agg_e", Pre::None, Co::Aggregates, Iterate)
    }
    pub fn agg_restrict(&self, ctx: &GpuContext, mode: Mode) -> wgpu::ComputePipeline {
        self.0
            .get(ctx, "agg_restrict", Pre::None, Co::Aggregates, mode)
    }
    pub fn agg_solve(&self, ctx: &GpuContext, mode: Mode) -> wgpu::ComputePipeline {
        self.0
            .get(ctx, "agg_solve", Pre::None, Co::Aggregates, mode)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::kernels::check;

    const FAMILIES: [(&Layout, &[&str]); 3] = [
        (&PCG_PRODUCT, PRODUCT_ENTRIES),
        (&PCG_UPDATE, UPDATE_ENTRIES),
        (&PCG_COARSE, COARSE_ENTRIES),
    ];

    /// Every shader file is well typed in every precision the PCG instantiates: f64, and
    /// f32 vectors with f64 or (a device without SHADER_F64) f32 accumulators.
    #[test]
    fn every_precision_parses() {
        for (layout, _) in FAMILIES {
            for (real, acc) in [("f64", "f64"), ("f32", "f64"), ("f32", "f32")] {
                let m = check::module(layout, real, acc);
                naga::valid::Validator::new(
                    naga::valid::ValidationFlags::all(),
                    naga::valid::Capabilities::all(),
                )
                .validate(&m)
                .unwrap_or_else(|e| panic!("{} ({real}/{acc}): {e:?}", layout.file));
            }
        }
    }

    /// Every file's bind group 0 is the PCG's bindings in order with their access, the
    /// params struct has Rust's size, every entry point a family asks for exists, and
    /// every aggregate header constant has Rust's value (the CG's slots come from the
    /// prelude, `gpu::kernels::slots`).
    #[test]
    fn layouts_params_entries_and_headers_match_the_wgsl() {
        use crate::gpu::pcg::aggregates::header as h;
        let size = std::mem::size_of::<PcgParams>();
        for (layout, entries) in FAMILIES {
            let m = check::layout(layout, "PcgParams", size, entries);
            let agg = [
                ("AGG_COUNT", h::COUNT),
                ("AGG_K", h::K),
                ("AGG_OF", h::OF),
                ("AGG_PTR", h::PTR),
                ("AGG_NODES", h::NODES),
                ("AGG_SLOT_PTR", h::SLOT_PTR),
                ("AGG_SLOT_OF", h::SLOT_OF),
                ("AGG_PAIR_PTR", h::PAIR_PTR),
                ("AGG_PAIR_SLOTS", h::PAIR_SLOTS),
                ("AGG_PAIR_OF", h::PAIR_OF),
                ("AGG_E", h::E),
                ("AGG_EINV", h::EINV),
                ("AGG_W", h::W),
                ("AGG_C", h::C),
            ];
            for (name, want) in agg {
                let (_, c) = m
                    .constants
                    .iter()
                    .find(|(_, c)| c.name.as_deref() == Some(name))
                    .unwrap_or_else(|| panic!("{}: no const {name}", layout.file));
                match m.global_expressions[c.init] {
                    naga::Expression::Literal(naga::Literal::U32(v)) => {
                        assert_eq!(v, want, "{name}")
                    }
                    ref e => panic!("{name} = {e:?}"),
                }
            }
        }
    }
}
