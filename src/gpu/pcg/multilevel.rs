//! The multilevel preconditioner on the device (shaders/vcycle.wgsl): the CPU CG's
//! V-cycle ([`crate::solve::multilevel`]) applied as z = M⁻¹r inside the device PCG.
//!
//! The levels' buffers are made once per hierarchy (a mesh): each level's index arrays
//! (clusters, patterns) uploaded, its values (ω, the coarse matrix, P, Pᵀ) and cluster
//! inverses allocated. Their values come from one of two places:
//! - the device itself ([`DeviceMultilevel::compute`], src/gpu/pcg/mlsetup.rs), which
//!   builds or refreshes them from the H the PCG holds: what the device Newton loop does,
//!   with nothing of the mesh's size crossing the bus per Newton iteration;
//! - a [`Multilevel`] built on the host by the CPU CG's code, uploaded
//!   ([`DeviceMultilevel::set`]): what `solve --solver gpu` and the benches do, since they
//!   hold H on the host anyway. Kept levels of the same generation move only their ω.
//!
//! Either way the values are the CPU's operator (the same clusters, pivots dropped and
//! ω, to rounding). This module records the V-cycle's dispatches; level 0's product is
//! the PCG's own (H read in place and rotated), so its matrix is never copied. Per V-cycle
//! and level: two smoothing dispatches, two products, a restriction and a prolongation.

use super::mllevels::{
    index, inverse_chunks, inverse_starts, DeviceLevel, InverseChunk, VcycleParams, WORKGROUP,
};
use super::mlsetup::{DeviceSetup, FinestMatrix};
use crate::core::constraints::Frames;
use crate::gpu::blocks::values_limit;
use crate::gpu::kernels::{self, Access, Layout};
use crate::gpu::{GpuContext, GpuError, Launch};
use crate::solve::multilevel::reuse::Levels;
use crate::solve::multilevel::{Hierarchy, LevelPattern, LevelSizes, LevelView, Multilevel};
use std::sync::Arc;

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/vcycle.wgsl.
pub const VCYCLE: Layout = Layout {
    file: "vcycle.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/vcycle.wgsl")),
    bindings: &[
        ("vp", U),
        ("idx", R),
        ("vals", R),
        ("b", W),
        ("x", W),
        ("ax", W),
        ("bn", W),
        ("xn", W),
        ("state", R),
        ("inv", R),
    ],
};

/// The pipelines of shaders/vcycle.wgsl.
struct Pipelines {
    smooth_pre: wgpu::ComputePipeline,
    smooth_post: wgpu::ComputePipeline,
    level_ax: wgpu::ComputePipeline,
    restrict_down: wgpu::ComputePipeline,
    prolong_up: wgpu::ComputePipeline,
}

/// The PCG's buffers level 0 works in: r (its b), z (its x), q (its A x) and the state.
pub(super) struct Finest<'a> {
    pub r: &'a wgpu::Buffer,
    pub z: &'a wgpu::Buffer,
    pub q: &'a wgpu::Buffer,
    pub state: &'a wgpu::Buffer,
}

/// One dispatch of the V-cycle, or level 0's product (recorded by the PCG).
pub(super) enum Step<'a> {
    Kernel(
        &'static str,
        &'a wgpu::ComputePipeline,
        Launch,
        &'a wgpu::BindGroup,
    ),
    FinestProduct,
}

/// Whose values the levels on the device hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    /// None yet: the levels' buffers were just made for a hierarchy.
    Empty,
    /// A host-built [`Multilevel`] of this [`Multilevel::generation`], uploaded.
    Host((u64, u32)),
    /// Built on the device from the H it holds ([`DeviceSetup`]).
    Device,
}

/// One level's values on the device, read back ([`super::DeviceCg::read_multilevel`]): the
/// arrays of [`LevelView`] in its layouts (ω; the matrix, empty at level 0, whose matrix is
/// the PCG's; the cluster inverses, level 0's with the constrained rows and columns zero;
/// P and Pᵀ, empty at the coarsest level), and where the device built the levels, the
/// power estimate λ̂ of λmax(B⁺A) that ω comes from (the last one made: a kept level's
/// is the estimate of its build, level 0's that of the last refresh).
#[derive(Debug, Clone)]
pub struct LevelValues {
    pub lambda: Option<f64>,
    pub omega: f64,
    pub matrix: Vec<f64>,
    pub inverses: Vec<f64>,
    pub p: Vec<f64>,
    pub pt: Vec<f64>,
}

/// The V-cycle's pipelines and every level's buffers for one hierarchy.
pub(super) struct DeviceMultilevel {
    ctx: GpuContext,
    dim: usize,
    kernels: Arc<VcycleKernels>,
    levels: Vec<DeviceLevel>,
    /// The hierarchy and binding limit the levels were built for.
    hierarchy: Option<(Arc<Hierarchy>, u64)>,
    source: Source,
    /// The kernels and buffers that build the levels on the device, once asked for.
    setup: Option<DeviceSetup>,
}

/// The device bytes of the V-cycle's levels of these sizes
/// ([`crate::solve::multilevel::Hierarchy::level_sizes`]) with `dim` components per item
/// and the cluster inverses split under `forced` (or the adapter's binding limit), each
/// buffer checked against the adapter's limits first: the error names the first that
/// does not fit. What a caller adds to its memory check before building anything.
pub fn multilevel_bytes(
    ctx: &GpuContext,
    sizes: &[LevelSizes],
    dim: usize,
    forced: Option<u64>,
) -> Result<u64, GpuError> {
    let limit = values_limit(ctx, forced);
    // The coarsest level's (unused) next level: two 16-byte placeholders.
    let mut total = 2 * ctx.checked_size("vcycle no level below", 16)?;
    for (l, s) in sizes.iter().enumerate() {
        let label = |what: &str| format!("vcycle level {l} {what}");
        total += ctx.checked_size(&label("indices"), 4 * s.index_words as u64)?;
        total += ctx.checked_size(&label("values"), 8 * s.values as u64)?;
        // Per buffer of inverses, the inverses and their parameters.
        for r in inverse_chunks(&s.inverses, limit, l)? {
            let v: usize = s.inverses[r].iter().sum();
            total += ctx.checked_size(&label("inverses"), 8 * v as u64)?;
            total += std::mem::size_of::<VcycleParams>() as u64;
        }
        // b, x and ax below the finest level (level 0's are the PCG's r, z and q).
        if l > 0 {
            total += 3 * ctx.checked_size(&label("vectors"), 8 * (s.items * dim) as u64)?;
        }
    }
    Ok(total)
}

/// The index arrays of one level, packed, with their offsets (in `idx` words and, for the
/// f64 arrays, in `vals` entries: ω, the matrix below the finest level, P, Pᵀ).
fn pack_indices(
    v: &LevelPattern<'_>,
    d: usize,
    finest: bool,
) -> Result<(Vec<u32>, VcycleParams), GpuError> {
    let u = index;
    let mut idx: Vec<u32> = Vec::new();
    let mut p = VcycleParams {
        n: u(v.n)?,
        clusters: u(v.ptr.len() - 1)?,
        ..Default::default()
    };
    let put = |idx: &mut Vec<u32>, xs: &mut dyn Iterator<Item = usize>| -> Result<u32, GpuError> {
        let at = u(idx.len())?;
        for x in xs {
            idx.push(u(x)?);
        }
        Ok(at)
    };
    p.of_at = put(&mut idx, &mut v.of.iter().map(|&x| x as usize))?;
    p.pos_at = put(&mut idx, &mut v.pos.iter().map(|&x| x as usize))?;
    p.ptr_at = put(&mut idx, &mut v.ptr.iter().copied())?;
    p.items_at = put(&mut idx, &mut v.items.iter().map(|&x| x as usize))?;
    p.inv_start_at = put(&mut idx, &mut inverse_starts(v.ptr, d).into_iter())?;
    let dd = d * d;
    // ω first, then the matrix below the finest level (level 0's is the PCG's own).
    let mut vals = 1usize;
    p.omega_at = 0;
    p.a_at = u(vals)?;
    if !finest {
        p.row_at = put(&mut idx, &mut v.row_ptr.iter().copied())?;
        p.col_at = put(&mut idx, &mut v.col_idx.iter().copied())?;
        vals += v.col_idx.len() * dd;
    }
    if let Some(pr) = &v.to_next {
        p.has_next = 1;
        p.p_ptr_at = put(&mut idx, &mut pr.p_ptr.iter().copied())?;
        p.p_col_at = put(&mut idx, &mut pr.p_col.iter().map(|&x| x as usize))?;
        p.pt_ptr_at = put(&mut idx, &mut pr.pt_ptr.iter().copied())?;
        p.pt_row_at = put(&mut idx, &mut pr.pt.iter().map(|&(i, _)| i as usize))?;
        p.p_at = u(vals)?;
        vals += pr.p_col.len() * dd;
        p.pt_at = u(vals)?;
        vals += pr.p_col.len() * dd;
    }
    u(vals)?;
    Ok((idx, p))
}

/// The f64 arrays of one level but its inverses (ω, the matrix below the finest, P, Pᵀ),
/// in the order of the offsets [`pack_indices`] gives.
fn pack_values(v: &LevelView<'_>, finest: bool) -> Vec<f64> {
    let mut vals = vec![v.omega];
    if !finest {
        vals.extend_from_slice(v.values);
    }
    if let Some(pr) = &v.to_next {
        vals.extend_from_slice(pr.p);
        vals.extend_from_slice(pr.pt_values);
    }
    vals
}

/// One level's cluster inverses, level 0's constrained rows and columns zeroed (`mask`):
/// z's constrained components stay zero whatever the residual there (the CPU's r is zero
/// there, so its z is too).
fn pack_inverses(v: &LevelView<'_>, d: usize, mask: Option<&[u8]>) -> Result<Vec<f64>, GpuError> {
    index(v.inv.len())?;
    let mut inv = v.inv.to_vec();
    let Some(mask) = mask else {
        return Ok(inv);
    };
    for c in 0..v.ptr.len() - 1 {
        let items = &v.items[v.ptr[c]..v.ptr[c + 1]];
        let m = items.len() * d;
        let block = &mut inv[v.inv_start[c]..v.inv_start[c + 1]];
        for (pi, &i) in items.iter().enumerate() {
            for a in 0..d {
                if mask[i as usize] & (1 << a) == 0 {
                    continue;
                }
                let row = pi * d + a;
                for k in 0..m {
                    block[row * m + k] = 0.0;
                    block[k * m + row] = 0.0;
                }
            }
        }
    }
    Ok(inv)
}

/// The bind group layout and pipelines of shaders/vcycle.wgsl for one dimension, built
/// once per device ([`GpuContext::cached`]).
struct VcycleKernels {
    layout: wgpu::BindGroupLayout,
    /// In the iterations, and in a chunk's verification (the VERIFY override).
    pipes: Pipelines,
    verify: Pipelines,
}

impl DeviceMultilevel {
    /// The V-cycle's pipelines for `dim`; levels come with [`DeviceMultilevel::set`] or
    /// [`DeviceMultilevel::compute`].
    pub(super) fn new(ctx: &GpuContext, dim: usize) -> Result<Self, GpuError> {
        VCYCLE.check_adapter(ctx)?;
        let dev = &ctx.device;
        let kernels = ctx.cached(&format!("vcycle pipelines: {dim}D"), || {
            let module = VCYCLE.module(dev, "f64", "f64");
            let (layout, pl) = VCYCLE.layouts(dev, "vcycle");
            let pipes = |verify: bool| {
                let pipe = |entry: &str| {
                    let constants = [
                        ("D", dim as f64),
                        ("WG", WORKGROUP as f64),
                        ("VERIFY", f64::from(u8::from(verify))),
                    ];
                    let label = format!("vcycle {entry} ({dim}D, verify {verify})");
                    kernels::pipeline(dev, &pl, &module, entry, &label, &constants)
                };
                Pipelines {
                    smooth_pre: pipe("smooth_pre"),
                    smooth_post: pipe("smooth_post"),
                    level_ax: pipe("level_ax"),
                    restrict_down: pipe("restrict_down"),
                    prolong_up: pipe("prolong_up"),
                }
            };
            VcycleKernels {
                layout,
                pipes: pipes(false),
                verify: pipes(true),
            }
        })?;
        Ok(DeviceMultilevel {
            ctx: ctx.clone(),
            dim,
            kernels,
            levels: Vec::new(),
            hierarchy: None,
            source: Source::Empty,
            setup: None,
        })
    }

    /// Makes the levels' buffers for `hierarchy` under the binding limit `limit` unless
    /// they are there; true when they were made (their values then are none yet).
    fn ensure_levels(
        &mut self,
        hierarchy: &Arc<Hierarchy>,
        finest: Finest<'_>,
        limit: u64,
    ) -> Result<bool, GpuError> {
        let same = self
            .hierarchy
            .as_ref()
            .is_some_and(|(h, lim)| Arc::ptr_eq(h, hierarchy) && *lim == limit);
        if same {
            return Ok(false);
        }
        self.levels = Vec::new();
        self.setup = None;
        self.source = Source::Empty;
        self.hierarchy = None;
        self.levels = self.build(hierarchy, finest, limit)?;
        self.hierarchy = Some((hierarchy.clone(), limit));
        Ok(true)
    }

    /// Uploads `ml`'s levels for the constraint set `frames`, the inverses split under
    /// `forced` (or the adapter's binding limit): only the smoothing weights when the
    /// device holds `ml`'s generation (kept levels refreshed without new masks: the rest
    /// is the same, and the finest matrix is the PCG's own), the values otherwise (the
    /// buffers made first when `ml`'s hierarchy is not the last call's).
    pub(super) fn set(
        &mut self,
        ml: &Multilevel,
        frames: &Frames,
        finest: Finest<'_>,
        forced: Option<u64>,
    ) -> Result<(), GpuError> {
        let d = self.dim;
        if ml.dim() != d {
            return Err(GpuError::Mismatch(format!(
                "the multilevel preconditioner is {}D, the device PCG {d}D",
                ml.dim()
            )));
        }
        let views = ml.levels();
        if views[0].n != frames.n_nodes {
            return Err(GpuError::Mismatch(format!(
                "the multilevel preconditioner has {} nodes, the constraints {}",
                views[0].n, frames.n_nodes
            )));
        }
        let limit = values_limit(&self.ctx, forced);
        self.ensure_levels(ml.hierarchy(), finest, limit)?;
        let generation = Source::Host(ml.generation());
        if self.source == generation {
            for (lev, v) in self.levels.iter().zip(&views) {
                // ω is the first value of every level (`pack_indices`).
                self.ctx
                    .write_buffer(&lev.vals, 0, bytemuck::cast_slice(&[v.omega]));
            }
            return Ok(());
        }
        self.source = Source::Empty;
        for (l, v) in views.iter().enumerate() {
            let mask = (l == 0).then_some(&frames.mask[..]);
            let vals = pack_values(v, l == 0);
            let inv = pack_inverses(v, d, mask)?;
            let lev = &self.levels[l];
            if vals.len() != lev.vals_len || v.inv_start != inverse_starts(v.ptr, d) {
                return Err(GpuError::Mismatch(
                    "the multilevel values do not have the layout of their hierarchy".into(),
                ));
            }
            self.ctx
                .write_buffer(&lev.vals, 0, bytemuck::cast_slice(&vals));
            for ch in &lev.inverses {
                let r = v.inv_start[ch.clusters.start]..v.inv_start[ch.clusters.end];
                self.ctx
                    .write_buffer(&ch.buffer, 0, bytemuck::cast_slice(&inv[r]));
            }
        }
        self.source = generation;
        Ok(())
    }

    /// Builds or refreshes the levels on the device as `how` says
    /// ([`crate::solve::multilevel::reuse::KeptLevels::plan`]), from the H the PCG holds
    /// (`matrix`) and the constraint set of `frames`: nothing of the mesh's size crosses
    /// the bus (module docs of src/gpu/pcg/mlsetup.rs). Kept or remasked levels must be
    /// the device's own, on the same hierarchy.
    pub(super) fn compute(
        &mut self,
        hierarchy: &Arc<Hierarchy>,
        how: Levels,
        finest: Finest<'_>,
        matrix: &FinestMatrix<'_>,
        forced: Option<u64>,
    ) -> Result<(), GpuError> {
        let limit = values_limit(&self.ctx, forced);
        let fresh = self.ensure_levels(hierarchy, finest, limit)?;
        if how != Levels::Built && (fresh || self.source != Source::Device) {
            return Err(GpuError::Mismatch(
                "kept multilevel levels that the device did not build".into(),
            ));
        }
        if self.setup.is_none() {
            let setup = DeviceSetup::new(&self.ctx, self.dim, hierarchy, &self.levels, matrix)?;
            self.setup = Some(setup);
        }
        self.source = Source::Empty;
        if let Some(setup) = self.setup.as_mut() {
            setup.run(&self.levels, how, matrix)?;
        }
        self.source = Source::Device;
        Ok(())
    }

    /// Every level's values as the V-cycle reads them, read back (tests and diagnostics).
    pub(super) fn read_levels(&self) -> Result<Vec<LevelValues>, GpuError> {
        let lambdas = match (&self.setup, self.source) {
            (Some(setup), Source::Device) => setup.lambdas()?,
            _ => Vec::new(),
        };
        let mut out = Vec::with_capacity(self.levels.len());
        for (l, lev) in self.levels.iter().enumerate() {
            let what = format!("reading back multilevel level {l}");
            let f64s = |b: Vec<u8>| -> Vec<f64> { bytemuck::pod_collect_to_vec(&b) };
            let vals = f64s(
                self.ctx
                    .download(&lev.vals, 0, 8 * lev.vals_len as u64, &what)?,
            );
            let mut inverses = Vec::new();
            for ch in &lev.inverses {
                let bytes = 8 * ch.len as u64;
                inverses.extend(f64s(self.ctx.download(&ch.buffer, 0, bytes, &what)?));
            }
            let p = &lev.params;
            let (a, pa, pta) = (p.a_at as usize, p.p_at as usize, p.pt_at as usize);
            let next = p.has_next != 0;
            out.push(LevelValues {
                lambda: lambdas.get(l).copied(),
                omega: vals[0],
                matrix: vals[a..if next { pa } else { vals.len() }].to_vec(),
                inverses,
                p: if next {
                    vals[pa..pta].to_vec()
                } else {
                    Vec::new()
                },
                pt: if next {
                    vals[pta..].to_vec()
                } else {
                    Vec::new()
                },
            });
        }
        Ok(out)
    }

    /// The levels' buffers for `hierarchy` (values zero but the coarsest level's ω, 1)
    /// and the V-cycle's bind groups over them.
    fn build(
        &self,
        hierarchy: &Hierarchy,
        finest: Finest<'_>,
        limit: u64,
    ) -> Result<Vec<DeviceLevel>, GpuError> {
        let (ctx, d) = (&self.ctx, self.dim);
        let sizes = hierarchy.level_sizes(d);
        let patterns = hierarchy.patterns();
        // b, x, ax of every level below the finest, then a spare pair for the coarsest's
        // (unused) next level.
        let mut vecs: Vec<[wgpu::Buffer; 3]> = Vec::with_capacity(patterns.len());
        for (l, v) in patterns.iter().enumerate().skip(1) {
            let bytes = (8 * v.n * d) as u64;
            let mk = |what: &str| ctx.storage_zeroed(&format!("vcycle level {l} {what}"), bytes);
            vecs.push([mk("b")?, mk("x")?, mk("ax")?]);
        }
        let spare = [
            ctx.storage_zeroed("vcycle no level below (b)", 16)?,
            ctx.storage_zeroed("vcycle no level below (x)", 16)?,
        ];
        let mut levels = Vec::with_capacity(patterns.len());
        for (l, v) in patterns.iter().enumerate() {
            let (idx, p) = pack_indices(v, d, l == 0)?;
            let vals_len = self.values_len(v, l == 0);
            let starts = inverse_starts(v.ptr, d);
            // The sizes the memory checks counted are the sizes packed.
            let want = &sizes[l];
            if (idx.len(), vals_len, starts[starts.len() - 1])
                != (want.index_words, want.values, want.inverses.iter().sum())
            {
                return Err(GpuError::Mismatch(format!(
                    "multilevel level {l}: {} index words, {vals_len} values and {} inverse \
                     values packed, {} and {} counted",
                    idx.len(),
                    starts[starts.len() - 1],
                    want.index_words,
                    want.values
                )));
            }
            let idx_buf = ctx.storage_with(
                &format!("vcycle level {l} indices"),
                bytemuck::cast_slice(&idx),
            )?;
            let vals_buf =
                ctx.storage_zeroed(&format!("vcycle level {l} values"), 8 * vals_len as u64)?;
            if l + 1 == patterns.len() {
                // The coarsest level is solved: ω = 1 (`LevelView::omega`).
                ctx.write_buffer(&vals_buf, 0, bytemuck::cast_slice(&[1.0f64]));
            }
            let mut inverses = Vec::new();
            for (k, r) in inverse_chunks(&want.inverses, limit, l)?
                .into_iter()
                .enumerate()
            {
                let at = starts[r.start]..starts[r.end];
                inverses.push(InverseChunk {
                    unknowns: v.ptr[r.start] * d..v.ptr[r.end] * d,
                    base: at.start,
                    len: at.len(),
                    buffer: ctx.storage_zeroed(
                        &format!("vcycle level {l} inverses {k}"),
                        8 * at.len() as u64,
                    )?,
                    clusters: r,
                });
            }
            let (b, x, ax) = if l == 0 {
                (finest.r, finest.z, finest.q)
            } else {
                let v = &vecs[l - 1];
                (&v[0], &v[1], &v[2])
            };
            let (bn, xn) = match vecs.get(l) {
                Some(v) => (&v[0], &v[1]),
                None => (&spare[0], &spare[1]),
            };
            let mut keep = Vec::new();
            let mut groups = Vec::with_capacity(inverses.len());
            for (k, ch) in inverses.iter().enumerate() {
                let u = index;
                let pk = VcycleParams {
                    t_begin: u(ch.unknowns.start)?,
                    t_end: u(ch.unknowns.end)?,
                    inv_base: u(ch.base)?,
                    ..p
                };
                let params = ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(&format!("vcycle level {l} params {k}")),
                    contents: bytemuck::bytes_of(&pk),
                    usage: wgpu::BufferUsages::UNIFORM,
                });
                let bufs = [
                    &params,
                    &idx_buf,
                    &vals_buf,
                    b,
                    x,
                    ax,
                    bn,
                    xn,
                    finest.state,
                    &ch.buffer,
                ];
                groups.push(kernels::bind_group(
                    &ctx.device,
                    &self.kernels.layout,
                    &format!("vcycle level {l} inverses {k}"),
                    &bufs,
                ));
                keep.push(params);
            }
            if l > 0 {
                keep.extend(vecs[l - 1].iter().cloned());
            }
            if l + 1 == patterns.len() {
                keep.extend(spare.iter().cloned());
            }
            levels.push(DeviceLevel {
                n: v.n,
                clusters: v.ptr.len() - 1,
                idx: idx_buf,
                params: p,
                vals: vals_buf,
                vals_len,
                inverses,
                groups,
                _keep: keep,
            });
        }
        ctx.check("making the multilevel preconditioner's buffers")?;
        Ok(levels)
    }

    /// The f64 values of one level but its inverses (ω, the matrix below the finest, P
    /// and Pᵀ).
    fn values_len(&self, v: &LevelPattern<'_>, finest: bool) -> usize {
        let dd = self.dim * self.dim;
        let a = if finest { 0 } else { v.col_idx.len() * dd };
        let p = v.to_next.map_or(0, |pr| 2 * pr.p_col.len() * dd);
        1 + a + p
    }

    /// Whether levels are on the device.
    pub(super) fn is_set(&self) -> bool {
        !self.levels.is_empty()
    }

    /// Clusters per level, finest first.
    pub(super) fn cluster_counts(&self) -> Vec<usize> {
        self.levels.iter().map(|l| l.clusters).collect()
    }

    /// Buffers of cluster inverses per level, finest first.
    pub(super) fn inverse_chunk_counts(&self) -> Vec<usize> {
        self.levels.iter().map(|l| l.inverses.len()).collect()
    }

    /// The dispatches of one V-cycle z = M⁻¹r, level 0's products left to the PCG. Each
    /// smoothing runs once per buffer of inverses, over that buffer's items. With
    /// `verify` the kernels of a chunk's verification, which run only while the PCG checks
    /// a converged recurrence's true residual.
    pub(super) fn steps(&self, verify: bool) -> Vec<Step<'_>> {
        let limits = self.ctx.launch();
        let policy = self.ctx.segments();
        let launch = |items: usize| {
            policy.launch(
                &limits,
                (items as u64).div_ceil(WORKGROUP as u64),
                WORKGROUP,
            )
        };
        let p = if verify {
            &self.kernels.verify
        } else {
            &self.kernels.pipes
        };
        let nl = self.levels.len();
        let product = |l: usize| -> Step<'_> {
            if l == 0 {
                Step::FinestProduct
            } else {
                let lev = &self.levels[l];
                Step::Kernel("ml level_ax", &p.level_ax, launch(lev.n), &lev.groups[0])
            }
        };
        let smoothing = |l: usize, post: bool| -> Vec<Step<'_>> {
            let lev = &self.levels[l];
            let (name, pipe) = if post {
                ("ml smooth_post", &p.smooth_post)
            } else {
                ("ml smooth_pre", &p.smooth_pre)
            };
            lev.inverses
                .iter()
                .zip(&lev.groups)
                .map(|(ch, g)| {
                    // One invocation per item: its D rows of the cluster's inverse.
                    let items = ch.unknowns.len() / self.dim;
                    Step::Kernel(name, pipe, launch(items), g)
                })
                .collect()
        };
        let mut steps = Vec::new();
        for (l, lev) in self.levels.iter().enumerate() {
            steps.extend(smoothing(l, false));
            if l + 1 == nl {
                break;
            }
            steps.push(product(l));
            steps.push(Step::Kernel(
                "ml restrict",
                &p.restrict_down,
                launch(lev.clusters),
                &lev.groups[0],
            ));
        }
        for (l, lev) in self.levels.iter().enumerate().rev().skip(1) {
            steps.push(Step::Kernel(
                "ml prolong",
                &p.prolong_up,
                launch(lev.n),
                &lev.groups[0],
            ));
            steps.push(product(l));
            steps.extend(smoothing(l, true));
        }
        steps
    }

    /// Bytes the V-cycle's kernels read or write at the least per application, level 0's
    /// products excluded (the PCG counts those).
    pub(super) fn bytes_per_cycle(&self) -> u64 {
        // Each level's inverses are read twice (both smoothings), its other values about
        // twice (the restriction and prolongation read P once each, the products A twice)
        // and its vectors a few times.
        self.levels
            .iter()
            .map(|l| {
                let inv: u64 = l.inverses.iter().map(|c| c.buffer.size()).sum();
                2 * inv + 16 * l.vals_len as u64 + 8 * 6 * (l.n * self.dim) as u64
            })
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bind group 0 is [`VCYCLE`]'s bindings in order and the params struct has Rust's
    /// size.
    #[test]
    fn layout_and_params_match_the_wgsl() {
        let entries = [
            "smooth_pre",
            "smooth_post",
            "level_ax",
            "restrict_down",
            "prolong_up",
        ];
        let size = std::mem::size_of::<VcycleParams>();
        kernels::check::layout(&VCYCLE, "VcycleParams", size, &entries);
    }
}
