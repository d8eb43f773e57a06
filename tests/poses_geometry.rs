//! Scene geometry on synthetic scans with exact depth: robust bounds, the
//! global-to-local normalisation and the fused point cloud written as PLY.

use nalgebra::{IsometryMatrix3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use nerflabel::poses::{
    fuse_cloud, normalize, scene_bounds, write_ply, BoundsOptions, BoundsSource, CloudOptions, DAabb, Normalization,
    NormalizeOptions, Orientation, SceneBounds,
};
use nerflabel::rng::Rng;
use nerflabel::scan::{Bounds, DepthMap, Frame, Intrinsics, Layout, RgbImage, Scan};
use std::f64::consts::TAU;

/// A box-shaped room [-half, half] filmed from inside, rotated then scaled
/// into the world; depth is exact (ray cast to the walls) unless `flying`.
struct Room {
    half: Vector3<f64>,
    rotation: UnitQuaternion<f64>,
    scale: f64,
    frames: usize,
    flying: f64,
    with_depth: bool,
}

const W: u32 = 64;
const H: u32 = 48;

impl Default for Room {
    fn default() -> Self {
        Room {
            half: Vector3::new(2.0, 1.5, 1.25),
            rotation: UnitQuaternion::identity(),
            scale: 1.0,
            frames: 24,
            flying: 0.0,
            with_depth: true,
        }
    }
}

impl Room {
    fn to_world(&self, p: &Point3<f64>) -> Point3<f64> {
        self.rotation * p * self.scale
    }

    fn scan(&self) -> Scan {
        let k = Intrinsics {
            fx: 40.0,
            fy: 40.0,
            cx: 31.5,
            cy: 23.5,
        };
        let frames = (0..self.frames)
            .map(|i| {
                let yaw = TAU * i as f64 / self.frames as f64;
                let eye = Point3::new(0.7 * yaw.cos(), 0.5 * yaw.sin(), 0.1 * yaw.sin());
                let fwd = Vector3::new((yaw + 0.3).cos(), (yaw + 0.3).sin(), 0.4 * (3.0 * yaw).sin()).normalize();
                let right = fwd.cross(&Vector3::z()).normalize();
                let rot = Matrix3::from_columns(&[right, fwd.cross(&right), fwd]);
                let mut rng = Rng::new(7, i as u64);
                let mut metres = Vec::with_capacity((W * H) as usize);
                let mut rgb = RgbImage::new(W, H);
                for v in 0..H {
                    for u in 0..W {
                        let d = rot * k.unproject(u as f64, v as f64);
                        let t = (0..3)
                            .filter(|&a| d[a] != 0.0)
                            .map(|a| (self.half[a].copysign(d[a]) - eye[a]) / d[a])
                            .fold(f64::INFINITY, f64::min);
                        let mut z = (t * self.scale) as f32;
                        if rng.f64() < self.flying {
                            z *= 1000.0;
                        }
                        metres.push(z);
                        rgb.put_pixel(u, v, image::Rgb([u as u8 * 4, v as u8 * 5, i as u8]));
                    }
                }
                let world_rot = self.rotation.to_rotation_matrix() * Rotation3::from_matrix_unchecked(rot);
                Frame {
                    id: i as u64,
                    name: format!("{i:06}"),
                    rgb,
                    depth: self.with_depth.then_some(DepthMap {
                        width: W,
                        height: H,
                        metres,
                    }),
                    camera_to_world: IsometryMatrix3::from_parts(
                        Translation3::from(self.to_world(&eye).coords),
                        world_rot,
                    ),
                    intrinsics: k,
                    depth_size: None,
                }
            })
            .collect();
        Scan {
            root: "synthetic-room".into(),
            layout: Layout::Native,
            frames,
            bounds: None,
            warnings: Vec::new(),
            inputs: Vec::new(),
        }
    }
}

fn bounds_of(scan: &Scan) -> SceneBounds {
    scene_bounds(scan, &BoundsOptions::default()).unwrap()
}

fn normalization_of(scan: &Scan) -> (SceneBounds, Normalization) {
    let b = bounds_of(scan);
    let n = normalize(&b, &NormalizeOptions::default()).unwrap();
    (b, n)
}

fn max_abs_diff(a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    (a - b).amax()
}

fn rotation(axis: Vector3<f64>, angle: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_scaled_axis(axis * angle)
}

#[test]
fn bounds_ignore_one_percent_flying_pixels_at_1000x_range() {
    let clean = bounds_of(&Room::default().scan());
    let noisy = bounds_of(
        &Room {
            flying: 0.01,
            ..Room::default()
        }
        .scan(),
    );
    assert_eq!(noisy.source, BoundsSource::Depth);
    let extent = clean.aabb.max_extent();
    assert!(
        max_abs_diff(&clean.aabb.min, &noisy.aabb.min) < 0.02 * extent,
        "{:?} vs {:?}",
        noisy.aabb,
        clean.aabb
    );
    assert!(
        max_abs_diff(&clean.aabb.max, &noisy.aabb.max) < 0.02 * extent,
        "{:?} vs {:?}",
        noisy.aabb,
        clean.aabb
    );
    // The flying pixels are counted as rejected.
    let flying = noisy.stats.sampled as f64 * 0.01;
    assert!(
        noisy.stats.rejected as f64 > 0.8 * flying,
        "{} rejected of ~{flying}",
        noisy.stats.rejected
    );
}

#[test]
fn bounds_ignore_flying_pixels_all_on_one_side() {
    // Cameras that all look the same way put every flying pixel beyond one
    // face: more than the 0.5 % percentile trims, so the gap rule must act.
    let mut scan = Room {
        flying: 0.02,
        ..Room::default()
    }
    .scan();
    scan.frames.retain(|f| f.camera_to_world.rotation[(0, 2)] > 0.5);
    let mut clean = Room::default().scan();
    clean.frames.retain(|f| f.camera_to_world.rotation[(0, 2)] > 0.5);
    let (noisy, clean) = (bounds_of(&scan), bounds_of(&clean));
    let extent = clean.aabb.max_extent();
    assert!(
        max_abs_diff(&clean.aabb.max, &noisy.aabb.max) < 0.02 * extent,
        "{:?} vs {:?}",
        noisy.aabb,
        clean.aabb
    );
}

#[test]
fn bounds_enclose_all_cameras_even_a_far_one() {
    let mut scan = Room::default().scan();
    scan.frames[5].camera_to_world.translation = Translation3::new(30.0, -4.0, 2.0);
    let b = bounds_of(&scan);
    for f in &scan.frames {
        assert!(
            b.aabb.contains(&f.camera_center()),
            "{} outside {:?}",
            f.camera_center(),
            b.aabb
        );
    }
}

#[test]
fn bbox_txt_overrides_the_depth() {
    let mut scan = Room::default().scan();
    // Reaches the wall at x = 2 (bounds holding no surface are refused).
    let user = Bounds {
        min: Point3::new(-0.5, -0.25, -0.1),
        max: Point3::new(2.5, 0.75, 0.3),
    };
    scan.bounds = Some(user);
    let (b, n) = normalization_of(&scan);
    assert_eq!(b.source, BoundsSource::User);
    assert_eq!((b.aabb.min, b.aabb.max), (user.min, user.max));
    assert!(!n.rotated);
    // The user box becomes the local box, its longest edge spanning 0.9.
    assert!(
        max_abs_diff(
            &n.transform.world_to_local_point(&user.min),
            &Point3::new(0.05, 0.35, 0.44)
        ) < 1e-12
    );
    assert!(
        max_abs_diff(
            &n.transform.world_to_local_point(&user.max),
            &Point3::new(0.95, 0.65, 0.56)
        ) < 1e-12
    );
}

#[test]
fn bbox_txt_holding_no_surface_is_refused() {
    // Regression: bounds away from the scene trained nothing and exited 0.
    let mut scan = Room::default().scan();
    scan.bounds = Some(Bounds {
        min: Point3::new(-0.5, -0.25, -0.1),
        max: Point3::new(0.5, 0.75, 0.3),
    });
    let err = scene_bounds(&scan, &BoundsOptions::default()).unwrap_err().to_string();
    assert!(err.contains("bbox.txt") && err.contains("hold 0 of"), "{err}");
}

#[test]
fn no_depth_fallback_is_finite_and_contains_the_cameras() {
    let room = Room {
        with_depth: false,
        ..Room::default()
    };
    let scan = room.scan();
    let b = bounds_of(&scan);
    assert_eq!(b.source, BoundsSource::CameraFrusta);
    assert!(b.aabb.is_valid());
    for f in &scan.frames {
        assert!(b.aabb.contains(&f.camera_center()));
        // Each optical axis is kept for the documented range, 2 x the
        // camera box diagonal (0.7 m radius trajectory: diagonal > 1.4 m).
        assert!(b
            .aabb
            .contains(&(f.camera_center() + f.camera_to_world.rotation.matrix().column(2) * 2.8)));
    }
    assert!(b.aabb.max_extent() < 20.0, "{:?}", b.aabb);
    let n = normalize(&b, &NormalizeOptions::default()).unwrap();
    assert!(DAabb::UNIT.contains_box(&n.local_aabb));
}

#[test]
fn normalisation_maps_the_bounds_into_the_unit_cube() {
    let (b, n) = normalization_of(&Room::default().scan());
    assert!(!n.rotated);
    for c in b.aabb.corners() {
        let l = n.transform.world_to_local_point(&c);
        assert!(
            n.local_aabb.padded(1e-12).contains(&l) && DAabb::UNIT.contains(&l),
            "{c} -> {l}"
        );
    }
    assert!((n.local_aabb.max_extent() - 0.9).abs() < 1e-12);
    assert!(max_abs_diff(&n.local_aabb.center(), &Point3::new(0.5, 0.5, 0.5)) < 1e-12);

    let room = Room {
        rotation: rotation(Vector3::z(), 0.6) * rotation(Vector3::y(), -0.25),
        ..Room::default()
    };
    let (b, n) = normalization_of(&room.scan());
    assert!(n.rotated, "a tilted room is aligned with its walls");
    assert!(DAabb::UNIT.contains_box(&n.local_aabb));
    let inside = b
        .samples
        .iter()
        .filter(|p| n.local_aabb.contains(&n.transform.world_to_local_point(p)))
        .count();
    assert!(
        inside as f64 > 0.99 * b.samples.len() as f64,
        "{inside} of {}",
        b.samples.len()
    );
    for c in &b.cameras {
        assert!(n.local_aabb.contains(&n.transform.world_to_local_point(c)));
    }
    // Aligned: the local box is the padded room (4 x 3 x 2.5 m, +0.4 m).
    let metres = n.local_aabb.extent() / n.transform.scale();
    assert!((metres - Vector3::new(4.4, 3.4, 2.9)).amax() < 0.03, "{metres}");
}

#[test]
fn normalisation_round_trips_and_preserves_angles_and_ratios() {
    let room = Room {
        rotation: rotation(Vector3::z(), 0.6),
        scale: 3.0,
        ..Room::default()
    };
    let (_, n) = normalization_of(&room.scan());
    let t = n.transform;
    let mut rng = Rng::new(11, 0);
    for _ in 0..1000 {
        let mut point = || Point3::from(Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 10.0);
        let (p, q, r) = (point(), point(), point());
        assert!((t.local_to_world_point(&t.world_to_local_point(&p)) - p).norm() < 1e-9);
        assert!((t.inverse().world_to_local_point(&t.world_to_local_point(&p)) - p).norm() < 1e-9);
        let (lp, lq, lr) = (
            t.world_to_local_point(&p),
            t.world_to_local_point(&q),
            t.world_to_local_point(&r),
        );
        let ratio = (q - p).norm() / (r - p).norm();
        assert!(((lq - lp).norm() / (lr - lp).norm() - ratio).abs() < 1e-9 * ratio.max(1.0));
        let angle = (q - p).angle(&(r - p));
        assert!(((lq - lp).angle(&(lr - lp)) - angle).abs() < 1e-9);
        assert!(((lq - lp).norm() - t.world_to_local_distance((q - p).norm())).abs() < 1e-9);
        let d = (q - p).normalize();
        assert!((t.local_to_world_direction(&t.world_to_local_direction(&d)) - d).norm() < 1e-12);
        assert!(((lq - lp).normalize() - t.world_to_local_direction(&d)).norm() < 1e-9);
    }
}

#[test]
fn camera_poses_stay_orthonormal_in_local_space_and_round_trip() {
    let room = Room {
        rotation: rotation(Vector3::x(), 0.3),
        scale: 0.01,
        ..Room::default()
    };
    let scan = room.scan();
    let (_, n) = normalization_of(&scan);
    let t = n.transform;
    for f in &scan.frames {
        let local = t.world_to_local_pose(&f.camera_to_world);
        let r = local.rotation.matrix();
        let err = (r.transpose() * r - Matrix3::identity()).amax();
        assert!(err < 1e-12 && (r.determinant() - 1.0).abs() < 1e-12, "frame {}", f.name);
        // The optical axis and centre follow the points.
        let ahead = f.camera_to_world * Point3::new(0.0, 0.0, 0.02);
        let ahead_local = local * Point3::new(0.0, 0.0, t.world_to_local_distance(0.02));
        assert!((t.world_to_local_point(&ahead) - ahead_local).norm() < 1e-9);
        let back = t.local_to_world_pose(&local);
        let diff = (back.to_homogeneous() - f.camera_to_world.to_homogeneous()).amax();
        assert!(diff < 1e-9, "frame {}", f.name);
    }
}

#[test]
fn scaled_scenes_get_the_same_local_coordinates() {
    for rotation in [
        UnitQuaternion::identity(),
        rotation(Vector3::z(), 0.6) * rotation(Vector3::y(), -0.25),
    ] {
        let (_, base) = normalization_of(
            &Room {
                rotation,
                ..Room::default()
            }
            .scan(),
        );
        for scale in [0.01, 100.0] {
            let room = Room {
                rotation,
                scale,
                ..Room::default()
            };
            let (_, n) = normalization_of(&room.scan());
            assert_eq!(n.rotated, base.rotated);
            assert!(
                max_abs_diff(&n.local_aabb.min, &base.local_aabb.min) < 1e-5,
                "{scale}: {:?}",
                n.local_aabb
            );
            assert!(
                max_abs_diff(&n.local_aabb.max, &base.local_aabb.max) < 1e-5,
                "{scale}: {:?}",
                n.local_aabb
            );
            for p in [
                Point3::origin(),
                Point3::new(1.0, -0.5, 0.25),
                Point3::new(-2.0, 1.5, 1.25),
            ] {
                let a = base.transform.world_to_local_point(&(rotation * p));
                let b = n.transform.world_to_local_point(&room.to_world(&p));
                assert!(max_abs_diff(&a, &b) < 1e-5, "scale {scale}: {p} -> {a} vs {b}");
            }
            assert!((n.transform.scale() * scale / base.transform.scale() - 1.0).abs() < 1e-5);
        }
    }
}

#[test]
fn identity_orientation_keeps_world_axes() {
    let room = Room {
        rotation: rotation(Vector3::z(), 0.6),
        ..Room::default()
    };
    let b = bounds_of(&room.scan());
    let n = normalize(
        &b,
        &NormalizeOptions {
            orientation: Orientation::Identity,
            ..NormalizeOptions::default()
        },
    )
    .unwrap();
    assert!(!n.rotated);
    assert_eq!(n.transform.rotation(), UnitQuaternion::identity());
    assert!(DAabb::UNIT.contains_box(&n.local_aabb));
}

/// Header lines and little-endian body of a binary PLY file.
fn parse_ply(bytes: &[u8]) -> (Vec<String>, &[u8]) {
    let marker = b"end_header\n";
    let end = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .expect("PLY has no end_header")
        + marker.len();
    let header = std::str::from_utf8(&bytes[..end])
        .unwrap()
        .lines()
        .map(str::to_owned)
        .collect();
    (header, &bytes[end..])
}

#[test]
fn ply_file_has_the_expected_header_and_points() {
    let scan = Room::default().scan();
    let cloud = fuse_cloud(
        &scan,
        &CloudOptions {
            voxels_per_extent: 64,
            ..CloudOptions::default()
        },
    )
    .unwrap();
    assert!(cloud.len() > 1000, "{}", cloud.len());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sub/cloud.ply");
    write_ply(&path, &cloud).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let (header, body) = parse_ply(&bytes);
    let expected_props = [
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
    ];
    assert_eq!(header[0], "ply");
    assert_eq!(header[1], "format binary_little_endian 1.0");
    assert!(header.contains(&format!("element vertex {}", cloud.len())));
    let props: Vec<&str> = header
        .iter()
        .filter(|l| l.starts_with("property"))
        .map(String::as_str)
        .collect();
    assert_eq!(props, expected_props);
    assert_eq!(body.len(), cloud.len() * 15);
    for (i, rec) in body.chunks_exact(15).enumerate() {
        let f = |k: usize| f32::from_le_bytes(rec[4 * k..4 * k + 4].try_into().unwrap());
        assert_eq!([f(0), f(1), f(2)], cloud.positions[i]);
        assert_eq!(&rec[12..15], &cloud.colors[i]);
        let p = Point3::new(f(0) as f64, f(1) as f64, f(2) as f64);
        assert!(cloud.bounds.contains(&p));
    }
    // Nothing but the file was left behind by the atomic write.
    assert_eq!(std::fs::read_dir(path.parent().unwrap()).unwrap().count(), 1);
}

#[test]
fn cloud_of_a_scaled_scene_scales_with_it() {
    let a = fuse_cloud(&Room::default().scan(), &CloudOptions::default()).unwrap();
    let b = fuse_cloud(
        &Room {
            scale: 100.0,
            ..Room::default()
        }
        .scan(),
        &CloudOptions::default(),
    )
    .unwrap();
    assert!((b.voxel_size / a.voxel_size - 100.0).abs() < 1e-3);
    let ratio = b.len() as f64 / a.len() as f64;
    assert!((ratio - 1.0).abs() < 0.01, "{} vs {} points", b.len(), a.len());
}
