//! The moving conditions' targets within one step, and the per-node geometry of a
//! condition's target set: the offset r of a node from it, the projector onto its
//! constrained directions, and the projection onto it.

use crate::sim::scene::BcShape;

/// The moving conditions within one step.
pub(super) struct MovingTargets {
    /// Per moving condition, its target set at t^{n+1}.
    pub(super) shapes: Vec<BcShape>,
    /// Per moving condition, whether its node has been snapped onto the target and
    /// eliminated (the key of the constraint set).
    pub(super) snapped: Vec<bool>,
}

/// r: the node's offset from its target set (slip: along the normal directions only).
pub fn offset(d: usize, s: &BcShape, xi: &[f64]) -> [f64; 3] {
    let mut p = [0.0; 3];
    p[..d].copy_from_slice(&xi[..d]);
    match s {
        BcShape::Sticky { anchor } => [p[0] - anchor[0], p[1] - anchor[1], p[2] - anchor[2]],
        BcShape::Plane { normal, offset } => {
            let dist = (0..3).map(|a| normal[a] * p[a]).sum::<f64>() - offset;
            [dist * normal[0], dist * normal[1], dist * normal[2]]
        }
        BcShape::Line { point, direction } => {
            let q = [p[0] - point[0], p[1] - point[1], p[2] - point[2]];
            let s: f64 = (0..3).map(|a| q[a] * direction[a]).sum();
            [
                q[0] - s * direction[0],
                q[1] - s * direction[1],
                q[2] - s * direction[2],
            ]
        }
    }
}

/// The projector P onto the constrained directions (row-major 3×3): I, nnᵀ or I − ttᵀ.
pub fn projector(d: usize, s: &BcShape) -> [f64; 9] {
    let mut p = [0.0; 9];
    match s {
        BcShape::Sticky { .. } => {
            for a in 0..d {
                p[a * 3 + a] = 1.0;
            }
        }
        BcShape::Plane { normal, .. } => {
            for a in 0..3 {
                for c in 0..3 {
                    p[a * 3 + c] = normal[a] * normal[c];
                }
            }
        }
        BcShape::Line { direction, .. } => {
            for a in 0..3 {
                for c in 0..3 {
                    p[a * 3 + c] = if a == c { 1.0 } else { 0.0 } - direction[a] * direction[c];
                }
            }
        }
    }
    p
}

/// Moves a node onto its constraint set (closest point).
pub(super) fn project(d: usize, s: &BcShape, xi: &mut [f64]) {
    let r = offset(d, s, xi);
    for a in 0..d {
        xi[a] -= r[a];
    }
}
