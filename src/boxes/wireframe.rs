//! Boxes drawn as points along their twelve edges, so a user can check
//! where they sit in any point-cloud viewer (every PLY reader shows
//! vertices; few show edges).

use super::parse::BoxSet;
use nalgebra::Vector3;

/// Edge colours, one per box in turn: saturated, unlike most scene colours.
const PALETTE: [[u8; 3]; 6] = [
    [255, 0, 255],
    [0, 255, 255],
    [255, 255, 0],
    [255, 64, 0],
    [0, 255, 64],
    [64, 128, 255],
];

/// Points every `spacing` metres (at least two per edge) along the edges of
/// every box, with each box's colour.
pub fn wireframe_points(set: &BoxSet, spacing: f64) -> Vec<([f32; 3], [u8; 3])> {
    let mut points = Vec::new();
    for (i, b) in set.boxes.iter().enumerate() {
        let colour = PALETTE[i % PALETTE.len()];
        let corner =
            |sx: f64, sy: f64, sz: f64| b.center + b.rotation * (0.5 * b.size).component_mul(&Vector3::new(sx, sy, sz));
        for (from, to) in edges() {
            let (a, c) = (corner(from[0], from[1], from[2]), corner(to[0], to[1], to[2]));
            let steps = ((c - a).norm() / spacing.max(1e-9)).ceil().clamp(1.0, 1e5) as usize;
            for s in 0..=steps {
                let p = a.lerp(&c, s as f64 / steps as f64);
                points.push((p.coords.map(|x| x as f32).into(), colour));
            }
        }
    }
    points
}

/// The twelve edges of the cube [-1, 1]^3 as pairs of corners.
fn edges() -> Vec<([f64; 3], [f64; 3])> {
    let mut edges = Vec::with_capacity(12);
    for axis in 0..3 {
        for a in [-1.0, 1.0] {
            for b in [-1.0, 1.0] {
                let mut from = [0.0; 3];
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                (from[u], from[v], from[axis]) = (a, b, -1.0);
                let mut to = from;
                to[axis] = 1.0;
                edges.push((from, to));
            }
        }
    }
    edges
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::boxes::Box3;
    use nalgebra::{Point3, Rotation3};

    #[test]
    fn edge_points_lie_on_the_box_surface_edges_and_cover_every_edge() {
        let b = Box3 {
            label: "crate".into(),
            instance_id: 1,
            center: Point3::new(1.0, -2.0, 0.5),
            size: Vector3::new(0.4, 0.2, 0.1),
            rotation: Rotation3::from_axis_angle(&Vector3::z_axis(), 0.3),
        };
        let set = BoxSet::from_boxes(vec![b.clone()]);
        let points = wireframe_points(&set, 0.01);
        // 4 edges of each length, about one point per centimetre.
        let expected = 4.0 * (0.4 + 0.2 + 0.1) / 0.01;
        assert!((points.len() as f64 - expected).abs() < 30.0, "{}", points.len());
        let mut corners_hit = 0;
        for (p, colour) in &points {
            assert_eq!(*colour, PALETTE[0]);
            let local = b.rotation.transpose() * (Point3::from(p.map(f64::from)) - b.center);
            let on_face: [bool; 3] = (local.abs() - 0.5 * b.size).abs().map(|d| d < 1e-5).into();
            // On an edge: on two faces at once (three at a corner).
            assert!(on_face.iter().filter(|&&f| f).count() >= 2, "{local:?}");
            corners_hit += (on_face.iter().all(|&f| f)) as usize;
        }
        // Each corner ends three edges.
        assert_eq!(corners_hit, 24);
    }
}
