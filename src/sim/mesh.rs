//! Simulation meshes: node positions, elements, lumped masses, and the generators the
//! scenes use (2D rectangle of triangles, 3D box of tetrahedra, rod and sheet of springs).

use crate::core::linalg::{cross3, norm3};

/// Element type of a mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ElementKind {
    /// Two-node segments (rods; springs only).
    Segment,
    /// Three-node triangles (2D solids, or sheets in 3D).
    Triangle,
    /// Four-node tetrahedra (3D solids).
    Tetrahedron,
}

impl ElementKind {
    pub fn nodes(self) -> usize {
        match self {
            ElementKind::Segment => 2,
            ElementKind::Triangle => 3,
            ElementKind::Tetrahedron => 4,
        }
    }

    /// VTK cell type id (legacy format).
    pub fn vtk_type(self) -> u8 {
        match self {
            ElementKind::Segment => 3,
            ElementKind::Triangle => 5,
            ElementKind::Tetrahedron => 10,
        }
    }
}

/// A mesh in `dim` dimensions. Positions are node-major: node i at `x[dim*i .. dim*i+dim]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    pub dim: usize,
    pub x: Vec<f64>,
    pub kind: ElementKind,
    /// `kind.nodes()` node indices per element.
    pub elements: Vec<Vec<usize>>,
}

impl Mesh {
    pub fn n_nodes(&self) -> usize {
        self.x.len() / self.dim
    }

    pub fn node(&self, i: usize) -> &[f64] {
        &self.x[i * self.dim..(i + 1) * self.dim]
    }

    /// Measure (length, area or volume) of element `e` at the stored positions.
    pub fn measure(&self, e: usize) -> f64 {
        let el = &self.elements[e];
        let p = |k: usize| self.node(el[k]);
        let sub = |a: &[f64], b: &[f64]| -> [f64; 3] {
            let mut r = [0.0; 3];
            for k in 0..self.dim {
                r[k] = a[k] - b[k];
            }
            r
        };
        match self.kind {
            ElementKind::Segment => norm3(&sub(p(1), p(0))),
            ElementKind::Triangle => {
                let a = sub(p(1), p(0));
                let b = sub(p(2), p(0));
                0.5 * norm3(&cross3(&a, &b))
            }
            ElementKind::Tetrahedron => {
                let a = sub(p(1), p(0));
                let b = sub(p(2), p(0));
                let c = sub(p(3), p(0));
                dot3(&a, &cross3(&b, &c)).abs() / 6.0
            }
        }
    }

    /// Lumped masses: each element gives density·measure / (nodes per element) to its nodes.
    pub fn lumped_masses(&self, density: f64) -> Vec<f64> {
        let mut m = vec![0.0; self.n_nodes()];
        let k = self.kind.nodes() as f64;
        for (e, el) in self.elements.iter().enumerate() {
            let share = density * self.measure(e) / k;
            for &i in el {
                m[i] += share;
            }
        }
        m
    }

    /// Per-node contact measure w_i of the distance barrier (docs/method.md, "Contact with
    /// half-spaces"): the node's lumped share of the body's boundary of codimension one in
    /// the ambient space.
    /// Solids (triangles in 2D, tetrahedra in 3D): every boundary facet (an edge or face
    /// that belongs to exactly one element) gives its length or area equally to its nodes.
    /// Lower-dimensional meshes are their own boundary: a rod in 2D or a sheet in 3D gives
    /// each element's measure equally to its nodes (both sides of a sheet count once);
    /// a rod in 3D does the same with its length (a unit-width strip, documented in
    /// `scene/mod.rs`). Interior nodes of a solid get 0: the barrier never acts on them, and
    /// only the line search's CCD bound, which covers every node, keeps them off an
    /// obstacle (a step where that bound alone holds one fails: the body has inverted).
    pub fn boundary_measure(&self) -> Vec<f64> {
        let mut w = vec![0.0; self.n_nodes()];
        let solid = matches!(
            (self.dim, self.kind),
            (2, ElementKind::Triangle) | (3, ElementKind::Tetrahedron)
        );
        if !solid {
            let k = self.kind.nodes() as f64;
            for (e, el) in self.elements.iter().enumerate() {
                let share = self.measure(e) / k;
                for &i in el {
                    w[i] += share;
                }
            }
            return w;
        }
        // Facets as sorted node lists; a facet seen once lies on the boundary.
        let nf = self.kind.nodes() - 1;
        let mut facets: Vec<Vec<usize>> = Vec::with_capacity(self.elements.len() * (nf + 1));
        for el in &self.elements {
            for skip in 0..el.len() {
                let mut f: Vec<usize> = (0..el.len())
                    .filter(|&k| k != skip)
                    .map(|k| el[k])
                    .collect();
                f.sort_unstable();
                facets.push(f);
            }
        }
        facets.sort_unstable();
        let p = |i: usize| {
            let mut q = [0.0; 3];
            q[..self.dim].copy_from_slice(self.node(i));
            q
        };
        let mut k = 0;
        while k < facets.len() {
            let mut j = k + 1;
            while j < facets.len() && facets[j] == facets[k] {
                j += 1;
            }
            if j - k == 1 {
                let f = &facets[k];
                let a = p(f[0]);
                let b = p(f[1]);
                let ab = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let measure = if nf == 2 {
                    norm3(&ab)
                } else {
                    let c = p(f[2]);
                    let ac = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
                    0.5 * norm3(&cross3(&ab, &ac))
                };
                for &i in f {
                    w[i] += measure / nf as f64;
                }
            }
            k = j;
        }
        w
    }

    /// Unique undirected edges of all elements, sorted.
    pub fn edges(&self) -> Vec<[usize; 2]> {
        let mut out = Vec::new();
        for el in &self.elements {
            for a in 0..el.len() {
                for b in a + 1..el.len() {
                    let (i, j) = (el[a].min(el[b]), el[a].max(el[b]));
                    out.push([i, j]);
                }
            }
        }
        out.sort_unstable();
        out.dedup();
        out
    }

    /// Length of the bounding-box diagonal (the characteristic length of a scene).
    pub fn bbox_diagonal(&self) -> f64 {
        let d = self.dim;
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for i in 0..self.n_nodes() {
            for a in 0..d {
                lo[a] = lo[a].min(self.x[i * d + a]);
                hi[a] = hi[a].max(self.x[i * d + a]);
            }
        }
        (0..d).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f64>().sqrt()
    }

    /// Applies x ← R_z(angle)·x + origin to every node (R_z: rotation about the z axis;
    /// in 2D the in-plane rotation).
    pub fn transform(&mut self, angle_z: f64, origin: &[f64]) {
        let (s, c) = angle_z.sin_cos();
        let d = self.dim;
        for i in 0..self.n_nodes() {
            let p = &mut self.x[i * d..(i + 1) * d];
            let (x, y) = (p[0], p[1]);
            p[0] = c * x - s * y + origin[0];
            p[1] = s * x + c * y + origin[1];
            if d == 3 {
                p[2] += origin[2];
            }
        }
    }
}

/// Most nodes a 2D scene may have, all bodies together (and so each body): 16 million.
///
/// A run keeps per node the mesh, the elements' reference data, the block Hessian (7
/// blocks of d² f64 per node in a 2D triangle mesh, 15 in a 3D Kuhn tetrahedral mesh), the
/// eliminated system and the solver's vectors or factor. Measured peak resident memory of
/// `stickslip run` (one step, release build, VTK output on or off alike): 2D triangles
/// 1.7 kB per node with CG, and 3.8 kB (90k nodes) to 4.0 kB (361k) with Cholesky, whose
/// fill grows slowly (total ∝ n^1.04: about 75 GB at 16 million); 3D tetrahedra 10.9 kB
/// per node with CG (30k to 227k nodes: 87 GB at 8 million); mass-spring rods and sheets
/// 1–2 kB. The caps keep a run under about 100 GB, what a 128 GB machine can hold.
pub const MAX_SCENE_NODES_2D: usize = 16_000_000;

/// Most nodes a 3D scene may have, all bodies together: 8 million (see
/// [`MAX_SCENE_NODES_2D`] for the memory per node). A sparse Cholesky factor of a 3D mesh
/// grows faster than the node count: [`MAX_CHOLESKY_NODES_3D`] caps it separately.
pub const MAX_SCENE_NODES_3D: usize = 8_000_000;

/// Most nodes of a 3D scene run with the sparse Cholesky solver: 400 thousand. Its factor
/// fills in faster than the node count grows: peak memory of one step measured 1.3 GB at
/// 30k nodes (43 kB per node) and 7.4 GB at 97k (76 kB per node), total ∝ n^1.48, which
/// reaches some 60 GB at 400k. (2D fill grows slowly and fits under the scene cap.)
pub const MAX_CHOLESKY_NODES_3D: usize = 400_000;

/// [`MAX_SCENE_NODES_2D`] or [`MAX_SCENE_NODES_3D`].
pub fn max_scene_nodes(dim: usize) -> usize {
    if dim == 3 {
        MAX_SCENE_NODES_3D
    } else {
        MAX_SCENE_NODES_2D
    }
}

/// Most nodes a generated mesh (rectangle, sheet, box, rod) may have: the larger scene
/// cap. The generators below panic past it; scenes check their own, smaller or equal, cap
/// ([`max_scene_nodes`]) before generating.
pub const MAX_NODES: usize = MAX_SCENE_NODES_2D;

/// Node and element counts of a generated grid with `cells[a]` cells along each axis (a rod
/// has one axis, a rectangle or sheet two, a box three) and `per_cell` elements per cell,
/// in checked arithmetic: None when the node count exceeds [`MAX_NODES`] (or overflows
/// `usize`). Under the cap the element count cannot overflow either.
pub fn grid_counts(cells: &[usize], per_cell: usize) -> Option<(usize, usize)> {
    let mut nodes = 1usize;
    let mut elements = per_cell;
    for &n in cells {
        nodes = nodes.checked_mul(n.checked_add(1)?)?;
        if nodes > MAX_NODES {
            return None;
        }
        elements = elements.checked_mul(n)?;
    }
    Some((nodes, elements))
}

/// [`grid_counts`], panicking past the cap (the generators' callers validate first).
fn grid_counts_or_panic(cells: &[usize], per_cell: usize) -> (usize, usize) {
    grid_counts(cells, per_cell).unwrap_or_else(|| {
        panic!("a mesh of {cells:?} cells has more than {MAX_NODES} nodes (mesh::MAX_NODES)")
    })
}

/// `[0,w]×[0,h]` split into nx×ny cells of two triangles each (alternating diagonals so
/// the mesh has no preferred shear direction). Node (i, j) has index j·(nx+1) + i.
/// In 3D the sheet lies in the plane z = 0.
///
/// # Panics
/// When the mesh would have more than [`MAX_NODES`] nodes (check with [`grid_counts`]).
pub fn rectangle(dim: usize, size: [f64; 2], cells: [usize; 2]) -> Mesh {
    let [nx, ny] = cells;
    let (nodes, n_elements) = grid_counts_or_panic(&cells, 2);
    let mut x = Vec::with_capacity(nodes * dim);
    for j in 0..=ny {
        for i in 0..=nx {
            x.push(size[0] * i as f64 / nx as f64);
            x.push(size[1] * j as f64 / ny as f64);
            if dim == 3 {
                x.push(0.0);
            }
        }
    }
    let id = |i: usize, j: usize| j * (nx + 1) + i;
    let mut elements = Vec::with_capacity(n_elements);
    for j in 0..ny {
        for i in 0..nx {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            // Counter-clockwise triangles; the diagonal alternates like a checkerboard.
            if (i + j) % 2 == 0 {
                elements.push(vec![a, b, c]);
                elements.push(vec![a, c, d]);
            } else {
                elements.push(vec![a, b, d]);
                elements.push(vec![b, c, d]);
            }
        }
    }
    Mesh {
        dim,
        x,
        kind: ElementKind::Triangle,
        elements,
    }
}

/// `[0,lx]×[0,ly]×[0,lz]` split into nx×ny×nz cubes of six tetrahedra each (Kuhn
/// subdivision along the main diagonal, positively oriented, conforming across cubes).
/// Node (i, j, k) has index (k·(ny+1) + j)·(nx+1) + i.
///
/// # Panics
/// When the mesh would have more than [`MAX_NODES`] nodes (check with [`grid_counts`]).
pub fn cuboid(size: [f64; 3], cells: [usize; 3]) -> Mesh {
    let [nx, ny, nz] = cells;
    let (nodes, n_elements) = grid_counts_or_panic(&cells, 6);
    let mut x = Vec::with_capacity(nodes * 3);
    for k in 0..=nz {
        for j in 0..=ny {
            for i in 0..=nx {
                x.push(size[0] * i as f64 / nx as f64);
                x.push(size[1] * j as f64 / ny as f64);
                x.push(size[2] * k as f64 / nz as f64);
            }
        }
    }
    let id = |i: usize, j: usize, k: usize| (k * (ny + 1) + j) * (nx + 1) + i;
    let mut elements = Vec::with_capacity(n_elements);
    // The six monotone paths from corner (0,0,0) to (1,1,1): axis orders.
    const PATHS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                for path in PATHS {
                    let mut c = [i, j, k];
                    let mut tet = vec![id(c[0], c[1], c[2])];
                    for &axis in &path {
                        c[axis] += 1;
                        tet.push(id(c[0], c[1], c[2]));
                    }
                    elements.push(tet);
                }
            }
        }
    }
    let mut m = Mesh {
        dim: 3,
        x,
        kind: ElementKind::Tetrahedron,
        elements,
    };
    orient_positive(&mut m);
    m
}

/// A straight rod of `cells` segments along x from the origin, length `length`.
///
/// # Panics
/// When the rod would have more than [`MAX_NODES`] nodes (check with [`grid_counts`]).
pub fn rod(dim: usize, length: f64, cells: usize) -> Mesh {
    let (nodes, _) = grid_counts_or_panic(&[cells], 1);
    let mut x = Vec::with_capacity(nodes * dim);
    for i in 0..=cells {
        x.push(length * i as f64 / cells as f64);
        x.push(0.0);
        if dim == 3 {
            x.push(0.0);
        }
    }
    Mesh {
        dim,
        x,
        kind: ElementKind::Segment,
        elements: (0..cells).map(|i| vec![i, i + 1]).collect(),
    }
}

/// Reads a Gmsh MSH 4.1 file (ASCII or binary, through `mshio`): 3-node triangles in 2D,
/// 4-node tetrahedra in 3D. Elements of lower dimension (boundary lines, faces, points) are
/// skipped; nodes no kept element uses are dropped (they would carry no mass); the others
/// keep their order in `$Nodes`, so node k is the file's k-th node that an element uses
/// (what `region = { nodes = [k] }` names); triangles are made counter-clockwise and
/// tetrahedra positively oriented. The error says what is wrong, the caller names the
/// file.
pub fn gmsh(dim: usize, bytes: &[u8]) -> Result<Mesh, String> {
    use mshio::mshfile::ElementType;
    use std::collections::HashMap;
    // mshio panics on some malformed files (a data size that overflows or is not an
    // integer width it knows; with overflow checks, a section of zero nodes or
    // elements): they are refused here first.
    let format = msh_format(bytes)?;
    for (name, what) in [(&b"Nodes"[..], "nodes"), (&b"Elements"[..], "elements")] {
        if msh_section_starts(bytes, name)
            .any(|start| msh_section_count(bytes, start, format) == Some(0))
        {
            return Err(format!(
                "its ${} section declares no {what}",
                what_section(name)
            ));
        }
    }
    // A panic left in mshio for a malformed file we did not foresee is this file's
    // error, not a crash.
    let parsed = crate::io::contain_panic(|| mshio::parse_msh_bytes(bytes))
        .ok_or("not a readable Gmsh MSH 4.1 file (its parser failed on it)")?;
    let f = parsed.map_err(|e| {
        // mshio's messages can carry a hex dump of the file: keep one readable line.
        let e = e.to_string();
        let e = e.split("Hex dump").next().unwrap_or_default();
        format!(
            "not a readable Gmsh MSH 4.1 file ({})",
            crate::io::one_line(e, 200)
        )
    })?;
    let nodes = f.data.nodes.ok_or("the file has no $Nodes section")?;
    let els = f.data.elements.ok_or("the file has no $Elements section")?;
    // Node tag → position. The tags are read from the file here: mshio keeps them only
    // when they are sparse, and otherwise numbers the nodes min_node_tag, +1, ... in file
    // order, which misplaces every node of a block listed out of order.
    let counts: Vec<usize> = nodes.node_blocks.iter().map(|b| b.nodes.len()).collect();
    let tags = msh_node_tags(bytes, &counts)?;
    let mut pos: HashMap<u64, [f64; 3]> = HashMap::new();
    for (b, tags) in nodes.node_blocks.iter().zip(&tags) {
        for (&t, n) in tags.iter().zip(&b.nodes) {
            if t == 0 {
                return Err("node tag 0 is reserved and cannot name a node".into());
            }
            if pos.insert(t, [n.x, n.y, n.z]).is_some() {
                return Err(format!("node tag {t} is given to two nodes in $Nodes"));
            }
        }
    }
    let (want, kind) = if dim == 2 {
        (ElementType::Tri3, ElementKind::Triangle)
    } else {
        (ElementType::Tet4, ElementKind::Tetrahedron)
    };
    let mut index: HashMap<u64, usize> = HashMap::new();
    let mut x = Vec::new();
    let mut elements = Vec::new();
    for b in &els.element_blocks {
        if b.entity_dim as usize != dim {
            continue;
        }
        if b.element_type != want {
            return Err(format!(
                "element type {:?} is not supported ({dim}D takes {:?} only)",
                b.element_type, want
            ));
        }
        for e in &b.elements {
            let mut el = Vec::with_capacity(e.nodes.len());
            for &tag in &e.nodes {
                let i = match index.get(&tag) {
                    Some(&i) => i,
                    None => {
                        let p = pos.get(&tag).ok_or_else(|| {
                            format!(
                                "element {} uses node {tag}, which is not in $Nodes",
                                e.element_tag
                            )
                        })?;
                        if dim == 2 && p[2] != 0.0 {
                            return Err(format!(
                                "node {tag} has z = {} but a 2D mesh must lie in z = 0",
                                p[2]
                            ));
                        }
                        if p.iter().any(|v| !v.is_finite()) {
                            return Err(format!("node {tag} has a non-finite coordinate"));
                        }
                        let i = x.len() / dim;
                        x.extend_from_slice(&p[..dim]);
                        index.insert(tag, i);
                        i
                    }
                };
                el.push(i);
            }
            elements.push(el);
        }
    }
    if elements.is_empty() {
        return Err(format!(
            "the file has no {} (element type {:?})",
            if dim == 2 { "triangles" } else { "tetrahedra" },
            want
        ));
    }
    // Nodes were numbered by first use; renumber the kept ones in their $Nodes order.
    let file_order: HashMap<u64, usize> = tags
        .iter()
        .flatten()
        .enumerate()
        .map(|(k, &t)| (t, k))
        .collect();
    // (Every kept tag was found in $Nodes above.)
    let mut kept: Vec<(usize, usize)> = index
        .iter()
        .map(|(t, &i)| (file_order.get(t).copied().unwrap_or(usize::MAX), i))
        .collect();
    kept.sort_unstable();
    let mut renumber = vec![0usize; kept.len()];
    let mut xs = vec![0.0; x.len()];
    for (new, &(_, old)) in kept.iter().enumerate() {
        renumber[old] = new;
        xs[new * dim..(new + 1) * dim].copy_from_slice(&x[old * dim..(old + 1) * dim]);
    }
    let x = xs;
    for el in elements.iter_mut() {
        for i in el.iter_mut() {
            *i = renumber[*i];
        }
    }
    let mut m = Mesh {
        dim,
        x,
        kind,
        elements,
    };
    if dim == 2 {
        for el in m.elements.iter_mut() {
            let p = |k: usize| [m.x[el[k] * 2], m.x[el[k] * 2 + 1]];
            let (a, b, c) = (p(0), p(1), p(2));
            let area2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
            if area2 < 0.0 {
                el.swap(1, 2);
            }
        }
    } else {
        orient_positive(&mut m);
    }
    Ok(m)
}

/// The position just after a line `key` (alone on its line, `\n` or `\r\n` ended)
/// at or after `from`, if any.
fn msh_after(bytes: &[u8], key: &[u8], from: usize) -> Option<usize> {
    let mut at = from;
    while at <= bytes.len() {
        let k = bytes[at..].windows(key.len()).position(|w| w == key)?;
        let start = at + k;
        let line_start = start == 0 || bytes[start - 1] == b'\n';
        let mut end = start + key.len();
        if bytes.get(end) == Some(&b'\r') {
            end += 1;
        }
        if line_start && bytes.get(end) == Some(&b'\n') {
            return Some(end + 1);
        }
        at = start + 1;
    }
    None
}

/// What the $MeshFormat line says: (binary, size of size_t, little-endian), and where
/// its line ends. MSH 4.1 only, ASCII (0) or binary (1), size_t of 4 or 8 bytes; a binary
/// file's byte order from the int 1 that follows the line.
fn msh_format(bytes: &[u8]) -> Result<(bool, usize, bool, usize), String> {
    let bad = |what: &str| format!("not a readable Gmsh MSH 4.1 file ({what})");
    let fmt = msh_after(bytes, b"$MeshFormat", 0).ok_or_else(|| bad("no $MeshFormat line"))?;
    let line_end = bytes[fmt..]
        .iter()
        .position(|&b| b == b'\n')
        .map(|k| fmt + k)
        .ok_or_else(|| bad("the format line does not end"))?;
    let line = std::str::from_utf8(&bytes[fmt..line_end])
        .map_err(|_| bad("the format line is not text"))?;
    let fields: Vec<&str> = line.split_ascii_whitespace().collect();
    let shown = crate::io::one_line(line, 40);
    if fields.len() != 3 || fields[0].parse::<f64>() != Ok(4.1) {
        return Err(bad(&format!(
            "format line '{shown}': expected '4.1 0 8' or '4.1 1 8'"
        )));
    }
    let binary = match fields[1] {
        "0" => false,
        "1" => true,
        _ => {
            return Err(bad(&format!(
                "file type '{}' is not 0 (ASCII) or 1 (binary)",
                crate::io::one_line(fields[1], 20)
            )))
        }
    };
    let size_t = match fields[2] {
        "4" => 4,
        "8" => 8,
        _ => {
            return Err(bad(&format!(
                "data size '{}' is not 4 or 8",
                crate::io::one_line(fields[2], 20)
            )))
        }
    };
    let little = if binary {
        match bytes.get(line_end + 1..line_end + 5) {
            Some(one) if one == 1i32.to_le_bytes() => true,
            Some(one) if one == 1i32.to_be_bytes() => false,
            _ => return Err(bad("no byte-order mark (the int 1) after the format line")),
        }
    } else {
        true
    };
    Ok((binary, size_t, little, line_end))
}

/// A section name as text, for messages.
fn what_section(name: &[u8]) -> String {
    crate::io::one_line(&String::from_utf8_lossy(name), 40)
}

/// Every place where mshio could start parsing a section `$name`: the content after
/// each `$name` followed by `\n` or `\r\n`, anywhere in the file. mshio finds a section
/// where the previous one's parser stopped, which in a malformed binary file can be inside
/// another section's data, so every such place is checked, not only the ones at a line start.
fn msh_section_starts<'a>(bytes: &'a [u8], name: &'a [u8]) -> impl Iterator<Item = usize> + 'a {
    let mut tag = b"$".to_vec();
    tag.extend_from_slice(name);
    let n = tag.len();
    bytes
        .windows(n)
        .enumerate()
        .filter(move |(_, w)| *w == &tag[..])
        .filter_map(move |(k, _)| match bytes.get(k + n..) {
            Some([b'\n', ..]) => Some(k + n + 1),
            Some([b'\r', b'\n', ..]) => Some(k + n + 2),
            _ => None,
        })
}

/// The second number of a section's header (numNodes of $Nodes, numElements of
/// $Elements) for a section whose content starts at `start`; None when it cannot be read.
fn msh_section_count(
    bytes: &[u8],
    start: usize,
    (binary, size_t, little, _): (bool, usize, bool, usize),
) -> Option<u64> {
    if binary {
        let raw = bytes.get(start + size_t..start + 2 * size_t)?;
        let mut w = [0u8; 8];
        Some(if little {
            w[..size_t].copy_from_slice(raw);
            u64::from_le_bytes(w)
        } else {
            w[8 - size_t..].copy_from_slice(raw);
            u64::from_be_bytes(w)
        })
    } else {
        // As mshio reads ASCII numbers: digits between runs of space, tab, CR and LF
        // (any length of them).
        let mut at = start;
        let mut number = || {
            while matches!(bytes.get(at), Some(b' ' | b'\t' | b'\r' | b'\n')) {
                at += 1;
            }
            let digits = bytes[at.min(bytes.len())..]
                .iter()
                .take_while(|b| b.is_ascii_digit())
                .count();
            let text = std::str::from_utf8(&bytes[at..at + digits]).ok()?;
            at += digits;
            text.parse::<u64>().ok()
        };
        number()?;
        number()
    }
}

/// The node tags of each block of the $Nodes section of a MSH 4.1 file (ASCII or
/// binary), read from the bytes; `counts` are the blocks' node counts as mshio parsed
/// them (each block must list exactly as many tags). Parametric nodes are not supported
/// (mshio refuses them), so each node has three coordinates.
fn msh_node_tags(bytes: &[u8], counts: &[usize]) -> Result<Vec<Vec<u64>>, String> {
    const BAD: &str = "the $Nodes section's node tags cannot be read";
    let (binary, size_t, little, line_end) = msh_format(bytes)?;
    let start = msh_after(bytes, b"$Nodes", line_end).ok_or(BAD)?;
    let mut out = Vec::with_capacity(counts.len());
    if binary {
        let mut at = start;
        let mut take = |n: usize| -> Result<&[u8], String> {
            let s = bytes.get(at..at.checked_add(n).ok_or(BAD)?).ok_or(BAD)?;
            at += n;
            Ok(s)
        };
        let uint = |b: &[u8]| -> u64 {
            let mut w = [0u8; 8];
            if little {
                w[..b.len()].copy_from_slice(b);
                u64::from_le_bytes(w)
            } else {
                w[8 - b.len()..].copy_from_slice(b);
                u64::from_be_bytes(w)
            }
        };
        take(4 * size_t)?;
        for &n in counts {
            take(3 * 4)?;
            if uint(take(size_t)?) != n as u64 {
                return Err(BAD.into());
            }
            let raw = take(n.checked_mul(size_t).ok_or(BAD)?)?;
            out.push(raw.chunks_exact(size_t).map(uint).collect());
            take(n.checked_mul(24).ok_or(BAD)?)?;
        }
    } else {
        let text = std::str::from_utf8(&bytes[start..]).map_err(|_| BAD)?;
        let mut tok = text.split_ascii_whitespace();
        let mut next = || tok.next().ok_or(BAD);
        for _ in 0..4 {
            next()?;
        }
        for &n in counts {
            for _ in 0..3 {
                next()?;
            }
            if next()?.parse::<u64>().ok() != Some(n as u64) {
                return Err(BAD.into());
            }
            let mut tags = Vec::with_capacity(n);
            for _ in 0..n {
                let t = next()?;
                tags.push(t.parse::<u64>().map_err(|_| {
                    format!("node tag '{}' is not a tag", crate::io::one_line(t, 40))
                })?);
            }
            out.push(tags);
            for _ in 0..3 * n {
                next()?;
            }
        }
    }
    Ok(out)
}

/// Swaps two nodes of every tetrahedron with negative signed volume.
fn orient_positive(m: &mut Mesh) {
    for e in 0..m.elements.len() {
        let el = m.elements[e].clone();
        let p = |k: usize| {
            let n = &m.x[el[k] * 3..el[k] * 3 + 3];
            [n[0], n[1], n[2]]
        };
        let (p0, p1, p2, p3) = (p(0), p(1), p(2), p(3));
        let a = [p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]];
        let b = [p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]];
        let c = [p3[0] - p0[0], p3[1] - p0[1], p3[2] - p0[2]];
        if dot3(&a, &cross3(&b, &c)) < 0.0 {
            m.elements[e].swap(2, 3);
        }
    }
}

pub(crate) fn dot3(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_meshes_have_the_right_measure() {
        let r = rectangle(2, [2.0, 1.0], [4, 3]);
        let area: f64 = (0..r.elements.len()).map(|e| r.measure(e)).sum();
        assert!((area - 2.0).abs() < 1e-12);
        let b = cuboid([1.0, 2.0, 0.5], [2, 3, 2]);
        let vol: f64 = (0..b.elements.len()).map(|e| b.measure(e)).sum();
        assert!((vol - 1.0).abs() < 1e-12);
        let m = b.lumped_masses(10.0);
        assert!((m.iter().sum::<f64>() - 10.0).abs() < 1e-12);
    }

    #[test]
    fn boundary_measure_is_the_surface() {
        // 2D: the perimeter; interior nodes get nothing.
        let r = rectangle(2, [2.0, 1.0], [4, 3]);
        let w = r.boundary_measure();
        assert!((w.iter().sum::<f64>() - 6.0).abs() < 1e-12);
        assert_eq!(w[5 + 1], 0.0);
        // 3D: the surface area 2(1·2 + 1·0.5 + 2·0.5) = 7.
        let b = cuboid([1.0, 2.0, 0.5], [2, 3, 2]);
        let w = b.boundary_measure();
        assert!((w.iter().sum::<f64>() - 7.0).abs() < 1e-12);
        // A rod in 2D: its length.
        let w = rod(2, 3.0, 5).boundary_measure();
        assert!((w.iter().sum::<f64>() - 3.0).abs() < 1e-12);
    }

    #[test]
    fn grid_counts_are_checked_against_the_cap() {
        assert_eq!(grid_counts(&[4, 3], 2), Some((20, 24)));
        assert_eq!(grid_counts(&[2, 3, 2], 6), Some((36, 72)));
        assert_eq!(grid_counts(&[5], 1), Some((6, 5)));
        // Exactly at the cap, and one past it.
        assert_eq!(
            grid_counts(&[MAX_NODES - 1], 1),
            Some((MAX_NODES, MAX_NODES - 1))
        );
        assert_eq!(grid_counts(&[MAX_NODES], 1), None);
        // (n+1)³ would overflow usize: rejected, not wrapped or saturated.
        assert_eq!(grid_counts(&[usize::MAX, usize::MAX, usize::MAX], 6), None);
        assert_eq!(grid_counts(&[usize::MAX], 1), None);
        assert_eq!(grid_counts(&[1 << 22, 1 << 22, 1 << 22], 6), None);
    }

    #[test]
    #[should_panic(expected = "MAX_NODES")]
    fn generators_panic_past_the_cap() {
        let _ = cuboid([1.0; 3], [1 << 22, 1 << 22, 1 << 22]);
    }
}
