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
//! Each shader's bind group 0 is described once, by a [`Layout`]: the bind-group layout is
//! built from it and bind groups name their buffers by it (`solver::builder`), and a test
//! checks the WGSL declarations against it.

/// Shared declarations, prepended to every kernel by [`prelude`].
pub const COMMON: &str = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/common.wgsl"));

/// The one slot table of the device CGs' scalar array `scal` (acc), state array `state`
/// (u32) and partial sums (`partials[slot · G + segment]`): `solve`'s CG (the driver in
/// src/gpu/solver/run.rs, the kernels in shaders/cg.wgsl, whose header says who writes and
/// reads each) and the device Newton loop's (src/gpu/pcg/mod.rs,
/// shaders/pcg.wgsl). The prelude declares every one as a WGSL `const` of the same
/// name; a slot one CG does not use is simply unused there.
pub mod slots {
    /// ρ = r·z.
    pub const SCAL_RHO: u32 = 0;
    /// ρ of the previous iteration (`solve`'s CG; the host sets it), or of the segment a
    /// device PCG segment resumes (host, rescaled).
    pub const SCAL_RHO_PREV: u32 = 1;
    /// p·q of the last α (the curvature reported when it is not positive).
    pub const SCAL_PQ: u32 = 2;
    pub const SCAL_ALPHA: u32 = 3;
    /// r·r of the last reduction.
    pub const SCAL_RR: u32 = 4;
    /// The convergence threshold tol²‖b‖² on r·r (`solve`'s CG; host).
    pub const SCAL_THRESH: u32 = 5;
    /// The direction scale `init` keeps (`solve`'s CG; host; 0: p = 0), or by which a
    /// resumed device PCG segment rescales p (host; 0: a fresh start).
    pub const SCAL_PSCALE: u32 = 6;
    /// β of the first update_p of a run (the link of a resumed Lanczos sequence).
    pub const SCAL_BETA0: u32 = 7;
    /// β (the device PCG's scalar_beta).
    pub const SCAL_BETA: u32 = 8;
    /// tol² (host) and ‖b̂‖² (scalar_start): the device PCG's threshold is their product.
    pub const SCAL_TOL2: u32 = 9;
    pub const SCAL_BB: u32 = 10;
    /// The leading slots read back with every status of the device PCG.
    pub const STATUS_SCAL: u32 = 12;
    /// The coarse correction on the translations (the device PCG): c = E⁺Zᵀr (D values),
    /// E⁺ (D², from the host), E = ZᵀĤZ (D², for the host), the rows' absolute sums per
    /// world axis (D, for the host).
    pub const SCAL_C: u32 = 12;
    pub const SCAL_EINV: u32 = 15;
    pub const SCAL_E: u32 = 24;
    pub const SCAL_EABS: u32 = 33;
    /// First slot of the Lanczos coefficient history (`solve`'s CG): α_j at
    /// SCAL_HIST + 2j, β_{j+1} at SCAL_HIST + 2j + 1. The slots before it are the fixed
    /// scalars of either CG.
    pub const SCAL_HIST: u32 = 36;
    /// A converged or stopped CG: every later dispatch of the chunk is a no-op.
    pub const STATE_DONE: u32 = 0;
    /// Non-positive curvature met.
    pub const STATE_HALT: u32 = 1;
    pub const STATE_CONVERGED: u32 = 2;
    /// A non-finite ρ or r·r.
    pub const STATE_BREAKDOWN: u32 = 3;
    /// Iterations done. The four flags come before it, so that clearing them keeps it.
    pub const STATE_ITERS: u32 = 4;
    /// Length of `state`.
    pub const N_STATE: u32 = 8;
    /// Partial-sum slots: p·q (the product), r·z and r·r (the updates, init), Zᵀr (D
    /// slots from PART_ZR, with the coarse correction on the translations), ‖b̂‖² (the
    /// device PCG's rhs), then E (D² slots) and its rows' absolute sums (D slots) of the
    /// device PCG's coarse_e.
    pub const PART_PQ: u32 = 0;
    pub const PART_RZ: u32 = 1;
    pub const PART_RR: u32 = 2;
    pub const PART_ZR: u32 = 3;
    pub const PART_BB: u32 = 6;
    pub const PART_E: u32 = 7;
    /// Partial-sum slots of the device PCG.
    pub const N_PART: u32 = 19;
    /// Where the device PCG's per-invocation sums carried between H's chunks start (×
    /// partials per slot), and how many each invocation carries.
    pub const PART_CARRY: u32 = N_PART;
    pub const CARRY_LEN: u32 = 12;

    // The slot ranges do not overlap (D ≤ 3).
    const _: () = assert!(SCAL_BB < STATUS_SCAL && STATUS_SCAL <= SCAL_C);
    const _: () = assert!(
        SCAL_C + 3 <= SCAL_EINV
            && SCAL_EINV + 9 <= SCAL_E
            && SCAL_E + 9 <= SCAL_EABS
            && SCAL_EABS + 3 <= SCAL_HIST
    );
    const _: () = assert!(STATE_ITERS < N_STATE);
    const _: () = assert!(PART_ZR + 3 <= PART_BB && PART_BB < PART_E && PART_E + 12 <= N_PART);
    // coarse_e carries E and the absolute sums.
    const _: () = assert!(CARRY_LEN == 12);
}

/// A packed column index holds the column node's constraint mask in its bits from this
/// one up (3 bits: d ≤ 3), so the GPU solver takes fewer than 2^29 nodes.
pub const MASK_SHIFT: u32 = 29;

/// Upper bound of the workgroup size (`GpuParams::workgroup_size`).
pub const WG_MAX: u32 = 256;

/// The u32 constants every kernel sees under these names (WGSL `const`s in the prelude).
pub const SHARED: &[(&str, u32)] = &[
    ("SCAL_RHO", slots::SCAL_RHO),
    ("SCAL_RHO_PREV", slots::SCAL_RHO_PREV),
    ("SCAL_PQ", slots::SCAL_PQ),
    ("SCAL_ALPHA", slots::SCAL_ALPHA),
    ("SCAL_RR", slots::SCAL_RR),
    ("SCAL_THRESH", slots::SCAL_THRESH),
    ("SCAL_PSCALE", slots::SCAL_PSCALE),
    ("SCAL_BETA0", slots::SCAL_BETA0),
    ("SCAL_HIST", slots::SCAL_HIST),
    ("STATE_DONE", slots::STATE_DONE),
    ("STATE_HALT", slots::STATE_HALT),
    ("STATE_ITERS", slots::STATE_ITERS),
    ("STATE_CONVERGED", slots::STATE_CONVERGED),
    ("STATE_BREAKDOWN", slots::STATE_BREAKDOWN),
    ("PART_PQ", slots::PART_PQ),
    ("PART_RZ", slots::PART_RZ),
    ("PART_RR", slots::PART_RR),
    ("PART_ZR", slots::PART_ZR),
    ("SCAL_BETA", slots::SCAL_BETA),
    ("SCAL_TOL2", slots::SCAL_TOL2),
    ("SCAL_BB", slots::SCAL_BB),
    ("SCAL_C", slots::SCAL_C),
    ("SCAL_EINV", slots::SCAL_EINV),
    ("SCAL_E", slots::SCAL_E),
    ("SCAL_EABS", slots::SCAL_EABS),
    ("PART_BB", slots::PART_BB),
    ("PART_E", slots::PART_E),
    ("PART_CARRY", slots::PART_CARRY),
    ("CARRY_LEN", slots::CARRY_LEN),
    ("MASK_SHIFT", MASK_SHIFT),
    ("COL_BITS", (1 << MASK_SHIFT) - 1),
    ("NO_ROTATION", crate::core::constraints::NO_ROTATION),
    ("NO_AGGREGATE", crate::solve::coarse::NO_AGGREGATE),
    ("WG_MAX", WG_MAX),
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

use Access::{Read as R, ReadWrite as W, Uniform as U};

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

    /// This shader's source after the prelude for `real`/`acc`, compiled; labelled
    /// "`file` (`real`/`acc`)".
    pub fn module(
        &self,
        dev: &wgpu::Device,
        real: &str,
        acc: &str,
        packed: bool,
    ) -> wgpu::ShaderModule {
        let code = format!("{}{}", prelude(real, acc, packed), self.source);
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

pub const MATVEC: Layout = Layout {
    file: "matvec.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/matvec.wgsl")),
    bindings: &[
        ("params", U),
        ("row_ptr", R),
        ("col", R),
        ("blk_a", R),
        ("mask", R),
        ("dvals", R),
        ("p", R),
        ("q", W),
        ("partials", W),
        ("state", R),
        ("blk_b", R),
        ("blk_c", R),
        ("rowsum", R),
        ("chunk", U),
        ("carry", W),
    ],
};

pub const SPRINGS: Layout = Layout {
    file: "springs.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/springs.wgsl")),
    bindings: &[
        ("params", U),
        ("adj_ptr", R),
        ("adj", R),
        ("pos", R),
        ("springs", R),
        ("mass", R),
        ("rot_index", R),
        ("rotations", R),
        ("mask", R),
        ("dvals", R),
        ("p", R),
        ("q", W),
        ("partials", W),
        ("state", R),
    ],
};

pub const ROTATE_BLOCKS: Layout = Layout {
    file: "rotate_blocks.wgsl",
    source: include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/shaders/rotate_blocks.wgsl"
    )),
    bindings: &[
        ("params", U),
        ("rot_index", R),
        ("rot_nodes", R),
        ("rotations", R),
        ("row_ptr", R),
        ("col", R),
        ("blk_a", W),
        ("blk_b", W),
        ("blk_c", W),
        ("chunk", U),
    ],
};

pub const PRECOND: Layout = Layout {
    file: "precond.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/precond.wgsl")),
    bindings: &[
        ("params", U),
        ("row_ptr", R),
        ("col", R),
        ("blk_a", R),
        ("mask", R),
        ("dvals", R),
        ("minv", W),
        ("blk_b", R),
        ("blk_c", R),
        ("chunk", U),
    ],
};

pub const CG: Layout = Layout {
    file: "cg.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/cg.wgsl")),
    bindings: &[
        ("params", U),
        ("x", W),
        ("r", W),
        ("z", W),
        ("p", W),
        ("q", R),
        ("b", R),
        ("minv", R),
        ("partials", W),
        ("scal", W),
        ("state", W),
        ("cmask", R),
        ("rot_index", R),
        ("rotations", R),
        ("einv", R),
        ("agg_of", R),
        ("wc", R),
    ],
};

pub const COARSE: Layout = Layout {
    file: "coarse.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/coarse.wgsl")),
    bindings: &[
        ("params", U),
        ("r", R),
        ("state", R),
        ("cmask", R),
        ("rot_index", R),
        ("rotations", R),
        ("agg_ptr", R),
        ("agg_nodes", R),
        ("einv", R),
        ("wc", W),
    ],
};

pub const REFINE: Layout = Layout {
    file: "refine.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/refine.wgsl")),
    bindings: &[
        ("params", U),
        ("b64", R),
        ("q64", W),
        ("rhs32", W),
        ("partials64", W),
        ("x32", R),
        ("y64", W),
        ("factors", R),
    ],
};

/// Every shader file's layout.
pub const LAYOUTS: [&Layout; 7] = [
    &MATVEC,
    &SPRINGS,
    &ROTATE_BLOCKS,
    &PRECOND,
    &CG,
    &COARSE,
    &REFINE,
];

/// The (real, acc, packed) triples the solver instantiates; `packed` is f32 blocks read
/// as u64 pairs (see [`prelude`]).
pub const PRELUDES: [(&str, &str, bool); 5] = [
    ("f32", "f64", false),
    ("f32", "f32", false),
    ("f32", "f64", true),
    ("f32", "f32", true),
    ("f64", "f64", false),
];

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

/// The prelude of a kernel instance: the scalar-type aliases, the block-load type
/// `blk4` with its `unpack4`, the shared constants and the shared declarations.
///
/// `packed` (f32 only, needs SHADER_INT64) reads four f32 block entries as two u64:
/// the bytes are the same as a `vec4<f32>`, so no writer changes. Why: llvmpipe
/// (lavapipe) loads a storage vector one component at a time in a loop over the SIMD
/// lanes, whatever the component's width, so halving the components read per block
/// is what makes an f32 matvec cheaper than an f64 one there; on a GPU both are one
/// 16-byte load.
pub fn prelude(real: &str, acc: &str, packed: bool) -> String {
    let blk = if packed {
        "alias blk4 = vec2<u64>;\n\
         fn unpack4(v: vec2<u64>) -> vec4<f32> {\n\
         \x20   return bitcast<vec4<f32>>(vec4<u32>(u32(v.x), u32(v.x >> 32u), u32(v.y), u32(v.y >> 32u)));\n\
         }\n"
            .to_string()
    } else {
        format!("alias blk4 = vec4<{real}>;\nfn unpack4(v: vec4<{real}>) -> vec4<{real}> {{ return v; }}\n")
    };
    let consts: String = SHARED
        .iter()
        .map(|(name, v)| format!("const {name}: u32 = {v}u;\n"))
        .collect();
    format!("alias real = {real};\nalias acc = {acc};\n{blk}{consts}{COMMON}\n")
}

/// Test helpers shared by every kernel module's layout test: a layout's WGSL parsed with a
/// prelude, and its bind group 0 as declared there checked against the layout's list.
#[cfg(test)]
pub(crate) mod check {
    use super::{prelude, Access, Layout};
    use naga::{AddressSpace, StorageAccess};

    /// `layout`'s source after the prelude for `real`/`acc`, parsed (panics naming the file).
    pub(crate) fn module(layout: &Layout, real: &str, acc: &str, packed: bool) -> naga::Module {
        let src = format!("{}{}", prelude(real, acc, packed), layout.source);
        naga::front::wgsl::parse_str(&src).unwrap_or_else(|e| {
            panic!("{} ({real}/{acc}): {}", layout.file, e.emit_to_string(&src))
        })
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
}

#[cfg(test)]
mod tests {
    use super::check::{bindings_match, module};
    use super::*;

    /// The WGSL declarations of bind group 0 are the layout's bindings: same indices,
    /// names and access, nothing more, nothing less.
    #[test]
    fn every_layout_matches_its_wgsl_declarations() {
        for layout in LAYOUTS {
            bindings_match(layout, &module(layout, "f64", "f64", false));
        }
    }

    /// Every shared constant is declared in the prelude with Rust's value, and no kernel
    /// indexes `scal`, `state` or the partial slots with a bare number.
    #[test]
    fn shared_constants_agree_and_no_kernel_uses_bare_slot_numbers() {
        for layout in LAYOUTS {
            let m = module(layout, "f32", "f32", false);
            for (name, want) in SHARED {
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
}
