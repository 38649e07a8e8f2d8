//! WGSL sources, their bind-group layouts, the constants Rust and WGSL share, and the
//! scalar-type prelude.
//!
//! WGSL `override` constants specialize values (block size D, workgroup size, masking,
//! preconditioner kind) but cannot change types, so the scalar types come from a one-line
//! alias prelude: `real` (vector and matrix storage) and `acc` (reduction accumulators,
//! f64 wherever the device has SHADER_F64), followed by the constants of [`SHARED`] and the
//! declarations every kernel shares (shaders/common.wgsl: the `Params` uniform, the
//! workgroup size and the one workgroup reduction).
//!
//! Each shader's bind group 0 is described once, by a [`Layout`] beside the Rust struct
//! that owns the shader's pipelines (`gpu::pcg`, `sim::device`): the bind-group layout is
//! built from it, and a test beside it checks the WGSL declarations against it
//! (`kernels::check`, in test builds).

/// Shared declarations, prepended to every kernel by [`prelude`].
pub const COMMON: &str = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/common.wgsl"));

/// The one slot table of the device PCG's scalar array `scal` (acc), state array `state`
/// (u32) and partial sums (`partials[slot · G + segment]`): src/gpu/pcg/ drives
/// shaders/pcg_*.wgsl; each slot below says who writes and who reads it. The prelude
/// declares every one as a WGSL `const` of the same name.
pub mod slots {
    /// ρ = r·z: scalar_start, update_p's first workgroup; read by update_yr.
    pub const SCAL_RHO: u32 = 0;
    /// ρ of the segment a device PCG segment resumes (host, rescaled; scalar_start).
    pub const SCAL_RHO_PREV: u32 = 1;
    /// p·q of the last α (the curvature reported when it is not positive): update_yr.
    pub const SCAL_PQ: u32 = 2;
    /// α: update_yr's first workgroup (the Lanczos history's).
    pub const SCAL_ALPHA: u32 = 3;
    /// r·r of the last reduction: update_p, scalar_start (the true residual).
    pub const SCAL_RR: u32 = 4;
    /// The factor by which a resumed segment rescales p (host; 0: a fresh start).
    pub const SCAL_PSCALE: u32 = 5;
    /// β: update_p's first workgroup; scalar_start for start_p.
    pub const SCAL_BETA: u32 = 6;
    /// tol² (host, or scalar_start from the rule) and ‖b̂‖² (scalar_start): the
    /// threshold on r·r is their product.
    pub const SCAL_TOL2: u32 = 7;
    pub const SCAL_BB: u32 = 8;
    /// The ρ the last α used (update_yr), what update_p's β divides by.
    pub const SCAL_RHO_OLD: u32 = 9;
    /// The relative tolerance of the solve (host, or scalar_start from the rule).
    pub const SCAL_ETA: u32 = 10;
    /// 1 while the tolerance rule (SCAL_RULE_*) is still to be evaluated by the next
    /// start (host; scalar_start clears it).
    pub const SCAL_RULE_ON: u32 = 11;
    /// The coarse correction on the translations: c = E⁺Zᵀr (D values: update_p,
    /// scalar_start), E⁺ (D², from the host), E = ZᵀĤZ unsymmetrized (D², row-major:
    /// coarse_e_sum), per world axis 2^-64 · Σ|entries| of the rows of component a of
    /// ZᵀĤ's blocks (D: coarse_e_sum). E and its sums are read with every status (the
    /// host asks whether a translation is pinned by nothing).
    pub const SCAL_C: u32 = 12;
    pub const SCAL_EINV: u32 = 15;
    pub const SCAL_E: u32 = 24;
    pub const SCAL_EABS: u32 = 33;
    /// The slots read back with every status: everything before this.
    pub const STATUS_SCAL: u32 = 36;
    /// The tolerance rule (host; src/solve/tolerance.rs, `ToleranceRule::Ratio`): ‖b̂‖
    /// of the previous system, γ, the guard (0: none), η_lo, η_hi.
    pub const SCAL_RULE_PREV: u32 = 36;
    pub const SCAL_RULE_GAMMA: u32 = 37;
    pub const SCAL_RULE_GUARD: u32 = 38;
    pub const SCAL_RULE_LO: u32 = 39;
    pub const SCAL_RULE_HI: u32 = 40;
    /// First slot of the Lanczos coefficient history: α_j at SCAL_HIST + 2j, β_{j+1} at
    /// SCAL_HIST + 2j + 1 (update_p's first workgroup). The slots before it are the
    /// fixed scalars.
    pub const SCAL_HIST: u32 = 48;
    /// A converged or stopped CG: every later iteration dispatch of the submit is a
    /// no-op.
    pub const STATE_DONE: u32 = 0;
    /// Non-positive curvature met.
    pub const STATE_HALT: u32 = 1;
    /// The recurrence residual met the tolerance (or a start's true residual did).
    pub const STATE_CONVERGED: u32 = 2;
    /// A non-finite ρ or r·r.
    pub const STATE_BREAKDOWN: u32 = 3;
    /// The true residual of the converged recurrence has been computed (`verified`).
    pub const STATE_VERIFIED: u32 = 4;
    /// ... and met the tolerance: the verified `recover` has formed Δx.
    pub const STATE_TRUE_OK: u32 = 5;
    /// The run's flags: the words before this, cleared together by the host.
    pub const STATE_FLAGS: u32 = 6;
    /// Set by `prepare` (shaders/coarse_factor.wgsl) when the aggregates' coarse matrix
    /// has a pivot that is not positive and finite: E⁺ must come from the host. Read back
    /// with every status; a run's start leaves it (it zeroes the other words).
    pub const STATE_COARSE_FAILED: u32 = 6;
    /// Iterations done (update_p's first workgroup).
    pub const STATE_ITERS: u32 = 8;
    /// Length of `state`.
    pub const N_STATE: u32 = 12;
    /// Partial-sum slots: p·q (the product), r·z and r·r (the updates, init), Zᵀr (D
    /// slots from PART_ZR, with the coarse correction on the translations), ‖b̂‖² (rhs),
    /// then E (D² slots) and its rows' absolute sums (D slots) of coarse_e.
    pub const PART_PQ: u32 = 0;
    pub const PART_RZ: u32 = 1;
    pub const PART_RR: u32 = 2;
    pub const PART_ZR: u32 = 3;
    pub const PART_BB: u32 = 6;
    pub const PART_E: u32 = 7;
    /// Partial-sum slots.
    pub const N_PART: u32 = 19;
    /// Where the per-invocation sums carried between H's chunks start (×
    /// partials per slot), and how many each invocation carries.
    pub const PART_CARRY: u32 = N_PART;
    pub const CARRY_LEN: u32 = 12;

    // The slot ranges do not overlap (D ≤ 3).
    const _: () = assert!(SCAL_RULE_ON < SCAL_C);
    const _: () = assert!(
        SCAL_C + 3 <= SCAL_EINV
            && SCAL_EINV + 9 <= SCAL_E
            && SCAL_E + 9 <= SCAL_EABS
            && SCAL_EABS + 3 <= STATUS_SCAL
            && STATUS_SCAL <= SCAL_RULE_PREV
            && SCAL_RULE_HI < SCAL_HIST
    );
    const _: () = assert!(STATE_TRUE_OK < STATE_FLAGS && STATE_FLAGS <= STATE_COARSE_FAILED);
    const _: () = assert!(STATE_COARSE_FAILED < STATE_ITERS && STATE_ITERS < N_STATE);
    const _: () = assert!(PART_ZR + 3 <= PART_BB && PART_BB < PART_E && PART_E + 12 <= N_PART);
    // coarse_e carries E and the absolute sums.
    const _: () = assert!(CARRY_LEN == 12);
}

/// The u32 constants every kernel sees under these names (WGSL `const`s in the prelude).
pub const SHARED: &[(&str, u32)] = &[
    ("SCAL_RHO", slots::SCAL_RHO),
    ("SCAL_RHO_PREV", slots::SCAL_RHO_PREV),
    ("SCAL_PQ", slots::SCAL_PQ),
    ("SCAL_ALPHA", slots::SCAL_ALPHA),
    ("SCAL_RR", slots::SCAL_RR),
    ("SCAL_PSCALE", slots::SCAL_PSCALE),
    ("SCAL_HIST", slots::SCAL_HIST),
    ("STATE_DONE", slots::STATE_DONE),
    ("STATE_HALT", slots::STATE_HALT),
    ("STATE_ITERS", slots::STATE_ITERS),
    ("STATE_CONVERGED", slots::STATE_CONVERGED),
    ("STATE_BREAKDOWN", slots::STATE_BREAKDOWN),
    ("STATE_COARSE_FAILED", slots::STATE_COARSE_FAILED),
    ("PART_PQ", slots::PART_PQ),
    ("PART_RZ", slots::PART_RZ),
    ("PART_RR", slots::PART_RR),
    ("PART_ZR", slots::PART_ZR),
    ("SCAL_BETA", slots::SCAL_BETA),
    ("SCAL_TOL2", slots::SCAL_TOL2),
    ("SCAL_BB", slots::SCAL_BB),
    ("SCAL_RHO_OLD", slots::SCAL_RHO_OLD),
    ("SCAL_ETA", slots::SCAL_ETA),
    ("SCAL_RULE_ON", slots::SCAL_RULE_ON),
    ("SCAL_RULE_PREV", slots::SCAL_RULE_PREV),
    ("SCAL_RULE_GAMMA", slots::SCAL_RULE_GAMMA),
    ("SCAL_RULE_GUARD", slots::SCAL_RULE_GUARD),
    ("SCAL_RULE_LO", slots::SCAL_RULE_LO),
    ("SCAL_RULE_HI", slots::SCAL_RULE_HI),
    ("STATE_VERIFIED", slots::STATE_VERIFIED),
    ("STATE_TRUE_OK", slots::STATE_TRUE_OK),
    ("SCAL_C", slots::SCAL_C),
    ("SCAL_EINV", slots::SCAL_EINV),
    ("SCAL_E", slots::SCAL_E),
    ("SCAL_EABS", slots::SCAL_EABS),
    ("PART_BB", slots::PART_BB),
    ("PART_E", slots::PART_E),
    ("PART_CARRY", slots::PART_CARRY),
    ("CARRY_LEN", slots::CARRY_LEN),
    ("NO_ROTATION", crate::core::constraints::NO_ROTATION),
    ("NO_AGGREGATE", crate::solve::coarse::NO_AGGREGATE),
];

/// How a kernel uses a binding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    Uniform,
    Read,
    ReadWrite,
}

/// Bind group 0 of one shader file: the bindings in `@binding` order, by their WGSL names.
#[derive(Debug)]
pub struct Layout {
    pub file: &'static str,
    pub source: &'static str,
    pub bindings: &'static [(&'static str, Access)],
}

impl Layout {
    /// Storage buffers bound by this shader's kernels.
    pub fn storage_bindings(&self) -> u32 {
        self.bindings
            .iter()
            .filter(|(_, a)| *a != Access::Uniform)
            .count() as u32
    }

    /// Fails, naming the adapter, where it allows fewer storage buffers per kernel than
    /// this shader binds (GL adapters allow 8).
    pub fn check_adapter(&self, ctx: &super::GpuContext) -> Result<(), super::GpuError> {
        let need = self.storage_bindings();
        let have = ctx.limits.max_storage_buffers_per_shader_stage;
        if have < need {
            return Err(super::GpuError::Unsupported(format!(
                "adapter '{}' ({:?}) allows {have} storage buffers per kernel; {} binds {need} \
                 (use a Vulkan, Metal or DX12 adapter)",
                ctx.info.name, ctx.info.backend, self.file
            )));
        }
        Ok(())
    }

    /// The bind group layout of this shader's bindings (in order, compute stage) and a
    /// pipeline layout holding it, labelled "`name` layout" and "`name` pipeline layout".
    pub fn layouts(
        &self,
        dev: &wgpu::Device,
        name: &str,
    ) -> (wgpu::BindGroupLayout, wgpu::PipelineLayout) {
        let entries: Vec<wgpu::BindGroupLayoutEntry> = self
            .bindings
            .iter()
            .enumerate()
            .map(|(i, (_, access))| wgpu::BindGroupLayoutEntry {
                binding: i as u32,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: match access {
                        Access::Uniform => wgpu::BufferBindingType::Uniform,
                        Access::Read => wgpu::BufferBindingType::Storage { read_only: true },
                        Access::ReadWrite => wgpu::BufferBindingType::Storage { read_only: false },
                    },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            })
            .collect();
        let layout = dev.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(&format!("{name} layout")),
            entries: &entries,
        });
        let pl = dev.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(&format!("{name} pipeline layout")),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        (layout, pl)
    }

    /// This shader's bind group layout and a pipeline per entry point of `entries` (in
    /// that order), all with the override `constants`: the adapter checked first, the
    /// compile counted as pipeline creation in the run's profile. Labels read
    /// "`name` `entry` (`real`)".
    pub fn pipelines(
        &self,
        ctx: &super::GpuContext,
        (real, acc): (&str, &str),
        name: &str,
        entries: &[&str],
        constants: &[(&str, f64)],
    ) -> Result<(wgpu::BindGroupLayout, Vec<wgpu::ComputePipeline>), super::GpuError> {
        self.check_adapter(ctx)?;
        let _compiling = ctx.phase(super::Phase::PipelineCreation);
        let dev = &ctx.device;
        let module = self.module(dev, real, acc);
        let (layout, pl) = self.layouts(dev, name);
        let pipelines = entries
            .iter()
            .map(|e| {
                let label = format!("{name} {e} ({real})");
                pipeline(dev, &pl, &module, e, &label, constants)
            })
            .collect();
        Ok((layout, pipelines))
    }

    /// This shader's source after the prelude for `real`/`acc`, compiled; labelled
    /// "`file` (`real`/`acc`)".
    pub fn module(&self, dev: &wgpu::Device, real: &str, acc: &str) -> wgpu::ShaderModule {
        let code = format!("{}{}", prelude(real, acc), self.source);
        dev.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(&format!("{} ({real}/{acc})", self.file)),
            source: wgpu::ShaderSource::Wgsl(code.into()),
        })
    }
}

/// The compute pipeline of `module` at `entry` with pipeline layout `pl` and the given
/// override constants, workgroup memory zeroed.
pub fn pipeline(
    dev: &wgpu::Device,
    pl: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    entry: &str,
    label: &str,
    constants: &[(&str, f64)],
) -> wgpu::ComputePipeline {
    dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: Some(pl),
        module,
        entry_point: Some(entry),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants,
            zero_initialize_workgroup_memory: true,
        },
        cache: None,
    })
}

/// A bind group of `layout` binding `buffers` whole, in `@binding` order.
pub fn bind_group(
    dev: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    label: &str,
    buffers: &[&wgpu::Buffer],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = buffers
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: b.as_entire_binding(),
        })
        .collect();
    dev.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &entries,
    })
}

/// The (real, acc) pairs the kernels are instantiated with: f32 with f64 or f32 sums,
/// and f64.
pub const PRELUDES: [(&str, &str); 3] = [("f32", "f64"), ("f32", "f32"), ("f64", "f64")];

/// A scalar type of a kernel instance (`real` or `acc` of the [`prelude`]), with its
/// host conversions: values are f64 on the host, rounded to f32 on upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Real {
    F32,
    F64,
}

impl Real {
    pub fn name(self) -> &'static str {
        match self {
            Real::F32 => "f32",
            Real::F64 => "f64",
        }
    }
    pub fn size(self) -> u64 {
        match self {
            Real::F32 => 4,
            Real::F64 => 8,
        }
    }
    /// `v` as this type's little-endian bytes (f64: `v`'s own, not copied).
    pub fn bytes(self, v: &[f64]) -> std::borrow::Cow<'_, [u8]> {
        match self {
            Real::F32 => {
                let w: Vec<f32> = v.iter().map(|&x| x as f32).collect();
                std::borrow::Cow::Owned(bytemuck::cast_slice(&w).to_vec())
            }
            Real::F64 => std::borrow::Cow::Borrowed(bytemuck::cast_slice(v)),
        }
    }
    pub fn values(self, b: &[u8]) -> Vec<f64> {
        match self {
            Real::F32 => b
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
                .collect(),
            Real::F64 => b
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect(),
        }
    }
}

/// The prelude of a kernel instance: the scalar-type aliases, the shared constants and
/// the shared declarations.
pub fn prelude(real: &str, acc: &str) -> String {
    let consts: String = SHARED
        .iter()
        .map(|(name, v)| format!("const {name}: u32 = {v}u;\n"))
        .collect();
    format!("alias real = {real};\nalias acc = {acc};\n{consts}{COMMON}\n")
}

/// Test helpers shared by every kernel module's layout test: a layout's WGSL parsed with a
/// prelude, and its bind group 0 as declared there checked against the layout's list.
#[cfg(test)]
pub(crate) mod check {
    use super::{prelude, Access, Layout};
    use naga::{AddressSpace, StorageAccess};

    /// `layout`'s source after the prelude for `real`/`acc`, parsed (panics naming the file).
    pub(crate) fn module(layout: &Layout, real: &str, acc: &str) -> naga::Module {
        let src = format!("{}{}", prelude(real, acc), layout.source);
        naga::front::wgsl::parse_str(&src).unwrap_or_else(|e| {
            panic!("{} ({real}/{acc}): {}", layout.file, e.emit_to_string(&src))
        })
    }

    /// `layout`'s f64 module, checked as every layout's test checks it: its bind group 0
    /// ([`bindings_match`]), the shared constants ([`shared_constants`]), the params
    /// struct `params` of `size` bytes ([`struct_size`]) and the `entries`.
    pub(crate) fn layout(
        layout: &Layout,
        params: &str,
        size: usize,
        entries: &[&str],
    ) -> naga::Module {
        let m = module(layout, "f64", "f64");
        bindings_match(layout, &m);
        shared_constants(layout, &m);
        struct_size(&m, params, size);
        for e in entries {
            assert!(
                m.entry_points.iter().any(|p| p.name == *e),
                "{}: no entry point {e}",
                layout.file
            );
        }
        m
    }

    /// Panics unless `m` declares a struct `name` of `size` bytes (a Rust `Pod` mirror).
    pub(crate) fn struct_size(m: &naga::Module, name: &str, size: usize) {
        let (_, ty) = m
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(name))
            .unwrap_or_else(|| panic!("no struct {name}"));
        match &ty.inner {
            naga::TypeInner::Struct { span, .. } => assert_eq!(*span as usize, size, "{name}"),
            other => panic!("{name} is {other:?}"),
        }
    }

    /// The member names of `m`'s struct `name` (panics without it).
    pub(crate) fn struct_members<'m>(m: &'m naga::Module, name: &str) -> Vec<&'m str> {
        match m
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(name))
        {
            Some((
                _,
                naga::Type {
                    inner: naga::TypeInner::Struct { members, .. },
                    ..
                },
            )) => members.iter().filter_map(|m| m.name.as_deref()).collect(),
            other => panic!("no struct {name}: {other:?}"),
        }
    }

    /// Panics unless the WGSL declarations of `m` are `layout.bindings`: all in group 0,
    /// same indices, names and access, nothing more, nothing less.
    pub(crate) fn bindings_match(layout: &Layout, m: &naga::Module) {
        let mut declared: Vec<(u32, String, Access)> = m
            .global_variables
            .iter()
            .filter_map(|(_, g)| {
                let b = g.binding.as_ref()?;
                assert_eq!(b.group, 0, "{}: {:?}", layout.file, g.name);
                let access = match g.space {
                    AddressSpace::Uniform => Access::Uniform,
                    AddressSpace::Storage { access } if access.contains(StorageAccess::STORE) => {
                        Access::ReadWrite
                    }
                    AddressSpace::Storage { .. } => Access::Read,
                    other => panic!("{}: {:?} in {other:?}", layout.file, g.name),
                };
                Some((b.binding, g.name.clone().unwrap_or_default(), access))
            })
            .collect();
        declared.sort_by_key(|d| d.0);
        let described: Vec<(u32, String, Access)> = layout
            .bindings
            .iter()
            .enumerate()
            .map(|(i, (n, a))| (i as u32, n.to_string(), *a))
            .collect();
        assert_eq!(declared, described, "{}", layout.file);
    }

    /// Panics unless `m` (parsed from `layout`) declares every shared constant with Rust's
    /// value and `layout`'s source indexes `scal`, `state` or the partial slots with no
    /// bare number.
    pub(crate) fn shared_constants(layout: &Layout, m: &naga::Module) {
        for (name, want) in super::SHARED {
            let (_, c) = m
                .constants
                .iter()
                .find(|(_, c)| c.name.as_deref() == Some(*name))
                .unwrap_or_else(|| panic!("{}: no const {name}", layout.file));
            match m.global_expressions[c.init] {
                naga::Expression::Literal(naga::Literal::U32(v)) => {
                    assert_eq!(v, *want, "{}: {name}", layout.file)
                }
                ref e => panic!("{}: {name} = {e:?}", layout.file),
            }
        }
        for (k, line) in layout.source.lines().enumerate() {
            let code = line.split("//").next().unwrap_or_default();
            for arr in ["scal[", "state[", "reduce_slot("] {
                if let Some(at) = code.find(arr) {
                    let next = code[at + arr.len()..].chars().next();
                    assert!(
                        !next.is_some_and(|c| c.is_ascii_digit()),
                        "{}:{}: a bare slot number: {line}",
                        layout.file,
                        k + 1
                    );
                }
            }
        }
    }
}
