//! The operations of the Newton loop's boundary conditions: the static projections of
//! the start of a step, the moving nodes' penalty terms, and the node lists read and
//! written when moving nodes snap to their targets.

use super::*;

/// One unsnapped moving node's penalty: ½ k_M m ‖r‖² − √m λ·r with r the node's offset
/// from `shape` (the target set at the end of the step; slip: along the normal
/// directions only), as the CPU's `Stepper` (integrator `offset`, `projector`).
#[derive(Debug, Clone, PartialEq)]
pub struct MovingTerm {
    pub node: usize,
    pub shape: BcShape,
    /// k_M · m of the node.
    pub coef: f64,
    /// √m · λ, the node's augmented-Lagrangian multiplier scaled by √m.
    pub sqrt_m_lambda: [f64; 3],
}

/// A node's static projection x_i ↦ P x_i + c.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticProjection {
    pub node: usize,
    /// P, row-major 3×3 (its d×d corner used).
    pub p: [f64; 9],
    pub c: [f64; 3],
}

/// The static projections of a scene's start of step, as `Stepper` applies them: a node
/// with one static condition onto its set (sticky: P = 0, c = anchor; plane: P = I − nnᵀ,
/// c = (offset) n; line: P = ttᵀ, c = p − ttᵀp), a node with several onto their
/// intersection (`JointTarget`: P = Σ f fᵀ over its free directions, c = point − P point).
pub fn static_projections(scene: &Scene) -> Result<Vec<StaticProjection>, String> {
    let d = scene.dim;
    let joint = joint_targets(d, &scene.x0, &scene.bcs, scene.characteristic_length)
        .map_err(|e| format!("{}: {}", e.label, e.problem))?;
    let mut is_joint = vec![false; scene.model.n_nodes];
    for j in &joint {
        is_joint[j.node] = true;
    }
    let mut out = Vec::new();
    for b in scene
        .bcs
        .iter()
        .filter(|b| b.motion.is_none() && !is_joint[b.node])
    {
        let (mut p, mut c) = ([0.0; 9], [0.0; 3]);
        match &b.shape {
            BcShape::Sticky { anchor } => c = *anchor,
            BcShape::Plane { normal, offset } => {
                for a in 0..3 {
                    for k in 0..3 {
                        p[a * 3 + k] = if a == k { 1.0 } else { 0.0 } - normal[a] * normal[k];
                    }
                    c[a] = offset * normal[a];
                }
            }
            BcShape::Line { point, direction } => {
                for a in 0..3 {
                    for k in 0..3 {
                        p[a * 3 + k] = direction[a] * direction[k];
                    }
                }
                for a in 0..3 {
                    c[a] = point[a] - (0..3).map(|k| p[a * 3 + k] * point[k]).sum::<f64>();
                }
            }
        }
        out.push(StaticProjection { node: b.node, p, c });
    }
    for j in &joint {
        let mut p = [0.0; 9];
        for f in &j.free {
            for a in 0..3 {
                for k in 0..3 {
                    p[a * 3 + k] += f[a] * f[k];
                }
            }
        }
        let mut c = [0.0; 3];
        for a in 0..3 {
            c[a] = j.point[a] - (0..3).map(|k| p[a * 3 + k] * j.point[k]).sum::<f64>();
        }
        out.push(StaticProjection { node: j.node, p, c });
    }
    Ok(out)
}

impl NewtonOps {
    /// The static projections applied by [`NewtonOps::begin_step`] (uploaded once; each
    /// node at most once).
    pub fn set_static_projections(&mut self, proj: &[StaticProjection]) -> Result<(), GpuError> {
        let nodes = self.node_indices(proj.iter().map(|p| p.node), "static projection")?;
        let mut table = Vec::with_capacity(proj.len() * PROJ_STRIDE);
        for p in proj {
            table.extend_from_slice(&p.p);
            table.extend_from_slice(&p.c);
        }
        let values = self.table("newton static projections", &to_bytes(true, &table))?;
        let index = self.table(
            "newton static projection nodes",
            bytemuck::cast_slice(&nodes),
        )?;
        let op = self.op(
            "static projection",
            Entry::ProjectStatic,
            OpsParams {
                count: proj.len() as u32,
                ..OpsParams::default()
            },
            Varying {
                table: Some(&values.buf),
                index: Some(&index.buf),
                ..Varying::default()
            },
        );
        self.proj = Some(StaticProjections {
            count: proj.len(),
            _values: values,
            _index: index,
            op,
        });
        Ok(())
    }

    /// Node indices as u32, each in range and listed once.
    pub(super) fn node_indices(
        &self,
        nodes: impl Iterator<Item = usize>,
        what: &str,
    ) -> Result<Vec<u32>, GpuError> {
        let mut seen = vec![false; self.n_nodes];
        nodes
            .map(|i| {
                if i >= self.n_nodes {
                    return Err(GpuError::Mismatch(format!(
                        "{what} of node {i}, the mesh has {}",
                        self.n_nodes
                    )));
                }
                if std::mem::replace(&mut seen[i], true) {
                    return Err(GpuError::Mismatch(format!("{what}: node {i} listed twice")));
                }
                Ok(i as u32)
            })
            .collect()
    }

    /// The unsnapped moving nodes' penalty terms (each node at most once); an empty list
    /// removes them.
    pub fn set_moving(&mut self, terms: &[MovingTerm]) -> Result<(), GpuError> {
        let nodes = self.node_indices(terms.iter().map(|t| t.node), "moving term")?;
        let mut table = Vec::with_capacity(terms.len() * MOVING_STRIDE);
        let mut index = Vec::with_capacity(terms.len() * MOVING_INDEX_STRIDE);
        for (t, &node) in terms.iter().zip(&nodes) {
            let (kind, a, off, dir) = match &t.shape {
                BcShape::Sticky { anchor } => (0u32, *anchor, 0.0, [0.0; 3]),
                BcShape::Plane { normal, offset } => (1, *normal, *offset, [0.0; 3]),
                BcShape::Line { point, direction } => (2, *point, 0.0, *direction),
            };
            table.extend_from_slice(&a);
            table.push(off);
            table.extend_from_slice(&dir);
            table.push(t.coef);
            table.extend_from_slice(&t.sqrt_m_lambda);
            table.push(0.0);
            let (chunk, blk) = self.diag[node as usize];
            index.extend_from_slice(&[node, kind, blk, chunk]);
        }
        let count = terms.len();
        let slot = slot_count(self.energy.len()) - 1;
        let p = |mode: u32, c: usize| OpsParams {
            count: c as u32,
            mode,
            slot: slot as u32,
            aux: 0,
        };
        // Reuse the buffers (and bind groups) while the new data fits.
        let groups = self.groups;
        if let Some(m) = &mut self.moving {
            let vb = to_bytes(true, &table);
            let ib: &[u8] = bytemuck::cast_slice(&index);
            if vb.len() as u64 <= m.values.bytes && ib.len() as u64 <= m.index.bytes {
                let ctx = &self.binder.ctx;
                ctx.write_buffer(&m.values.buf, 0, &vb);
                ctx.write_buffer(&m.index.buf, 0, ib);
                m.count = count;
                for (ch, add) in m.adds.iter().enumerate() {
                    let q = OpsParams {
                        aux: ch as u32,
                        ..p(0, count)
                    };
                    ctx.write_buffer(&add.params, 0, bytemuck::bytes_of(&q));
                }
                for (op, q) in [
                    (&m.energy, p(MODE_MOVING_ENERGY, count)),
                    (&m.energy_finish, p(MODE_MOVING_ENERGY, groups)),
                ] {
                    ctx.write_buffer(&op.params, 0, bytemuck::bytes_of(&q));
                }
                return Ok(());
            }
        }
        let values = self.table("newton moving terms", &to_bytes(true, &table))?;
        let idx = self.table("newton moving nodes", bytemuck::cast_slice(&index))?;
        let var = Varying {
            table: Some(&values.buf),
            index: Some(&idx.buf),
            ..Varying::default()
        };
        // One update per values chunk (aux: its index): each writes the blocks in its
        // chunk, the first the gradient too.
        let adds: Vec<Op> = self
            .binder
            .hvals
            .iter()
            .enumerate()
            .map(|(ch, h)| {
                self.op(
                    "add moving",
                    Entry::AddMoving,
                    OpsParams {
                        aux: ch as u32,
                        ..p(0, count)
                    },
                    Varying {
                        hvals: Some(h),
                        ..var
                    },
                )
            })
            .collect();
        let red = self.op(
            "moving energy",
            Entry::Reduce,
            p(MODE_MOVING_ENERGY, count),
            var,
        );
        let fin = self.op(
            "moving energy finish",
            Entry::Finish,
            p(MODE_MOVING_ENERGY, self.groups),
            var,
        );
        self.moving = Some(MovingTerms {
            count,
            values,
            index: idx,
            adds,
            energy: red,
            energy_finish: fin,
        });
        Ok(())
    }

    /// Adds the moving terms to the assembled gradient (k m r − P √m λ) and to their
    /// nodes' diagonal blocks of H (k m P), at the evaluation positions; after
    /// [`GpuAssembly::assemble`].
    pub fn add_moving(&self) -> Result<(), GpuError> {
        if let Some(m) = &self.moving {
            let grid = Self::grid(m.count);
            let ops: Vec<_> = m.adds.iter().map(|a| (a, grid)).collect();
            self.run("newton add moving", &ops, |_| {})?;
        }
        Ok(())
    }

    /// Σ ½ k m ‖r‖² − √m λ·r over the moving terms at the evaluation positions (0 without
    /// any).
    pub fn moving_energy(&self) -> Result<f64, GpuError> {
        let Some(m) = &self.moving else {
            return Ok(0.0);
        };
        if m.count == 0 {
            return Ok(0.0);
        }
        self.run(
            "newton moving energy",
            &[(&m.energy, self.groups), (&m.energy_finish, 1)],
            |_| {},
        )?;
        Ok(self.read_result(slot_count(self.energy.len()) - 1, 1)?[0])
    }

    /// x of the listed nodes (node after node, d each).
    pub fn read_nodes(&mut self, nodes: &[usize]) -> Result<Vec<f64>, GpuError> {
        if nodes.is_empty() {
            return Ok(Vec::new());
        }
        let idx: Vec<u32> = nodes
            .iter()
            .map(|&i| {
                if i < self.n_nodes {
                    Ok(i as u32)
                } else {
                    Err(GpuError::Mismatch(format!(
                        "node {i} read, the mesh has {}",
                        self.n_nodes
                    )))
                }
            })
            .collect::<Result<_, _>>()?;
        let fits = self
            .nodes
            .as_ref()
            .is_some_and(|list| list.capacity >= nodes.len());
        if !fits {
            let cap = nodes.len().next_power_of_two();
            let index = self.table("newton node list", &vec![0u8; cap * 4])?;
            let vals = self.table("newton node values", &vec![0u8; cap * self.dim * 8])?;
            let op = self.op(
                "gather nodes",
                Entry::GatherNodes,
                OpsParams::default(),
                Varying {
                    index: Some(&index.buf),
                    node_vals: Some(&vals.buf),
                    ..Varying::default()
                },
            );
            self.nodes = Some(NodeList {
                capacity: cap,
                index,
                values: vals,
                gather: op,
            });
        }
        let Some(NodeList {
            index,
            values: vals,
            gather: op,
            ..
        }) = &self.nodes
        else {
            return Err(GpuError::Internal("node list buffers missing".into()));
        };
        self.ctx
            .write_buffer(&index.buf, 0, bytemuck::cast_slice(&idx));
        self.set_params(
            op,
            OpsParams {
                count: nodes.len() as u32,
                ..OpsParams::default()
            },
        );
        self.run(
            "newton read nodes",
            &[(op, Self::grid(nodes.len()))],
            |_| {},
        )?;
        let b = self.ctx.download(
            &vals.buf,
            0,
            (nodes.len() * self.dim * 8) as u64,
            "reading node positions",
        )?;
        Ok(from_bytes(true, &b))
    }

    /// Writes x of the listed nodes (node after node, d each), into the accepted iterate
    /// and the evaluation positions.
    pub fn write_nodes(&self, nodes: &[usize], values: &[f64]) -> Result<(), GpuError> {
        let d = self.dim;
        if values.len() != nodes.len() * d {
            return Err(GpuError::Mismatch(format!(
                "{} values for {} nodes of {d} coordinates",
                values.len(),
                nodes.len()
            )));
        }
        for (k, &i) in nodes.iter().enumerate() {
            if i >= self.n_nodes {
                return Err(GpuError::Mismatch(format!(
                    "node {i} written, the mesh has {}",
                    self.n_nodes
                )));
            }
            let b = to_bytes(true, &values[k * d..(k + 1) * d]);
            let off = (i * d * 8) as u64;
            self.ctx.write_buffer(&self.binder.x, off, &b);
            self.ctx.write_buffer(&self.binder.pos, off, &b);
        }
        Ok(())
    }
}
