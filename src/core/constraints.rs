//! Per-node linear equality constraints and the per-node change of basis V_i = [C_i F_i].
//!
//! Every constraint touches one node. The rows of all constraints on a node stack into
//! A_i (each row normalized to unit length, its value scaled alike, because a row's scale
//! carries no geometry); the node's number of constrained directions r_i is the numerical
//! rank of A_i: the count of singular values above [`RANK_RTOL`] times the largest. Two
//! planes make a line, three make a sticky node, and nearly redundant rows add nothing.
//!
//! Frames (docs/method.md, "Constraints and node frames"): a free node and a sticky node
//! carry no rotation; a slip whose constrained directions are coordinate axes carries no
//! rotation either (it only masks those axes); every other slip node carries an orthonormal
//! V_i whose first r_i columns span the constrained directions.

use crate::core::linalg::{cross3, dot, norm2, unit};

/// Relative rank tolerance for the stacked, row-normalized constraints of one node: a
/// singular value σ counts when σ > RANK_RTOL · σ_max. Two unit rows at angle θ have
/// σ_min ≈ θ/√2, so rows closer than about 1.4e-8 rad in angle act as one constraint.
pub const RANK_RTOL: f64 = 1e-8;

/// Relative consistency tolerance: rows whose values disagree are contradictory and
/// rejected. A row is missed when the least-squares lift misses its value (along the unit
/// row) by more than max(CONSISTENCY_RTOL · max|value|, 64 ε (σ_max/σ_r)(‖lift‖ + max|value|)):
/// the second term is the rounding a consistent but nearly dependent set of rows
/// (smallest kept singular value σ_r) can produce, at most ~1.4e-6 relative since
/// σ_r > RANK_RTOL · σ_max.
pub const CONSISTENCY_RTOL: f64 = 1e-8;

/// A node's normal is "nearly parallel to e_x" when |n_x| > this; then the tangent is
/// built from e_y instead of e_x, keeping |n × e| ≥ 0.43 (docs/method.md, "Constraints and
/// node frames").
pub const AXIS_SWITCH: f64 = 0.9;

/// The shortest normal, direction or row accepted: the smallest normal f64 (about
/// 2.2e-308). A subnormal length has lost its significant digits, and dividing by it
/// (normalizing, or an offset / |normal|) can overflow.
pub const MIN_LENGTH: f64 = f64::MIN_POSITIVE;

/// At most this many constraint labels are listed when a message names a node's set.
const LABELS_SHOWN: usize = 8;

/// Marks a node without a rotation in [`Frames::rot_index`].
pub const NO_ROTATION: u32 = u32::MAX;

/// What a constraint asks of one node (docs/method.md, "The constrained Newton step").
#[derive(Debug, Clone, PartialEq)]
pub enum ConstraintKind {
    /// The node does not move, or moves by the given displacement.
    Sticky { displacement: Option<Vec<f64>> },
    /// nᵀΔx = offset (3D: a plane; 2D: a line). `normal` need not be unit length.
    Plane { normal: Vec<f64>, offset: f64 },
    /// Δx ∈ offset + span(direction).
    Line {
        direction: Vec<f64>,
        offset: Option<Vec<f64>>,
    },
    /// Any rows a_kᵀΔx = values_k.
    Rows {
        rows: Vec<Vec<f64>>,
        values: Vec<f64>,
    },
}

/// One constraint on one node, with a label that names it in error messages
/// (for example `constraints[3]` or `row 12`).
#[derive(Debug, Clone, PartialEq)]
pub struct Constraint {
    pub node: usize,
    pub kind: ConstraintKind,
    pub label: String,
}

/// Builders. A constraint built here has an empty label; [`crate::Problem`] names it
/// `constraints[k]` (its place in the list) in error messages.
impl Constraint {
    fn unlabelled(node: usize, kind: ConstraintKind) -> Self {
        Constraint {
            node,
            kind,
            label: String::new(),
        }
    }

    /// The node does not move (or moves by [`Constraint::displacement`]).
    pub fn sticky(node: usize) -> Self {
        Self::unlabelled(node, ConstraintKind::Sticky { displacement: None })
    }

    /// nᵀΔx = 0 (3D: a plane; 2D: a line); `normal` need not be unit length. Set the
    /// value with [`Constraint::offset`] or [`Constraint::displacement`].
    pub fn plane(node: usize, normal: &[f64]) -> Self {
        Self::unlabelled(
            node,
            ConstraintKind::Plane {
                normal: normal.to_vec(),
                offset: 0.0,
            },
        )
    }

    /// Δx ∈ span(direction) (3D): the node slides along a line.
    pub fn line(node: usize, direction: &[f64]) -> Self {
        Self::unlabelled(
            node,
            ConstraintKind::Line {
                direction: direction.to_vec(),
                offset: None,
            },
        )
    }

    /// Any rows a_kᵀΔx = values_k on one node.
    pub fn rows(node: usize, rows: &[&[f64]], values: &[f64]) -> Self {
        Self::unlabelled(
            node,
            ConstraintKind::Rows {
                rows: rows.iter().map(|r| r.to_vec()).collect(),
                values: values.to_vec(),
            },
        )
    }

    /// Prescribes a displacement `v` (length d) along the constrained directions: a
    /// sticky node moves by `v`; a plane's value becomes nᵀv; a line passes through `v`;
    /// rows' values become a_kᵀv. A `v` of the wrong length is reported when the problem
    /// is built.
    pub fn displacement(mut self, v: &[f64]) -> Self {
        match &mut self.kind {
            ConstraintKind::Sticky { displacement } => *displacement = Some(v.to_vec()),
            ConstraintKind::Line { offset, .. } => *offset = Some(v.to_vec()),
            ConstraintKind::Plane { normal, offset } => {
                *offset = if v.len() == normal.len() {
                    dot(normal, v)
                } else {
                    f64::NAN // reported as a non-finite offset
                };
            }
            ConstraintKind::Rows { rows, values } => {
                *values = rows
                    .iter()
                    .map(|r| {
                        if r.len() == v.len() {
                            dot(r, v)
                        } else {
                            f64::NAN
                        }
                    })
                    .collect();
            }
        }
        self
    }

    /// The value c of a plane constraint nᵀΔx = c (with n as given, not normalized).
    /// Only planes have a single value: on other kinds this does nothing (use
    /// [`Constraint::displacement`]).
    pub fn offset(mut self, c: f64) -> Self {
        if let ConstraintKind::Plane { offset, .. } = &mut self.kind {
            *offset = c;
        }
        self
    }
}

/// A constraint the model cannot accept. `label` names the constraint (or node).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{label}: {problem}")]
pub struct ConstraintError {
    pub label: String,
    pub problem: String,
    /// The node whose constraints are at fault, when the fault is in one node's set.
    pub node: Option<usize>,
}

fn cerr(label: &str, problem: impl Into<String>) -> ConstraintError {
    ConstraintError {
        label: label.to_string(),
        problem: problem.into(),
        node: None,
    }
}

/// The per-node bases, masks and lifting of a constraint set: everything elimination needs.
#[derive(Debug, Clone, PartialEq)]
pub struct Frames {
    pub dim: usize,
    pub n_nodes: usize,
    /// Per node: bit k set when component k of y_i = V_iᵀΔx_i is constrained.
    pub mask: Vec<u8>,
    /// Per node: index into `rot_nodes` / `rotations`, or [`NO_ROTATION`].
    pub rot_index: Vec<u32>,
    /// The nodes that carry a rotation, ascending.
    pub rot_nodes: Vec<u32>,
    /// d·d values per rotated node: V_i row-major (its columns are the basis [C_i F_i]).
    pub rotations: Vec<f64>,
    /// Δx_p: the minimum-norm per-node displacement meeting the prescribed values
    /// (all zero when the constraints are homogeneous). Length d·n.
    pub lift: Vec<f64>,
    /// True when every prescribed value is zero (Δx_p = 0).
    pub homogeneous: bool,
}

impl Frames {
    /// No constraints at all.
    pub fn unconstrained(dim: usize, n_nodes: usize) -> Self {
        Frames {
            dim,
            n_nodes,
            mask: vec![0; n_nodes],
            rot_index: vec![NO_ROTATION; n_nodes],
            rot_nodes: Vec::new(),
            rotations: Vec::new(),
            lift: vec![0.0; dim * n_nodes],
            homogeneous: true,
        }
    }

    /// Builds frames, masks and the lift from a list of constraints (any order; several
    /// per node combine by rank).
    pub fn build(
        dim: usize,
        n_nodes: usize,
        constraints: &[Constraint],
    ) -> Result<Self, ConstraintError> {
        Self::build_with_tolerance(dim, n_nodes, constraints, 0.0)
    }

    /// [`Frames::build`] with an absolute floor `abs_tol` under the consistency tolerance
    /// (see [`CONSISTENCY_RTOL`]): a row counts as missed only when it misses its value by
    /// more than `abs_tol` too. bc.json and B.mtx use 0 (their values are displacements
    /// with no scale of their own); a scene, whose values are positions, passes the
    /// rounding level of its coordinates.
    pub fn build_with_tolerance(
        dim: usize,
        n_nodes: usize,
        constraints: &[Constraint],
        abs_tol: f64,
    ) -> Result<Self, ConstraintError> {
        if dim != 2 && dim != 3 {
            return Err(cerr("dim", format!("dimension must be 2 or 3, got {dim}")));
        }
        let mut per_node: Vec<Vec<usize>> = Vec::new();
        let mut order: Vec<usize> = (0..constraints.len()).collect();
        for c in constraints {
            validate(dim, n_nodes, c)?;
        }
        order.sort_by_key(|&k| constraints[k].node);
        let mut last = usize::MAX;
        for k in order {
            if constraints[k].node != last {
                per_node.push(Vec::new());
                last = constraints[k].node;
            }
            per_node.last_mut().expect("pushed above").push(k);
        }
        let mut f = Frames::unconstrained(dim, n_nodes);
        for group in per_node {
            let node = constraints[group[0]].node;
            let cs: Vec<&Constraint> = group.iter().map(|&k| &constraints[k]).collect();
            let nf = node_frame(dim, &cs, abs_tol).map_err(|e| ConstraintError {
                node: Some(node),
                ..e
            })?;
            f.mask[node] = nf.mask;
            for a in 0..dim {
                f.lift[node * dim + a] = nf.lift[a];
            }
            if let Some(v) = nf.rotation {
                f.rot_index[node] = f.rot_nodes.len() as u32;
                f.rot_nodes.push(node as u32);
                f.rotations.extend_from_slice(&v[..dim * dim]);
            }
        }
        f.homogeneous = f.lift.iter().all(|&v| v == 0.0);
        Ok(f)
    }

    pub fn ndof(&self) -> usize {
        self.dim * self.n_nodes
    }

    /// True when some node rotates (a slip constraint off the coordinate axes).
    pub fn has_rotation(&self) -> bool {
        !self.rot_nodes.is_empty()
    }

    /// True when some component is constrained.
    pub fn has_constraints(&self) -> bool {
        self.mask.iter().any(|&m| m != 0)
    }

    /// Number of constrained scalar components.
    pub fn constrained_dofs(&self) -> usize {
        self.mask.iter().map(|m| m.count_ones() as usize).sum()
    }

    pub fn free_dofs(&self) -> usize {
        self.ndof() - self.constrained_dofs()
    }

    /// Is component `a` of node `i` (in the node's frame) free?
    #[inline]
    pub fn is_free(&self, i: usize, a: usize) -> bool {
        self.mask[i] & (1 << a) == 0
    }

    /// V_i row-major for a rotated node, None otherwise.
    pub fn rotation(&self, i: usize) -> Option<&[f64]> {
        let r = self.rot_index[i];
        if r == NO_ROTATION {
            None
        } else {
            let dd = self.dim * self.dim;
            Some(&self.rotations[r as usize * dd..(r as usize + 1) * dd])
        }
    }

    /// y = Vᵀ x (per node; nodes without a rotation are copied).
    pub fn to_frame(&self, x: &[f64], y: &mut [f64]) {
        y.copy_from_slice(x);
        let d = self.dim;
        for (r, &node) in self.rot_nodes.iter().enumerate() {
            let v = &self.rotations[r * d * d..(r + 1) * d * d];
            let i = node as usize;
            for c in 0..d {
                let mut s = 0.0;
                for k in 0..d {
                    s += v[k * d + c] * x[i * d + k];
                }
                y[i * d + c] = s;
            }
        }
    }

    /// x = V y (per node; nodes without a rotation are copied).
    pub fn from_frame(&self, y: &[f64], x: &mut [f64]) {
        x.copy_from_slice(y);
        let d = self.dim;
        for (r, &node) in self.rot_nodes.iter().enumerate() {
            let v = &self.rotations[r * d * d..(r + 1) * d * d];
            let i = node as usize;
            for k in 0..d {
                let mut s = 0.0;
                for c in 0..d {
                    s += v[k * d + c] * y[i * d + c];
                }
                x[i * d + k] = s;
            }
        }
    }

    /// x ← V x in place, per rotated node.
    pub fn from_frame_in_place(&self, x: &mut [f64]) {
        let d = self.dim;
        for (r, &node) in self.rot_nodes.iter().enumerate() {
            let v = &self.rotations[r * d * d..(r + 1) * d * d];
            let i = node as usize;
            let mut t = [0.0f64; 3];
            t[..d].copy_from_slice(&x[i * d..i * d + d]);
            for k in 0..d {
                x[i * d + k] = (0..d).map(|c| v[k * d + c] * t[c]).sum();
            }
        }
    }

    /// x ← Vᵀ x in place, per rotated node.
    pub fn to_frame_in_place(&self, x: &mut [f64]) {
        let d = self.dim;
        for (r, &node) in self.rot_nodes.iter().enumerate() {
            let v = &self.rotations[r * d * d..(r + 1) * d * d];
            let i = node as usize;
            let mut t = [0.0f64; 3];
            t[..d].copy_from_slice(&x[i * d..i * d + d]);
            for c in 0..d {
                x[i * d + c] = (0..d).map(|k| v[k * d + c] * t[k]).sum();
            }
        }
    }

    /// Zeroes the constrained components of a vector in frame coordinates (applies P).
    pub fn apply_mask(&self, y: &mut [f64]) {
        let d = self.dim;
        for (i, &m) in self.mask.iter().enumerate() {
            if m != 0 {
                for a in 0..d {
                    if m & (1 << a) != 0 {
                        y[i * d + a] = 0.0;
                    }
                }
            }
        }
    }
}

/// Stacked unit rows and values of every constraint in `cs` (all on one node).
pub fn node_rows(dim: usize, c: &Constraint) -> (Vec<Vec<f64>>, Vec<f64>) {
    match &c.kind {
        ConstraintKind::Sticky { displacement } => {
            let mut rows = Vec::new();
            let mut vals = Vec::new();
            for a in 0..dim {
                let mut r = vec![0.0; dim];
                r[a] = 1.0;
                rows.push(r);
                vals.push(displacement.as_ref().map_or(0.0, |d| d[a]));
            }
            (rows, vals)
        }
        ConstraintKind::Plane { normal, offset } => (vec![normal.clone()], vec![*offset]),
        ConstraintKind::Line { direction, offset } => {
            let t = unit(direction);
            let cons = line_constrained_dirs(dim, &t);
            let vals = cons
                .iter()
                .map(|c| offset.as_ref().map_or(0.0, |o| dot(c, o)))
                .collect();
            (cons, vals)
        }
        ConstraintKind::Rows { rows, values } => (rows.clone(), values.clone()),
    }
}

fn validate(dim: usize, n_nodes: usize, c: &Constraint) -> Result<(), ConstraintError> {
    let l = &c.label;
    if c.node >= n_nodes {
        return Err(cerr(
            l,
            format!(
                "node {} is out of range (the system has {n_nodes} nodes, numbered from 0)",
                c.node
            ),
        ));
    }
    let vec_check = |name: &str, v: &[f64], nonzero: bool| -> Result<(), ConstraintError> {
        if v.len() != dim {
            return Err(cerr(
                l,
                format!("{name} has {} components, expected {dim}", v.len()),
            ));
        }
        if let Some(k) = v.iter().position(|x| !x.is_finite()) {
            return Err(cerr(l, format!("{name}[{k}] is not finite")));
        }
        if nonzero {
            if v.iter().all(|&x| x == 0.0) {
                return Err(cerr(l, format!("{name} is zero")));
            }
            // A vector can be finite with a norm that overflows (entries near 1e200), or
            // so short (subnormal) that it has lost its digits and 1/length overflows.
            let len = norm2(v);
            if !len.is_finite() {
                return Err(cerr(l, format!("{name} has a length that overflows f64")));
            }
            if len < MIN_LENGTH {
                return Err(cerr(
                    l,
                    format!(
                        "{name} has length {len:e}, below {MIN_LENGTH:.1e} (the smallest normal f64): too short to normalize reliably"
                    ),
                ));
            }
        }
        Ok(())
    };
    match &c.kind {
        ConstraintKind::Sticky { displacement } => {
            if let Some(d) = displacement {
                vec_check("displacement", d, false)?;
            }
        }
        ConstraintKind::Plane { normal, offset } => {
            vec_check("normal", normal, true)?;
            if !offset.is_finite() {
                return Err(cerr(l, "offset is not finite"));
            }
        }
        ConstraintKind::Line { direction, offset } => {
            vec_check("direction", direction, true)?;
            if let Some(o) = offset {
                vec_check("offset", o, false)?;
            }
        }
        ConstraintKind::Rows { rows, values } => {
            if rows.is_empty() {
                return Err(cerr(l, "rows is empty"));
            }
            if values.len() != rows.len() {
                return Err(cerr(
                    l,
                    format!(
                        "values has {} entries but there are {} rows",
                        values.len(),
                        rows.len()
                    ),
                ));
            }
            for (k, r) in rows.iter().enumerate() {
                vec_check(&format!("rows[{k}]"), r, true)?;
            }
            if let Some(k) = values.iter().position(|x| !x.is_finite()) {
                return Err(cerr(l, format!("values[{k}] is not finite")));
            }
        }
    }
    Ok(())
}

struct NodeFrame {
    mask: u8,
    rotation: Option<[f64; 9]>,
    lift: [f64; 3],
}

/// Names the constraints of one node in messages: the constraint's own label when there is
/// one, else `node N (a, b, ...)` listing at most [`LABELS_SHOWN`] of them.
fn node_label(cs: &[&Constraint]) -> String {
    if cs.len() == 1 {
        return cs[0].label.clone();
    }
    let names: Vec<&str> = cs
        .iter()
        .take(LABELS_SHOWN)
        .map(|c| c.label.as_str())
        .collect();
    let more = if cs.len() > LABELS_SHOWN {
        format!(" and {} more", cs.len() - LABELS_SHOWN)
    } else {
        String::new()
    };
    format!("node {} ({}{more})", cs[0].node, names.join(", "))
}

/// The lift must be a finite displacement: values near the top of the f64 range, or
/// divided by a short row, can overflow.
fn check_lift(dim: usize, label: &str, lift: &[f64; 3]) -> Result<(), ConstraintError> {
    if lift[..dim].iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(cerr(
            label,
            format!(
                "the prescribed displacement is not finite ({:?}): the prescribed values overflow f64",
                &lift[..dim]
            ),
        ))
    }
}

/// The frame, mask and lift of one node from all its constraints: a single sticky,
/// plane or line constraint takes its exact path; anything else is stacked as unit rows,
/// reduced to a d×d block, decomposed (SVD: rank and minimum-norm lift), checked for
/// consistency, and the frame follows from the rank.
fn node_frame(dim: usize, cs: &[&Constraint], abs_tol: f64) -> Result<NodeFrame, ConstraintError> {
    let label = node_label(cs);
    if let [c] = cs {
        if let Some(f) = single_frame(dim, c, &label)? {
            return Ok(f);
        }
    }
    let stacked = unit_rows(dim, cs, &label)?;
    let (block, c) = reduce_rows(dim, &stacked.rows, &stacked.vals);
    let dec = RowDecomposition::new(dim, &block, &c, &label)?;
    check_lift(dim, &label, &dec.lift)?;
    check_consistency(dim, cs, &stacked, &dec, abs_tol, &label)?;
    Ok(dec.frame(dim))
}

/// The fast exact paths of a single sticky, plane or line constraint (the frame then
/// matches the seeds' construction to the last bit); None for rows, which take the
/// general path.
fn single_frame(
    dim: usize,
    c: &Constraint,
    label: &str,
) -> Result<Option<NodeFrame>, ConstraintError> {
    let mut lift = [0.0; 3];
    let frame = match &c.kind {
        ConstraintKind::Sticky { displacement } => {
            if let Some(d) = displacement {
                lift[..dim].copy_from_slice(d);
            }
            check_lift(dim, label, &lift)?;
            NodeFrame {
                mask: (1u8 << dim) - 1,
                rotation: None,
                lift,
            }
        }
        ConstraintKind::Plane { normal, offset } => {
            let len = norm2(normal);
            let along = offset / len;
            if !along.is_finite() {
                return Err(cerr(
                    label,
                    format!(
                        "offset / |normal| = {offset:e} / {len:e} overflows f64: the plane is not at a finite distance"
                    ),
                ));
            }
            let n = unit(normal);
            for a in 0..dim {
                lift[a] = n[a] * along;
            }
            check_lift(dim, label, &lift)?;
            frame_from_constrained(dim, &[n], lift)
        }
        ConstraintKind::Line { direction, offset } => {
            let t = unit(direction);
            if let Some(o) = offset {
                // Minimum-norm point of o + span(t): remove the t component.
                let ot = dot(o, &t);
                for a in 0..dim {
                    lift[a] = o[a] - ot * t[a];
                }
            }
            check_lift(dim, label, &lift)?;
            line_frame(dim, &t, lift)
        }
        ConstraintKind::Rows { .. } => return Ok(None),
    };
    Ok(Some(frame))
}

/// The frame of a node free only along the unit direction `t`; in 3D with the seed's line
/// frame V = [m l t] exactly.
fn line_frame(dim: usize, t: &[f64], lift: [f64; 3]) -> NodeFrame {
    let cons = line_constrained_dirs(dim, t);
    let mut f = frame_from_constrained(dim, &cons, lift);
    if dim == 3 && f.rotation.is_some() {
        let t3 = [t[0], t[1], t[2]];
        let (m, l) = tangents(&t3);
        f.rotation = Some(columns3(&m, &l, &t3));
    }
    f
}

/// A node's constraint rows scaled to unit length, with their values.
struct UnitRows {
    rows: Vec<[f64; 3]>,
    vals: Vec<f64>,
    /// Per row: the index in the node's constraints of the one it comes from (named in
    /// messages).
    owner: Vec<usize>,
}

/// Stacks every row of `cs` as a unit row with its value divided by the row's length; a
/// value that overflows there is an error naming the entry.
fn unit_rows(dim: usize, cs: &[&Constraint], label: &str) -> Result<UnitRows, ConstraintError> {
    let mut out = UnitRows {
        rows: Vec::new(),
        vals: Vec::new(),
        owner: Vec::new(),
    };
    for (ci, c) in cs.iter().enumerate() {
        let (r, v) = node_rows(dim, c);
        for (ri, (row, val)) in r.into_iter().zip(v).enumerate() {
            let len = norm2(&row);
            let scaled = val / len;
            if !scaled.is_finite() {
                let who = if cs.len() > 1 {
                    format!("{}: ", c.label)
                } else {
                    String::new()
                };
                let which = match &c.kind {
                    ConstraintKind::Rows { rows, .. } if rows.len() > 1 => {
                        format!("values[{ri}] / |rows[{ri}]|")
                    }
                    ConstraintKind::Rows { .. } => "the value / |row|".to_string(),
                    ConstraintKind::Plane { .. } => "offset / |normal|".to_string(),
                    _ => "the prescribed value".to_string(),
                };
                return Err(cerr(
                    label,
                    format!(
                        "{who}{which} = {val:e} / {len:e} overflows f64: the prescribed displacement is not finite"
                    ),
                ));
            }
            let mut u = [0.0; 3];
            for a in 0..dim {
                u[a] = row[a] / len;
            }
            out.rows.push(u);
            out.vals.push(scaled);
            out.owner.push(ci);
        }
    }
    Ok(out)
}

/// The d×d block to decompose and the values it carries. Up to d rows: the rows
/// themselves, zero-padded (V complete). More rows: rank ≤ d, so the Householder QR
/// [A | vals] = Q [R | c] reduces them to R (d×d) and c = Q₁ᵀvals first; A = Q₁R has
/// R's singular values and right singular vectors, and U_Aᵀvals = U_Rᵀc. Orthogonal
/// transformations keep the conditioning of A (forming AᵀA would square it), and the
/// memory is O(k·d), not the k×k U of a full SVD of A.
fn reduce_rows(dim: usize, rows: &[[f64; 3]], vals: &[f64]) -> ([[f64; 3]; 3], [f64; 3]) {
    let k = rows.len();
    if k <= dim {
        let mut b = [[0.0; 3]; 3];
        let mut c = [0.0; 3];
        b[..k].copy_from_slice(rows);
        c[..k].copy_from_slice(vals);
        return (b, c);
    }
    // vals scaled to max |value| ≤ 1 for the reduction (c is linear in vals): finite
    // values near 1e307 must not overflow in the reflections' sums.
    let vmax = vals.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let vs = if vmax > 0.0 { vmax } else { 1.0 };
    let scaled: Vec<f64> = vals.iter().map(|v| v / vs).collect();
    let (b, mut c) = householder_reduce(dim, rows, &scaled);
    c.iter_mut().for_each(|x| *x *= vs);
    (b, c)
}

/// The SVD of a node's reduced block: singular values in decreasing order, the rank, the
/// right singular vectors and the minimum-norm lift of the kept triplets.
struct RowDecomposition {
    /// Singular values, largest first.
    sigma: Vec<f64>,
    /// Right singular vectors in the order of `sigma`, as columns of d values.
    dirs: Vec<Vec<f64>>,
    rank: usize,
    lift: [f64; 3],
}

impl RowDecomposition {
    fn new(
        dim: usize,
        block: &[[f64; 3]; 3],
        c: &[f64; 3],
        label: &str,
    ) -> Result<Self, ConstraintError> {
        // faer's dense SVD: accurate to round-off on rank-deficient blocks (nalgebra 0.34's
        // SVD was seen to return a factorization off by 5e-2 on such a 3×3, see tests).
        let a = faer::Mat::<f64>::from_fn(dim, dim, |i, j| block[i][j]);
        let svd = a.svd().map_err(|e| {
            cerr(
                label,
                format!("the singular value decomposition of the rows failed: {e:?}"),
            )
        })?;
        let (u, sv, v) = (svd.U(), svd.S(), svd.V());
        let sv: Vec<f64> = (0..dim).map(|j| sv[j]).collect();
        let mut idx: Vec<usize> = (0..dim).collect();
        idx.sort_by(|&p, &q| sv[q].total_cmp(&sv[p]));
        let smax = sv[idx[0]];
        let rank = idx.iter().filter(|&&j| sv[j] > RANK_RTOL * smax).count();
        let mut lift = [0.0; 3];
        for &j in idx.iter().take(rank) {
            let ub: f64 = (0..dim).map(|i| u[(i, j)] * c[i]).sum();
            let coef = ub / sv[j];
            for a in 0..dim {
                lift[a] += coef * v[(a, j)];
            }
        }
        Ok(RowDecomposition {
            sigma: idx.iter().map(|&j| sv[j]).collect(),
            dirs: idx
                .iter()
                .map(|&j| (0..dim).map(|a| v[(a, j)]).collect())
                .collect(),
            rank,
            lift,
        })
    }

    /// The frame of the rank: free (0), fixed (d), one constrained direction, or (3D,
    /// rank 2) free along the remaining right singular vector.
    fn frame(&self, dim: usize) -> NodeFrame {
        let lift = self.lift;
        match (dim, self.rank) {
            (_, 0) => NodeFrame {
                mask: 0,
                rotation: None,
                lift,
            },
            (d, r) if r == d => NodeFrame {
                mask: (1u8 << d) - 1,
                rotation: None,
                lift,
            },
            (_, 1) => frame_from_constrained(dim, &[unit(&self.dirs[0])], lift),
            (3, 2) => line_frame(3, &unit(&self.dirs[2]), lift),
            _ => unreachable!("rank is at most dim"),
        }
    }
}

/// Every row must hold at the lift within a tolerance that scales with the values, the
/// conditioning of the kept rows and the lift's size; the worst row names the
/// contradiction (a NaN miss, from values that overflow in the product, counts as the
/// worst).
fn check_consistency(
    dim: usize,
    cs: &[&Constraint],
    stacked: &UnitRows,
    dec: &RowDecomposition,
    abs_tol: f64,
    label: &str,
) -> Result<(), ConstraintError> {
    let lift = &dec.lift;
    let vmax = stacked.vals.iter().fold(0.0f64, |s, v| s.max(v.abs()));
    let lift_norm = norm2(&lift[..dim]);
    let smax = dec.sigma[0];
    let smin_kept = if dec.rank > 0 {
        dec.sigma[dec.rank - 1]
    } else {
        smax
    };
    let tol = (CONSISTENCY_RTOL * vmax)
        .max(64.0 * f64::EPSILON * (smax / smin_kept) * (lift_norm + vmax))
        .max(abs_tol);
    let mut worst: Option<(usize, f64)> = None;
    for (i, row) in stacked.rows.iter().enumerate() {
        let miss = (dot(&row[..dim], &lift[..dim]) - stacked.vals[i]).abs();
        if (miss.is_nan() || miss > tol) && worst.is_none_or(|(_, w)| miss.is_nan() || miss > w) {
            worst = Some((i, miss));
        }
    }
    let Some((i, miss)) = worst else {
        return Ok(());
    };
    let of = if cs.len() > 1 {
        format!(" of {}", cs[stacked.owner[i]].label)
    } else {
        String::new()
    };
    Err(cerr(
        label,
        format!(
            "contradictory constraints on node {}: the rows cannot all hold (a row{of} misses its value by {miss:.3e})",
            cs[0].node
        ),
    ))
}

/// Householder QR of the k×d block of unit rows with its values as an extra column,
/// [A | vals] = Q [R | c] (k > d): returns R's d×d upper triangle (row-major) and the first
/// d entries of c = Qᵀvals. Each reflector is computed from its column scaled by the
/// column's largest entry, so neither its norm nor vᵀv can underflow or overflow. Time
/// O(k·d²), memory O(k·d).
fn householder_reduce(dim: usize, rows: &[[f64; 3]], vals: &[f64]) -> ([[f64; 3]; 3], [f64; 3]) {
    let k = rows.len();
    // Column-major [A | vals].
    let mut cols: Vec<Vec<f64>> = (0..dim)
        .map(|j| rows.iter().map(|r| r[j]).collect())
        .collect();
    cols.push(vals.to_vec());
    let mut v = vec![0.0; k];
    for j in 0..dim {
        let s = cols[j][j..].iter().fold(0.0f64, |m, x| m.max(x.abs()));
        if s == 0.0 {
            continue; // the column is already zero below the diagonal
        }
        let vj = &mut v[..k - j];
        for (vi, x) in vj.iter_mut().zip(&cols[j][j..]) {
            *vi = x / s;
        }
        let nv = vj.iter().map(|x| x * x).sum::<f64>().sqrt();
        // alpha = −sign(v₀)‖v‖ avoids cancellation in v₀ − alpha.
        let alpha = if vj[0] >= 0.0 { -nv } else { nv };
        vj[0] -= alpha;
        // vᵀv = 2‖v‖(‖v‖ + |v₀|) ≥ 2, since the largest |entry| of v is 1.
        let vtv: f64 = vj.iter().map(|x| x * x).sum();
        for col in cols.iter_mut().skip(j + 1) {
            let t = 2.0 * vj.iter().zip(&col[j..]).map(|(a, b)| a * b).sum::<f64>() / vtv;
            for (x, vi) in col[j..].iter_mut().zip(vj.iter()) {
                *x -= t * vi;
            }
        }
        cols[j][j] = alpha * s;
        for x in cols[j][j + 1..].iter_mut() {
            *x = 0.0;
        }
    }
    let mut r = [[0.0; 3]; 3];
    let mut c = [0.0; 3];
    for i in 0..dim {
        for j in i..dim {
            r[i][j] = cols[j][i];
        }
        c[i] = cols[dim][i];
    }
    (r, c)
}

/// Builds the frame from orthonormal constrained directions: mask only when they are
/// coordinate axes, else a rotation whose first columns are the constrained directions.
fn frame_from_constrained(dim: usize, cons: &[Vec<f64>], lift: [f64; 3]) -> NodeFrame {
    let axis_of = |v: &[f64]| -> Option<usize> {
        let nz: Vec<usize> = (0..dim).filter(|&a| v[a] != 0.0).collect();
        (nz.len() == 1).then(|| nz[0])
    };
    let axes: Vec<Option<usize>> = cons.iter().map(|c| axis_of(c)).collect();
    if axes.iter().all(|a| a.is_some()) {
        let mask = axes.iter().fold(0u8, |m, a| m | (1 << a.expect("checked")));
        return NodeFrame {
            mask,
            rotation: None,
            lift,
        };
    }
    let r = cons.len();
    let mut v = [0.0; 9];
    match dim {
        2 => {
            let n = &cons[0];
            v[0] = n[0];
            v[1] = -n[1];
            v[2] = n[1];
            v[3] = n[0];
        }
        _ => {
            let cols = if r == 1 {
                let n = [cons[0][0], cons[0][1], cons[0][2]];
                let (m, l) = tangents(&n);
                columns3(&n, &m, &l)
            } else {
                let c0 = [cons[0][0], cons[0][1], cons[0][2]];
                let c1 = [cons[1][0], cons[1][1], cons[1][2]];
                let t = unit(&cross3(&c0, &c1));
                columns3(&c0, &c1, &[t[0], t[1], t[2]])
            };
            v = cols;
        }
    }
    NodeFrame {
        mask: (1u8 << r) - 1,
        rotation: Some(v),
        lift,
    }
}

/// The two constrained directions of a line with unit direction t (3D), or the one
/// normal of a 2D line.
fn line_constrained_dirs(dim: usize, t: &[f64]) -> Vec<Vec<f64>> {
    if dim == 2 {
        vec![vec![-t[1], t[0]]]
    } else {
        let (m, l) = tangents(&[t[0], t[1], t[2]]);
        vec![m.to_vec(), l.to_vec()]
    }
}

/// m = normalize(n × e_x) (or e_y when n is nearly parallel to e_x), l = n × m.
pub fn tangents(n: &[f64; 3]) -> ([f64; 3], [f64; 3]) {
    let e = if n[0].abs() > AXIS_SWITCH {
        [0.0, 1.0, 0.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let m = unit(&cross3(n, &e));
    let m = [m[0], m[1], m[2]];
    let l = cross3(n, &m);
    (m, l)
}

/// Row-major 3×3 matrix with the given columns.
fn columns3(a: &[f64; 3], b: &[f64; 3], c: &[f64; 3]) -> [f64; 9] {
    [a[0], b[0], c[0], a[1], b[1], c[1], a[2], b[2], c[2]]
}

#[cfg(test)]
mod tests;
