//! Writes the indenter meshes shipped in `assets/meshes/` (millimetres, tip down):
//!
//! ```sh
//! cargo run --release -p sparsh-scene --example make_meshes -- assets/meshes
//! ```

use std::f32::consts::{PI, TAU};
use std::path::PathBuf;

use glam::Vec3;
use sparsh_scene::TriMesh;

/// A closed surface from a (rows × cols) grid of points, wrapping around in `cols`; the first
/// and last rows are closed with a fan to their centroid.
fn closed_grid(rows: &[Vec<Vec3>]) -> TriMesh {
    let cols = rows[0].len() as u32;
    let mut vertices: Vec<Vec3> = rows.iter().flatten().copied().collect();
    let at = |r: u32, c: u32| r * cols + c % cols;
    let mut triangles = Vec::new();
    for r in 0..rows.len() as u32 - 1 {
        for c in 0..cols {
            triangles.push([at(r, c), at(r + 1, c), at(r + 1, c + 1)]);
            triangles.push([at(r, c), at(r + 1, c + 1), at(r, c + 1)]);
        }
    }
    for (row, flip) in [(0u32, true), (rows.len() as u32 - 1, false)] {
        let ring = &rows[row as usize];
        let centre = ring.iter().copied().sum::<Vec3>() / ring.len() as f32;
        vertices.push(centre);
        let hub = vertices.len() as u32 - 1;
        for c in 0..cols {
            let (a, b) = (at(row, c), at(row, c + 1));
            triangles.push(if flip { [hub, b, a] } else { [hub, a, b] });
        }
    }
    TriMesh {
        vertices,
        triangles,
    }
}

/// A solid of revolution about z from a profile of (radius, z) points, bottom to top.
fn revolve(profile: &[(f32, f32)], segments: u32) -> TriMesh {
    let rows: Vec<Vec<Vec3>> = profile
        .iter()
        .map(|&(r, z)| {
            (0..segments)
                .map(|s| {
                    let phi = TAU * s as f32 / segments as f32;
                    Vec3::new(r * phi.cos(), r * phi.sin(), z)
                })
                .collect()
        })
        .collect();
    closed_grid(&rows)
}

/// A prism: the polygon `outline` (x, y, counter-clockwise) extruded from z = 0 to `height`.
fn prism(outline: &[(f32, f32)], height: f32) -> TriMesh {
    let ring = |z: f32| -> Vec<Vec3> { outline.iter().map(|&(x, y)| Vec3::new(x, y, z)).collect() };
    closed_grid(&[ring(0.0), ring(height)])
}

/// Torus of ring radius `major`, tube radius `minor`, lying flat.
fn torus(major: f32, minor: f32) -> TriMesh {
    let (rings, segments) = (48u32, 24u32);
    let mut vertices = Vec::new();
    for i in 0..rings {
        let u = TAU * i as f32 / rings as f32;
        for j in 0..segments {
            let v = TAU * j as f32 / segments as f32;
            let r = major + minor * v.cos();
            vertices.push(Vec3::new(r * u.cos(), r * u.sin(), minor * v.sin()));
        }
    }
    let at = |i: u32, j: u32| (i % rings) * segments + j % segments;
    let mut triangles = Vec::new();
    for i in 0..rings {
        for j in 0..segments {
            triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
            triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
        }
    }
    TriMesh {
        vertices,
        triangles,
    }
}

/// A square plate whose underside carries a grid of hemispherical dots.
fn dotted_plate(side: f32, pitch: f32, dot_radius: f32, thickness: f32) -> TriMesh {
    let n = 96u32;
    // Underside: a height field over an (n + 1)² grid, dots hanging down.
    let mut rows = Vec::new();
    for jy in 0..=n {
        let y = -side / 2.0 + side * jy as f32 / n as f32;
        let mut row = Vec::new();
        for ix in 0..=n {
            let x = -side / 2.0 + side * ix as f32 / n as f32;
            let (dx, dy) = (
                (x / pitch).round() * pitch - x,
                (y / pitch).round() * pitch - y,
            );
            let d2 = dx * dx + dy * dy;
            let bump = (dot_radius * dot_radius - d2).max(0.0).sqrt();
            row.push(Vec3::new(x, y, dot_radius - bump));
        }
        rows.push(row);
    }
    let w = n + 1;
    let mut vertices: Vec<Vec3> = rows.iter().flatten().copied().collect();
    let mut triangles = Vec::new();
    let at = |ix: u32, jy: u32| jy * w + ix;
    for jy in 0..n {
        for ix in 0..n {
            triangles.push([at(ix, jy), at(ix + 1, jy + 1), at(ix + 1, jy)]);
            triangles.push([at(ix, jy), at(ix, jy + 1), at(ix + 1, jy + 1)]);
        }
    }
    // Top face and four sides.
    let top = dot_radius + thickness;
    let corners = [
        (-side / 2.0, -side / 2.0),
        (side / 2.0, -side / 2.0),
        (side / 2.0, side / 2.0),
        (-side / 2.0, side / 2.0),
    ];
    let base = vertices.len() as u32;
    vertices.extend(corners.iter().map(|&(x, y)| Vec3::new(x, y, top)));
    triangles.push([base, base + 1, base + 2]);
    triangles.push([base, base + 2, base + 3]);
    let edges: [Vec<u32>; 4] = [
        (0..w).map(|ix| at(ix, 0)).collect(),
        (0..w).map(|jy| at(n, jy)).collect(),
        (0..w).rev().map(|ix| at(ix, n)).collect(),
        (0..w).rev().map(|jy| at(0, jy)).collect(),
    ];
    for (k, edge) in edges.iter().enumerate() {
        let (c0, c1) = (base + k as u32, base + (k as u32 + 1) % 4);
        for pair in edge.windows(2) {
            triangles.push([pair[0], c0, pair[1]]);
        }
        triangles.push([edge[edge.len() - 1], c0, c1]);
    }
    TriMesh {
        vertices,
        triangles,
    }
}

fn main() {
    let dir = PathBuf::from(std::env::args().nth(1).unwrap_or("assets/meshes".into()));
    std::fs::create_dir_all(&dir).expect("output directory");
    let capsule_profile: Vec<(f32, f32)> = (0..=12)
        .map(|k| {
            let t = PI / 2.0 * k as f32 / 12.0;
            (3.0 * t.sin(), 3.0 * (1.0 - t.cos()))
        })
        .chain([(3.0, 10.0)])
        .collect();
    let hexagon: Vec<(f32, f32)> = (0..6)
        .map(|k| {
            let a = TAU * k as f32 / 6.0;
            (4.0 * a.cos(), 4.0 * a.sin())
        })
        .collect();
    // A 90° edge along y: triangular cross-section in x–z, extruded 12 mm.
    let ridge = {
        let mut m = prism(&[(-4.0, 4.0), (0.0, 0.0), (4.0, 4.0)], 12.0);
        for v in &mut m.vertices {
            *v = Vec3::new(v.x, v.z - 6.0, v.y);
        }
        m
    };
    let meshes: [(&str, TriMesh); 5] = [
        ("capsule.obj", revolve(&capsule_profile, 48)),
        ("ridge.obj", ridge),
        ("torus.obj", torus(4.0, 1.2)),
        ("hex_prism.glb", prism(&hexagon, 6.0)),
        ("dotted_plate.glb", dotted_plate(14.0, 2.0, 0.6, 2.0)),
    ];
    for (name, mesh) in meshes {
        let mesh = mesh.validated().expect("generated meshes are valid");
        let bytes = if name.ends_with(".obj") {
            mesh.to_obj().into_bytes()
        } else {
            mesh.to_glb()
        };
        std::fs::write(dir.join(name), bytes).expect("write mesh");
        println!("{name}: {} triangles", mesh.triangles.len());
    }
}
