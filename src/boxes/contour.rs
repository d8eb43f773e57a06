//! One outline polygon per instance of a mask, for YOLO segmentation
//! labels: the outer boundary of each 4-connected part, traced along pixel
//! edges (vertices on pixel corners), simplified, and the parts of an
//! instance split by an occluder joined into one polygon by zero-width
//! bridges between their closest vertices, the way ultralytics joins the
//! several polygons of a COCO object (`merge_multi_segment`). Holes are
//! not cut out: a YOLO polygon has none.

use crate::mask::Components;

/// A point in pixel units: (0, 0) is the top-left corner of the image,
/// (w, h) the bottom-right one.
pub type Point = [f64; 2];

/// How far (pixels) a simplified outline may stray from the traced one.
pub const SIMPLIFY_PX: f64 = 0.5;

/// The outline of instance `id` in a row-major `w` x `h` mask, given the
/// mask's 4-connected components ([`crate::mask::components`], computed once per mask):
/// its parts, largest first, joined into one closed polygon (the first
/// vertex is not repeated at the end). Empty when no pixel holds `id`.
pub(crate) fn instance_polygon(parts: &Components, w: usize, h: usize, id: u16) -> Vec<Point> {
    join_parts(outlines(parts, w, h, id))
}

/// Outer outlines of the 4-connected parts of instance `id`, each with the
/// pixel count of its part, largest part first, simplified by [`SIMPLIFY_PX`].
pub(crate) fn outlines(components: &Components, w: usize, h: usize, id: u16) -> Vec<(usize, Vec<Point>)> {
    if components.label.len() != w * h {
        return Vec::new();
    }
    let mut parts: Vec<(usize, Vec<Point>)> = Vec::new();
    let mut traced = vec![false; components.size.len()];
    for (i, &part) in components.label.iter().enumerate() {
        let part_index = part as usize;
        if components.value[part_index] != id || traced[part_index] {
            continue;
        }
        traced[part_index] = true;
        let outline = trace(&components.label, w, h, part, i % w, i / w);
        parts.push((components.size[part_index], simplify(&outline, SIMPLIFY_PX)));
    }
    // Stable: equal areas keep raster order.
    parts.sort_by_key(|p| std::cmp::Reverse(p.0));
    parts
}

/// Walk the outer boundary of part `label`, whose first pixel in raster
/// order is (`x0`, `y0`), along pixel edges with the part on the right
/// (clockwise on screen, y down); returns the corner vertices.
fn trace(labels: &[u32], w: usize, h: usize, label: u32, x0: usize, y0: usize) -> Vec<Point> {
    // Headings east, south, west, north; turning right is +1.
    const STEP: [(i64, i64); 4] = [(1, 0), (0, 1), (-1, 0), (0, -1)];
    let inside = |x: i64, y: i64| -> bool {
        x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h && labels[y as usize * w + x as usize] == label
    };
    // The pixels ahead of vertex (x, y) on the right and on the left of heading d.
    let ahead = |x: i64, y: i64, d: usize| -> (bool, bool) {
        match d {
            0 => (inside(x, y), inside(x, y - 1)),
            1 => (inside(x - 1, y), inside(x, y)),
            2 => (inside(x - 1, y - 1), inside(x - 1, y)),
            _ => (inside(x, y - 1), inside(x - 1, y - 1)),
        }
    };
    let start = (x0 as i64, y0 as i64);
    let (mut x, mut y) = start;
    // Arriving at the start vertex up the part's left side.
    let mut d = 3usize;
    let mut corners = Vec::new();
    // Every edge is walked at most once.
    let limit = 4 * (w + 1) * (h + 1);
    for _ in 0..limit {
        let (right, left) = ahead(x, y, d);
        let turned = if !right {
            (d + 1) % 4
        } else if left {
            (d + 3) % 4
        } else {
            d
        };
        if turned != d {
            corners.push([x as f64, y as f64]);
            d = turned;
        }
        x += STEP[d].0;
        y += STEP[d].1;
        if (x, y) == start {
            break;
        }
    }
    corners
}

/// Douglas-Peucker on a closed polygon: drop vertices closer than `eps` to
/// the simplified outline. Keeps at least three vertices.
pub fn simplify(polygon: &[Point], eps: f64) -> Vec<Point> {
    let n = polygon.len();
    if n <= 3 {
        return polygon.to_vec();
    }
    // Split the ring at vertex 0 and the vertex farthest from it.
    let far = (1..n)
        .max_by(|&a, &b| dist2(polygon[0], polygon[a]).total_cmp(&dist2(polygon[0], polygon[b])))
        .unwrap_or(n / 2);
    let mut keep = vec![false; n];
    keep[0] = true;
    keep[far] = true;
    let ring: Vec<Point> = polygon.iter().chain(std::iter::once(&polygon[0])).copied().collect();
    let mut stack = vec![(0usize, far), (far, n)];
    while let Some((a, b)) = stack.pop() {
        if b <= a + 1 {
            continue;
        }
        let (mut worst, mut at) = (0.0f64, a);
        for i in a + 1..b {
            let d = segment_distance(ring[i], ring[a], ring[b]);
            if d > worst {
                (worst, at) = (d, i);
            }
        }
        if worst > eps {
            keep[at] = true;
            stack.push((a, at));
            stack.push((at, b));
        }
    }
    let kept: Vec<Point> = (0..n).filter(|&i| keep[i]).map(|i| polygon[i]).collect();
    if kept.len() >= 3 {
        kept
    } else {
        polygon.to_vec()
    }
}

fn dist2(a: Point, b: Point) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

/// Distance of `p` from the segment `a`-`b`.
fn segment_distance(p: Point, a: Point, b: Point) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len2 = dx * dx + dy * dy;
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    dist2(p, [a[0] + t * dx, a[1] + t * dy]).sqrt()
}

/// One closed polygon from several outlines (largest first): each further
/// part is bridged to the closest part already joined, at their closest
/// pair of vertices; the walk goes around every part once and crosses each
/// bridge there and back, so the bridges enclose no area.
pub fn join_parts(parts: Vec<(usize, Vec<Point>)>) -> Vec<Point> {
    let parts: Vec<Vec<Point>> = parts.into_iter().map(|(_, p)| p).filter(|p| !p.is_empty()).collect();
    if parts.len() <= 1 {
        return parts.into_iter().next().unwrap_or_default();
    }
    // children[p] = (vertex of p, child part, child's entry vertex).
    let mut children: Vec<Vec<(usize, usize, usize)>> = vec![Vec::new(); parts.len()];
    let mut joined = vec![false; parts.len()];
    joined[0] = true;
    for _ in 1..parts.len() {
        let mut best: Option<(f64, usize, usize, usize, usize)> = None;
        for (p, part) in parts.iter().enumerate().filter(|(p, _)| joined[*p]) {
            for (c, other) in parts.iter().enumerate().filter(|(c, _)| !joined[*c]) {
                for (i, &a) in part.iter().enumerate() {
                    for (j, &b) in other.iter().enumerate() {
                        let d = dist2(a, b);
                        if best.is_none_or(|(bd, ..)| d < bd) {
                            best = Some((d, p, i, c, j));
                        }
                    }
                }
            }
        }
        let Some((_, p, i, c, j)) = best else { break };
        children[p].push((i, c, j));
        joined[c] = true;
    }
    let mut out = Vec::new();
    walk(&parts, &children, 0, 0, &mut out);
    // The walk ends where it began; a polygon is closed implicitly.
    out.pop();
    out.dedup();
    if out.len() > 1 && out.first() == out.last() {
        out.pop();
    }
    out
}

/// Go around part `p` from vertex `entry` back to it, detouring into each
/// child at its bridge vertex.
fn walk(parts: &[Vec<Point>], children: &[Vec<(usize, usize, usize)>], p: usize, entry: usize, out: &mut Vec<Point>) {
    let part = &parts[p];
    let n = part.len();
    for k in 0..n {
        let i = (entry + k) % n;
        out.push(part[i]);
        for &(at, child, child_entry) in children[p].iter().filter(|(at, ..)| *at == i) {
            walk(parts, children, child, child_entry, out);
            out.push(part[at]);
        }
    }
    out.push(part[entry]);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mask::components;

    /// Pixels whose centre lies inside `polygon` (even-odd rule, as polygon
    /// fills rasterise a YOLO outline back into a mask).
    pub fn rasterise(polygon: &[Point], w: usize, h: usize) -> Vec<bool> {
        let mut out = vec![false; w * h];
        for y in 0..h {
            let py = y as f64 + 0.5;
            for x in 0..w {
                let px = x as f64 + 0.5;
                let mut inside = false;
                for k in 0..polygon.len() {
                    let (a, b) = (polygon[k], polygon[(k + 1) % polygon.len()]);
                    if (a[1] > py) != (b[1] > py) {
                        let cross = a[0] + (py - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
                        if px < cross {
                            inside = !inside;
                        }
                    }
                }
                out[y * w + x] = inside;
            }
        }
        out
    }

    fn mask_from(rows: &[&str]) -> (Vec<u16>, usize, usize) {
        let (w, h) = (rows[0].len(), rows.len());
        let mask = rows
            .iter()
            .flat_map(|r| r.bytes().map(|c| if c == b'.' { 0 } else { (c - b'0') as u16 }))
            .collect();
        (mask, w, h)
    }

    fn iou(a: &[bool], b: &[bool]) -> f64 {
        let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
        let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
        inter as f64 / union.max(1) as f64
    }

    #[test]
    fn single_pixel_and_rectangle_outlines_are_their_corners() {
        let (mask, w, h) = mask_from(&["...", ".1.", "..."]);
        assert_eq!(
            instance_polygon(&components(&mask, w, h), w, h, 1),
            vec![[1.0, 1.0], [2.0, 1.0], [2.0, 2.0], [1.0, 2.0]]
        );
        let (mask, w, h) = mask_from(&["....", ".11.", ".11.", ".11."]);
        assert_eq!(
            instance_polygon(&components(&mask, w, h), w, h, 1),
            vec![[1.0, 1.0], [3.0, 1.0], [3.0, 4.0], [1.0, 4.0]]
        );
        assert!(instance_polygon(&components(&mask, w, h), w, h, 2).is_empty());
    }

    #[test]
    fn traced_outline_rasterises_back_to_the_part_with_its_holes_filled() {
        // An L, a notch and a one-pixel hole; unsimplified the outline is exact.
        let (mask, w, h) = mask_from(&[
            "........", ".1111...", ".1..1...", ".1111.1.", ".111111.", "..11111.", "........",
        ]);
        let parts = components(&mask, w, h);
        let outline = trace(&parts.label, w, h, parts.label[w + 1], 1, 1);
        let filled = rasterise(&outline, w, h);
        let mut want: Vec<bool> = mask.iter().map(|&m| m == 1).collect();
        want[2 * w + 2] = true;
        want[2 * w + 3] = true;
        assert_eq!(filled, want);
        // Clockwise on screen (y down): positive shoelace area in these axes.
        let area: f64 = (0..outline.len())
            .map(|k| {
                let (a, b) = (outline[k], outline[(k + 1) % outline.len()]);
                a[0] * b[1] - b[0] * a[1]
            })
            .sum::<f64>()
            / 2.0;
        assert_eq!(area, 24.0, "22 pixels and the 2-pixel hole");
    }

    #[test]
    fn diagonal_neighbours_are_separate_parts_and_the_pinch_is_kept() {
        let (mask, w, h) = mask_from(&["11..", "11..", "..11", "..11"]);
        let parts = outlines(&components(&mask, w, h), w, h, 1);
        assert_eq!(parts.len(), 2);
        let joined = instance_polygon(&components(&mask, w, h), w, h, 1);
        assert_eq!(
            rasterise(&joined, w, h),
            mask.iter().map(|&m| m == 1).collect::<Vec<_>>()
        );
    }

    #[test]
    fn parts_split_by_an_occluder_join_into_one_polygon_covering_both() {
        // Instance 1 cut in three by instance 2 (a pole in front of it).
        let (mask, w, h) = mask_from(&["..........", ".112111211", ".112111211", ".112111211", "...2...2.."]);
        let parts = outlines(&components(&mask, w, h), w, h, 1);
        assert_eq!(parts.iter().map(|p| p.0).collect::<Vec<_>>(), vec![9, 6, 6]);
        let joined = instance_polygon(&components(&mask, w, h), w, h, 1);
        assert!(joined.len() >= 12, "{joined:?}");
        let want: Vec<bool> = mask.iter().map(|&m| m == 1).collect();
        assert_eq!(rasterise(&joined, w, h), want, "bridges add no area: {joined:?}");
        for p in &joined {
            assert!(p[0] >= 0.0 && p[0] <= w as f64 && p[1] >= 0.0 && p[1] <= h as f64);
        }
    }

    #[test]
    fn simplified_disc_stays_within_half_a_pixel_and_keeps_its_pixels() {
        let (w, h) = (64usize, 48usize);
        let mask: Vec<u16> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
                u16::from((x - 30.0).powi(2) + (y - 22.0).powi(2) < 18.0f64.powi(2))
            })
            .collect();
        let parts = components(&mask, w, h);
        let first = mask.iter().position(|&m| m == 1).unwrap();
        let traced = trace(&parts.label, w, h, parts.label[first], first % w, first / w);
        let polygon = instance_polygon(&components(&mask, w, h), w, h, 1);
        assert!(
            polygon.len() < traced.len(),
            "{} of {} vertices",
            polygon.len(),
            traced.len()
        );
        let want: Vec<bool> = mask.iter().map(|&m| m == 1).collect();
        let score = iou(&rasterise(&polygon, w, h), &want);
        eprintln!("{} of {} vertices, IoU {score:.4}", polygon.len(), traced.len());
        assert!(score > 0.995, "IoU {score}: every pixel centre stays on its side");
        for v in &traced {
            let d = (0..polygon.len())
                .map(|k| segment_distance(*v, polygon[k], polygon[(k + 1) % polygon.len()]))
                .fold(f64::INFINITY, f64::min);
            assert!(d <= SIMPLIFY_PX + 1e-12, "{v:?} is {d} px away");
        }
    }
}
