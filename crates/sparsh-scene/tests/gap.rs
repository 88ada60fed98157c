//! Gap fields against closed-form geometry: analytic primitives, and a tessellated sphere cast
//! through the BVH within its tessellation bound.

use glam::{DVec3, Vec3};
use sparsh_scene::{GapField, Grid, Indenter, MeshIndenter, Pose, TriMesh};

const GRID: Grid = Grid {
    nx: 96,
    ny: 72,
    cell_mm: 0.15,
};

fn poses() -> [Pose; 3] {
    [
        Pose {
            position_mm: DVec3::new(0.0, 0.0, -1.0),
            rotation_deg: DVec3::ZERO,
        },
        Pose {
            position_mm: DVec3::new(1.3, -0.8, -1.6),
            rotation_deg: DVec3::ZERO,
        },
        Pose {
            position_mm: DVec3::new(-0.6, 0.9, -1.2),
            rotation_deg: DVec3::new(20.0, -35.0, 10.0),
        },
    ]
}

/// Sphere of radius R whose local centre is (0, 0, R): the world centre is pose(0, 0, R) and the
/// gap is c_z − √(R² − ρ²) where the vertical through the cell meets it.
#[test]
fn analytic_sphere_matches_closed_form_for_translated_and_rotated_poses() {
    let radius_mm = 4.0;
    let sphere = Indenter::Sphere { radius_mm };
    for pose in poses() {
        let centre = pose.apply(DVec3::new(0.0, 0.0, radius_mm));
        let gap = GapField::cast(&sphere, &pose, GRID);
        for j in 0..GRID.ny {
            for i in 0..GRID.nx {
                let rho2 = (GRID.x_mm(i) - centre.x).powi(2) + (GRID.y_mm(j) - centre.y).powi(2);
                let expected = if rho2 <= radius_mm * radius_mm {
                    centre.z - (radius_mm * radius_mm - rho2).sqrt()
                } else {
                    f64::INFINITY
                };
                let got = gap.gap_mm[j * GRID.nx + i];
                if expected.is_finite() {
                    assert!(
                        (got - expected).abs() < 1e-9,
                        "cell {i},{j}: {got} vs {expected}"
                    );
                } else {
                    assert!(
                        got.is_infinite(),
                        "cell {i},{j}: expected a miss, got {got}"
                    );
                }
            }
        }
    }
}

/// The UV sphere's vertices lie on the sphere, so the mesh sits inside it: the ray enters the
/// mesh at or after the sphere, later by at most ε/|n·d|, where ε = R(1 − cos ρ) is the largest
/// distance from a facet to the sphere (ρ the facets' angular circumradius) and n·d the cosine
/// between the ray and the sphere's normal.
#[test]
fn tessellated_sphere_gap_is_within_the_tessellation_bound() {
    let (radius_mm, rings, segments) = (4.0f64, 64u32, 128u32);
    let mesh = Indenter::Mesh(Box::new(MeshIndenter::new(TriMesh::uv_sphere(
        radius_mm as f32,
        rings,
        segments,
    ))));
    let sphere = Indenter::Sphere { radius_mm };
    let d_theta = std::f64::consts::PI / rings as f64;
    let d_phi = std::f64::consts::TAU / segments as f64;
    let rho = (d_theta / 2.0).hypot(d_phi / 2.0);
    let eps_mm = radius_mm * (1.0 - rho.cos());
    let mut checked = 0;
    for pose in poses() {
        let centre = pose.apply(DVec3::new(0.0, 0.0, radius_mm));
        let exact = GapField::cast(&sphere, &pose, GRID);
        let tess = GapField::cast(&mesh, &pose, GRID);
        for c in 0..GRID.len() {
            let g = exact.gap_mm[c];
            if !g.is_finite() {
                continue;
            }
            let hit = DVec3::new(GRID.x_mm(c % GRID.nx), GRID.y_mm(c / GRID.nx), g);
            let cos = ((hit - centre) / radius_mm).z.abs();
            if cos < 0.5 {
                continue;
            }
            let slack = eps_mm / cos + 2e-4;
            let t = tess.gap_mm[c];
            assert!(
                t >= g - 2e-4 && t <= g + slack,
                "cell {c}: mesh gap {t} vs sphere {g} (bound {slack})"
            );
            checked += 1;
        }
    }
    assert!(checked > 1000, "only {checked} cells under the sphere");
}

/// A flat punch presents a flat disc: gap = z inside the radius, nothing outside.
#[test]
fn flat_punch_gap_is_flat_inside_its_radius() {
    let punch = Indenter::Cylinder {
        radius_mm: 2.0,
        height_mm: 5.0,
    };
    let pose = Pose {
        position_mm: DVec3::new(0.5, 0.0, -0.3),
        rotation_deg: DVec3::ZERO,
    };
    let gap = GapField::cast(&punch, &pose, GRID);
    for c in 0..GRID.len() {
        let r = (GRID.x_mm(c % GRID.nx) - 0.5).hypot(GRID.y_mm(c / GRID.nx));
        let g = gap.gap_mm[c];
        if r < 1.99 {
            assert!((g + 0.3).abs() < 1e-12, "r = {r}: gap {g}");
        } else if r > 2.01 {
            assert!(g.is_infinite(), "r = {r}: gap {g}");
        }
    }
}

/// A cone of semi-angle α has gap z + r·cot α at distance r from its axis.
#[test]
fn cone_gap_grows_linearly_with_radius() {
    let alpha = 60.0f64;
    let cone = Indenter::Cone {
        half_angle_deg: alpha,
        height_mm: 3.0,
    };
    let pose = Pose {
        position_mm: DVec3::new(0.0, 0.0, -0.5),
        rotation_deg: DVec3::ZERO,
    };
    let gap = GapField::cast(&cone, &pose, GRID);
    let rim = 3.0 * alpha.to_radians().tan();
    for c in 0..GRID.len() {
        let r = GRID.x_mm(c % GRID.nx).hypot(GRID.y_mm(c / GRID.nx));
        if r < rim - 0.01 {
            let expected = -0.5 + r / alpha.to_radians().tan();
            assert!((gap.gap_mm[c] - expected).abs() < 1e-9, "r = {r}");
        }
    }
}

/// A box turned 90° about z swaps its x and y extents; its bottom face stays at the pose's z.
#[test]
fn rotated_box_swaps_its_footprint() {
    let block = Indenter::Box {
        size_mm: [4.0, 2.0, 1.0],
    };
    let pose = Pose {
        position_mm: DVec3::new(0.0, 0.0, -0.2),
        rotation_deg: DVec3::new(0.0, 0.0, 90.0),
    };
    let gap = GapField::cast(&block, &pose, GRID);
    for c in 0..GRID.len() {
        let (x, y) = (GRID.x_mm(c % GRID.nx), GRID.y_mm(c / GRID.nx));
        let inside = x.abs() < 0.99 && y.abs() < 1.99;
        let outside = x.abs() > 1.01 || y.abs() > 2.01;
        if inside {
            assert!((gap.gap_mm[c] + 0.2).abs() < 1e-9, "({x}, {y})");
        } else if outside {
            assert!(gap.gap_mm[c].is_infinite(), "({x}, {y})");
        }
    }
}

#[test]
fn uv_sphere_vertices_lie_on_the_sphere() {
    let mesh = TriMesh::uv_sphere(3.0, 16, 24);
    for v in &mesh.vertices {
        assert!(((*v - Vec3::new(0.0, 0.0, 3.0)).length() - 3.0).abs() < 1e-5);
    }
}

/// Every mesh shipped in `assets/meshes` loads and presents a surface to the gel.
#[test]
fn shipped_meshes_load_and_touch() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/meshes");
    let mut count = 0;
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let mesh = TriMesh::load(&path, sparsh_scene::LengthUnit::Mm, 1.0)
            .unwrap_or_else(|e| panic!("{e}"))
            .anchored_at_tip();
        let indenter = Indenter::Mesh(Box::new(MeshIndenter::new(mesh)));
        let pose = Pose {
            position_mm: DVec3::new(0.0, 0.0, -0.2),
            rotation_deg: DVec3::ZERO,
        };
        let gap = GapField::cast(&indenter, &pose, GRID);
        let deepest = gap.max_penetration_mm();
        // The tip reaches 0.2 mm; a sharp tip between cell centres shows up to a cell less
        // (the faces here are at most 45° steep).
        assert!(
            deepest <= 0.2 + 1e-5 && deepest > 0.2 - GRID.cell_mm,
            "{}: {deepest}",
            path.display()
        );
        count += 1;
    }
    assert!(count >= 5);
}
