//! Scene files (TOML) and their resolution into a simulation model.
//!
//! A scene names the dimension, time step, steps (or end time), gravity, bodies (a
//! generated mesh and a material), boundary conditions selected by region (box, plane
//! within a tolerance, node list, all), optionally moving, the linear solver and output.
//! Every key is checked: unknown keys and out-of-range values are [`InputError`]s naming
//! the key path, e.g. `bodies[0].material.poisson`. The built-in scenes in `scenes/` are
//! compiled into the binary and run by name; `size` multiplies every mesh resolution.
//!
//! Units: SI. Tolerances that carry a length are relative to the characteristic length L
//! (the bounding-box diagonal of all bodies at t = 0 unless `solver.characteristic_length`
//! sets it):
//! - Newton stops when ‖Δx‖∞ / h < `solver.newton_tolerance` · L (per second);
//!   default 1e-6 · L/s, at an iterate whose largest unbalanced free force is at most
//!   `solver.force_tolerance` (default 1e-4) of the step's force scale.
//! - A moving boundary node is satisfied (snapped and eliminated) when
//!   ‖x_k − x̂_k‖ / h < `moving.tolerance` · L (per second); default 1e-3 · L/s.
//!
//! Obstacles (`[[obstacle]]`, the distance barrier of docs/method.md, "Contact with
//! half-spaces"; see [`crate::sim::energy::barrier`]):
//!
//! ```toml
//! [[obstacle]]
//! kind = "half-space"            # the allowed side is n·(x − point) > 0
//! point = [0.0, 0.0, 0.0]
//! normal = [0.0, 1.0, 0.0]       # outward (into the allowed side), need not be unit
//! dhat = 0.005                   # activation distance d̂ in metres; default 1e-2 · L
//! kappa = 1e5                    # barrier stiffness κ in Pa; default: the largest
//!                                # neo-Hookean Young's modulus of the scene (1e5 Pa
//!                                # when every body is mass-spring)
//! motion = { velocity = [0.0, 0.1, 0.0], end = 0.5 }   # optional; translation only
//! ```
//!
//! Each node i carries the contact measure w_i used to weight the barrier: its lumped share
//! of the body's boundary ([`crate::sim::mesh::Mesh::boundary_measure`]: boundary edges in 2D and
//! boundary faces in 3D split equally among their nodes; a rod in 2D or a sheet in 3D is its
//! own boundary, a rod in 3D counts its length as a unit-width strip). At rest on a plane a
//! body presses with about κ·(1 − d/d̂) per unit contact measure, so κ ≈ E puts the resting
//! gap within a few percent of d̂ below d̂ for everyday loads. Every node must start at a
//! positive distance from every obstacle; otherwise the scene is rejected naming the node.
//!
//! Limits, all checked before anything big is allocated: a name of at most
//! [`MAX_NAME_BYTES`] bytes; at most [`crate::sim::mesh::MAX_SCENE_NODES_2D`] or
//! [`crate::sim::mesh::MAX_SCENE_NODES_3D`] nodes over all bodies together (what a run fits in about
//! 100 GB), and [`crate::sim::mesh::MAX_CHOLESKY_NODES_3D`] for a 3D scene solved by Cholesky (checked
//! when the run starts, after the command line's `--solver` and `--newton`); several
//! static conditions on one node must agree at the initial configuration
//! ([`joint_targets`]).
//!
//! Layout: `spec` holds the file schema (serde), `resolve` turns a parsed file into a
//! [`Scene`], and `mesh_build` generates or loads each body's mesh.

mod check;
mod mesh_build;
mod model;
mod resolve;
mod spec;

pub use spec::{
    BcKindSpec, BodySpec, BoundarySpec, BoxRegion, CgTolerance, InversionPolicy, LinearChoice,
    LinearKind, MaterialModel, MaterialSpec, MeshKind, MeshSpec, MotionSpec, MovingSpec,
    NewtonLoop, ObstacleKind, ObstacleSpec, OutputSpec, PlaneRegion, PreconditionerChoice,
    RegionSpec, SceneFile, SolverSpec,
};

pub use model::{
    builtin, check_name, check_solver_size, consistency_floor, joint_targets, BcShape, CellBlock,
    JointTarget, Motion, NodeBc, Obstacle, Scene, BUILTIN, MAX_NAME_BYTES, MAX_STEPS,
};

use crate::error::InputError;
pub use crate::sim::memory::LoadError;
use resolve::resolve;

/// Parses a scene file's text. `file` names it in errors; `size` multiplies every mesh
/// resolution (cells), rounded, at least 1. A scene too large for the memory the process
/// may allocate is refused with [`LoadError::Memory`] (the bytes it needs), before its
/// meshes are built when their sizes are known from the file.
pub fn load(text: &str, file: &str, size: f64) -> Result<Scene, LoadError> {
    let de = toml::Deserializer::parse(text).map_err(|e| toml_error(file, text, &e, ""))?;
    let spec: SceneFile = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        toml_error(file, text, &inner, &path)
    })?;
    resolve(spec, file, size)
}

/// [`load`], with a scene too large for memory reported as an error on the file.
pub fn parse(text: &str, file: &str, size: f64) -> Result<Scene, InputError> {
    load(text, file, size).map_err(|e| match e {
        LoadError::Input(e) => e,
        LoadError::Memory(m) => InputError::new(file, "", m.to_string()),
    })
}

fn toml_error(file: &str, text: &str, e: &toml::de::Error, path: &str) -> InputError {
    let mut msg = e.message().trim().to_string();
    if let Some(span) = e.span() {
        let line = text[..span.start.min(text.len())].matches('\n').count() + 1;
        msg = format!("{msg} (line {line})");
    }
    let entry = if path.is_empty() || path == "." {
        String::new()
    } else {
        path.to_string()
    };
    InputError::new(file, entry, msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    const OK: &str = r#"
dimension = 2
time_step = 0.01
steps = 3
[[bodies]]
mesh = { kind = "rectangle", size = [1.0, 0.5], cells = [4, 2] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.3, density = 100 }
"#;

    #[test]
    fn every_builtin_scene_parses() {
        for (name, text) in BUILTIN {
            let s = parse(text, name, 1.0).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert!(s.steps > 0);
        }
    }

    #[test]
    fn minimal_scene_parses() {
        let s = parse(OK, "ok.toml", 1.0).expect("valid");
        assert_eq!(s.x0.len(), 2 * 15);
        let s2 = parse(OK, "ok.toml", 2.0).expect("valid");
        assert_eq!(s2.x0.len(), 2 * 45);
    }

    fn entry_of(text: &str) -> InputError {
        parse(text, "bad.toml", 1.0).expect_err("must fail")
    }

    #[test]
    fn bad_values_name_their_key() {
        let e = entry_of(&OK.replace("poisson = 0.3", "poisson = 0.5"));
        assert_eq!(e.entry, "bodies[0].material.poisson");
        assert!(e.problem.contains("(0, 0.5)"));
        let e = entry_of(&OK.replace("young = 1e4", "young = -1"));
        assert_eq!(e.entry, "bodies[0].material.young");
        let e = entry_of(&OK.replace("time_step = 0.01", "time_step = 0"));
        assert_eq!(e.entry, "time_step");
        let e = entry_of(&OK.replace("cells = [4, 2]", "cells = [4]"));
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        let e = entry_of(&format!(
            "{OK}\n[[boundary]]\nkind = \"plane\"\nregion = {{ all = true }}\n"
        ));
        assert_eq!(e.entry, "boundary[0].normal");
        let e = entry_of(&format!(
            "{OK}\n[[boundary]]\nkind = \"sticky\"\nregion = {{ nodes = [99] }}\n"
        ));
        assert_eq!(e.entry, "boundary[0].region.nodes[0]");
    }

    #[test]
    fn unknown_keys_and_types_name_their_key() {
        let e = entry_of(&OK.replace("poisson = 0.3", "poison = 0.3"));
        assert_eq!(e.entry, "bodies[0].material.poison");
        assert!(e.problem.contains("poison"), "{e}");
        let e = entry_of(&OK.replace("steps = 3", "steps = 3\nfoo = 1"));
        assert!(e.problem.contains("foo"), "{e}");
        let e = entry_of(&OK.replace("time_step = 0.01", "time_step = \"fast\""));
        assert_eq!(e.entry, "time_step");
        let e = entry_of(&OK.replace("neo-hookean", "rubber"));
        assert_eq!(e.entry, "bodies[0].material.model");
        let e = entry_of("dimension = 2\ntime_step = [");
        assert!(e.problem.contains("line"), "{e}");
        // One line, naming the file and the key.
        let e = entry_of(&OK.replace("poisson = 0.3", "poisson = 0.7"));
        let line = e.to_string();
        assert!(
            !line.contains('\n') && line.starts_with("bad.toml: bodies[0].material.poisson: "),
            "{line}"
        );
    }

    const BOX: &str = r#"
dimension = 3
time_step = 0.01
steps = 3
[[bodies]]
mesh = { kind = "box", size = [1.0, 0.5, 0.5], cells = [4, 2, 2] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.3, density = 100 }
"#;

    #[test]
    fn huge_meshes_are_input_errors_not_overflows() {
        // --size 1e7 on a box: (4e7+1)(2e7+1)² nodes overflows usize.
        let e = parse(BOX, "box.toml", 1e7).expect_err("too big");
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        assert!(
            e.problem.contains("--size") && e.problem.contains("cap"),
            "{e}"
        );
        // Every builtin scene, at a size that overflows.
        for (name, text) in BUILTIN {
            let e = parse(text, name, 1e300).expect_err(name);
            assert!(e.entry.ends_with(".mesh.cells"), "{name}: {e}");
        }
        // Over the cap without overflow, and from the file alone (size 1).
        let e = entry_of(&BOX.replace("cells = [4, 2, 2]", "cells = [1000, 1000, 100]"));
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        assert!(!e.problem.contains("--size"), "{e}");
        let e = entry_of(&OK.replace("cells = [4, 2]", "cells = [18446744073709551615, 2]"));
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        // Within the cap it still parses.
        let s = parse(BOX, "box.toml", 2.0).expect("valid");
        assert_eq!(s.x0.len(), 3 * 9 * 5 * 5);
    }

    #[test]
    fn step_counts_are_capped() {
        let e = entry_of(&OK.replace("steps = 3", "end_time = 1e300"));
        assert_eq!(e.entry, "end_time");
        assert!(e.problem.contains("cap"), "{e}");
        let e = entry_of(&OK.replace("steps = 3", "steps = 1000000001"));
        assert_eq!(e.entry, "steps");
        let e = entry_of(&OK.replace("steps = 3", "steps = 18446744073709551615"));
        assert_eq!(e.entry, "steps");
        let s = parse(&OK.replace("steps = 3", "end_time = 0.1"), "ok.toml", 1.0).expect("ok");
        assert_eq!(s.steps, 10);
        let s = parse(
            &OK.replace("steps = 3", &format!("steps = {MAX_STEPS}")),
            "ok.toml",
            1.0,
        )
        .expect("at the cap");
        assert_eq!(s.steps, MAX_STEPS);
    }

    #[test]
    fn size_is_checked_once_naming_the_option() {
        for size in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = parse(OK, "ok.toml", size).expect_err("bad size");
            assert_eq!(e.file, "--size", "{e}");
            assert!(
                e.to_string()
                    .starts_with("--size: must be a positive number"),
                "{e}"
            );
        }
    }

    #[test]
    fn names_must_be_plain_file_names() {
        for bad in ["", "a/b", "/abs", "..", "../up", "a\\b", "x..y", "a\nb"] {
            let text = format!("name = {bad:?}\n{OK}");
            let e = entry_of(&text);
            assert_eq!(e.entry, "name", "{bad:?}: {e}");
        }
        for good in ["scene", "my-scene_2", "a.b", "drop v2"] {
            let s = parse(&format!("name = {good:?}\n{OK}"), "ok.toml", 1.0).expect(good);
            assert_eq!(s.name, good);
        }
        // A name taken from the file stem is checked too ("...toml" has the stem "..").
        let e = parse(OK, "dir/...toml", 1.0).expect_err("stem ..");
        assert_eq!(e.entry, "name");
        assert_eq!(parse(OK, "dir/ok.toml", 1.0).expect("ok").name, "ok");
    }
}
