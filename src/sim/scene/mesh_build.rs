//! Body meshes for a scene: the generated ones (rectangle, box, rod, sheet) scaled by the
//! run's size option, and Gmsh files, each then rotated and translated.

use super::check::Ctx;
use super::spec::{MeshKind, MeshSpec};
use crate::error::InputError;
use crate::sim::mesh::{self, Mesh};

/// `cells · size`, rounded, at least 1; None when it is 2⁶² or more (checked before the
/// cast: `as usize` would saturate). The node caps are checked on the product after.
fn scaled(cells: usize, size: f64) -> Option<usize> {
    let n = (cells as f64 * size).round();
    if n < (1u64 << 62) as f64 {
        Some((n as usize).max(1))
    } else {
        None
    }
}

/// `cells = [..][ times --size S] gives`: how a generated mesh's size is named in messages.
fn cells_text(m: &MeshSpec, size: f64) -> String {
    let by = if size == 1.0 {
        String::new()
    } else {
        format!(" times --size {size}")
    };
    format!("cells = {:?}{by} gives", m.cells)
}

/// The node count of a generated mesh whose `cells` are well formed, before generating it:
/// Some(Some(n)), or Some(None) past `usize` or the generators' cap. None for a gmsh mesh
/// or malformed cells ([`build_mesh`] reports those).
fn generated_nodes(m: &MeshSpec, size: f64) -> Option<Option<usize>> {
    let want = match m.kind {
        MeshKind::Rod => 1,
        MeshKind::Rectangle | MeshKind::Sheet => 2,
        MeshKind::Box => 3,
        MeshKind::Gmsh => return None,
    };
    if m.cells.len() != want || m.cells.contains(&0) {
        return None;
    }
    // Π (cells + 1) in checked arithmetic (the exact count is named in messages).
    let mut nodes = Some(1usize);
    for &n in &m.cells {
        nodes = match (nodes, scaled(n, size)) {
            (Some(p), Some(k)) => p.checked_mul(k + 1),
            _ => None,
        };
    }
    Some(nodes)
}

/// Checks the node cap over every generated body before any mesh is allocated (a gmsh
/// body counts when it is loaded). Returns the planned node count of the generated bodies.
pub(super) fn check_planned_nodes(
    c: &Ctx,
    meshes: &[&MeshSpec],
    dim: usize,
    size: f64,
) -> Result<usize, InputError> {
    let mut before = 0usize;
    for (b, m) in meshes.iter().enumerate() {
        if let Some(nodes) = generated_nodes(m, size) {
            if let Some(p) = over_cap(&cells_text(m, size), nodes, before, dim) {
                return Err(c.err(format!("bodies[{b}].mesh.cells"), p));
            }
            before += nodes.expect("under the cap");
        }
    }
    Ok(before)
}

/// The problem when a body of `nodes` nodes (None: more than `usize` or the generators'
/// cap) after `before` nodes of earlier bodies is over the scene's cap; None when it fits.
fn over_cap(what: &str, nodes: Option<usize>, before: usize, dim: usize) -> Option<String> {
    let cap = mesh::max_scene_nodes(dim);
    let why = format!(
        "the cap for a {dim}D scene, all bodies together (mesh::MAX_SCENE_NODES_{dim}D, what a run fits in about 100 GB of memory)"
    );
    match nodes {
        None => Some(format!("{what} more than {cap} nodes, {why}")),
        Some(n) if n > cap => Some(format!("{what} {n} nodes, more than {cap}, {why}")),
        Some(n) if n > cap - before.min(cap) => Some(format!(
            "{what} {n} nodes; with the {before} nodes of the bodies before it the scene has {}, more than {cap}, {why}",
            before + n
        )),
        Some(_) => None,
    }
}

/// Builds one body's mesh. `before`: the nodes of the bodies before it (the scene's node
/// cap counts all bodies together, and is checked before a generated mesh is allocated).
pub(super) fn build_mesh(
    c: &Ctx,
    key: &str,
    m: &MeshSpec,
    dim: usize,
    size: f64,
    before: usize,
) -> Result<Mesh, InputError> {
    let mk = format!("{key}.mesh");
    if m.kind == MeshKind::Gmsh {
        let mesh = gmsh_mesh(c, &mk, m, dim)?;
        if let Some(p) = over_cap("the file has", Some(mesh.n_nodes()), before, dim) {
            return Err(c.err(format!("{mk}.file"), p));
        }
        return Ok(mesh);
    }
    if m.file.is_some() {
        return Err(c.err(format!("{mk}.file"), "only a gmsh mesh takes a file"));
    }
    let want_cells = match m.kind {
        MeshKind::Rod => 1,
        MeshKind::Rectangle | MeshKind::Sheet => 2,
        MeshKind::Box => 3,
        MeshKind::Gmsh => 0,
    };
    if m.cells.len() != want_cells {
        return Err(c.err(
            format!("{mk}.cells"),
            format!("must have {want_cells} entries for a {:?} mesh", m.kind).to_lowercase(),
        ));
    }
    if let Some(k) = m.cells.iter().position(|&n| n == 0) {
        return Err(c.err(format!("{mk}.cells[{k}]"), "must be at least 1"));
    }
    // Node count in checked arithmetic, against the scene's cap, before allocating.
    let nodes = generated_nodes(m, size).expect("cells checked above");
    if let Some(p) = over_cap(&cells_text(m, size), nodes, before, dim) {
        return Err(c.err(format!("{mk}.cells"), p));
    }
    let cells: Vec<usize> = m
        .cells
        .iter()
        .map(|&n| scaled(n, size).expect("under the cap"))
        .collect();
    let size_vec = |n: usize| -> Result<Vec<f64>, InputError> {
        let s = m
            .size
            .as_ref()
            .ok_or_else(|| c.err(format!("{mk}.size"), format!("missing ({n} lengths)")))?;
        if s.len() != n {
            return Err(c.err(
                format!("{mk}.size"),
                format!("must have {n} entries, got {}", s.len()),
            ));
        }
        for (a, &v) in s.iter().enumerate() {
            c.positive(&format!("{mk}.size[{a}]"), v)?;
        }
        Ok(s.clone())
    };
    let mesh = match m.kind {
        MeshKind::Rectangle => {
            if dim != 2 {
                return Err(c.err(
                    format!("{mk}.kind"),
                    "a rectangle is a 2D mesh (use box or sheet in 3D)",
                ));
            }
            let s = size_vec(2)?;
            mesh::rectangle(2, [s[0], s[1]], [cells[0], cells[1]])
        }
        MeshKind::Sheet => {
            let s = size_vec(2)?;
            mesh::rectangle(dim, [s[0], s[1]], [cells[0], cells[1]])
        }
        MeshKind::Box => {
            if dim != 3 {
                return Err(c.err(
                    format!("{mk}.kind"),
                    "a box is a 3D mesh (use rectangle in 2D)",
                ));
            }
            let s = size_vec(3)?;
            mesh::cuboid([s[0], s[1], s[2]], [cells[0], cells[1], cells[2]])
        }
        MeshKind::Rod => {
            let l = m
                .length
                .ok_or_else(|| c.err(format!("{mk}.length"), "missing (a rod needs a length)"))?;
            let l = c.positive(&format!("{mk}.length"), l)?;
            mesh::rod(dim, l, cells[0])
        }
        MeshKind::Gmsh => unreachable!("handled above"),
    };
    if m.kind != MeshKind::Rod && m.length.is_some() {
        return Err(c.err(
            format!("{mk}.length"),
            "only a rod takes a length (use size)",
        ));
    }
    if m.kind == MeshKind::Rod && m.size.is_some() {
        return Err(c.err(format!("{mk}.size"), "a rod takes a length, not a size"));
    }
    place(c, &mk, m, dim, mesh)
}

/// Loads `mesh.file` (Gmsh), then applies rotation and origin like the generated meshes.
fn gmsh_mesh(c: &Ctx, mk: &str, m: &MeshSpec, dim: usize) -> Result<Mesh, InputError> {
    for (name, given) in [
        ("cells", !m.cells.is_empty()),
        ("size", m.size.is_some()),
        ("length", m.length.is_some()),
    ] {
        if given {
            return Err(c.err(
                format!("{mk}.{name}"),
                "does not apply to a gmsh mesh (the file fixes it)",
            ));
        }
    }
    let f = m.file.as_ref().ok_or_else(|| {
        c.err(
            format!("{mk}.file"),
            "missing (a gmsh mesh needs a .msh file)",
        )
    })?;
    let path = std::path::Path::new(f);
    let path = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::path::Path::new(c.file)
            .parent()
            .map(|d| d.join(path))
            .unwrap_or_else(|| path.to_path_buf())
    };
    let shown = path.display().to_string();
    // The general input limit (an 8M-node MSH 4.1 ASCII mesh is ~2.5 GB); a device is
    // never read whole.
    let bytes = crate::io::read_limited(&path, crate::io::input_limit(), false)
        .map_err(|e| c.err(format!("{mk}.file"), format!("{shown}: {}", e.problem)))?;
    let mesh = mesh::gmsh(dim, &bytes)
        .map_err(|e| c.err(format!("{mk}.file"), format!("{shown}: {e}")))?;
    place(c, mk, m, dim, mesh)
}

/// Applies the spec's `rotate_degrees` (about z) and then its `origin` to a built mesh.
fn place(c: &Ctx, mk: &str, m: &MeshSpec, dim: usize, mut mesh: Mesh) -> Result<Mesh, InputError> {
    let origin = match &m.origin {
        Some(o) => c.vector(&format!("{mk}.origin"), o, dim)?,
        None => [0.0; 3],
    };
    let angle = match m.rotate_degrees {
        Some(a) if !a.is_finite() => {
            return Err(c.err(format!("{mk}.rotate_degrees"), "must be finite"))
        }
        Some(a) => a.to_radians(),
        None => 0.0,
    };
    mesh.transform(angle, &origin);
    Ok(mesh)
}
