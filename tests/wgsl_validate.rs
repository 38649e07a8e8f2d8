//! Parses and validates every shaders/*.wgsl with naga (no GPU needed), in every scalar
//! prelude the solver uses (f32 with f64 or f32 accumulation, and f64).

use naga::valid::{Capabilities, ValidationFlags, Validator};

/// The head of every pcg_*.wgsl.
const PCG_COMMON: &str = "pcg_common.wgsl";

#[test]
fn every_shader_parses_and_validates() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .expect("shaders/ exists")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "wgsl"))
        // common.wgsl is part of the prelude and pcg_common.wgsl heads every pcg_*.wgsl:
        // each is validated inside the kernels that include it.
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n != "common.wgsl" && n != PCG_COMMON)
        })
        .collect();
    files.sort();
    assert!(
        files.len() >= 6,
        "expected the kernel files, found {files:?}"
    );
    let mut checked = 0;
    for path in &files {
        let mut src = std::fs::read_to_string(path).expect("readable shader");
        // The PCG's shader files share one bind group and its helpers (gpu::pcg's
        // `pcg_source!` prepends them the same way).
        if path
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with("pcg_"))
        {
            src = std::fs::read_to_string(dir.join(PCG_COMMON)).expect("readable shader") + &src;
        }
        for (real, acc) in stickslip::gpu::kernels::PRELUDES {
            let full = format!("{}{}", stickslip::gpu::kernels::prelude(real, acc), src);
            let module = naga::front::wgsl::parse_str(&full).unwrap_or_else(|e| {
                panic!(
                    "{} ({real}/{acc}) does not parse:\n{}",
                    path.display(),
                    e.emit_to_string(&full)
                )
            });
            let mut v = Validator::new(ValidationFlags::all(), Capabilities::all());
            if let Err(e) = v.validate(&module) {
                panic!(
                    "{} ({real}/{acc}) does not validate:\n{}",
                    path.display(),
                    e.emit_to_string(&full)
                );
            }
            checked += 1;
        }
    }
    println!(
        "validated {checked} shader variants from {} files",
        files.len()
    );
}
