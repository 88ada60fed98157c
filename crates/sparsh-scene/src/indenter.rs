//! Indenters: analytic primitives, procedural textured plates and triangle meshes (OBJ via tobj,
//! glTF/GLB via gltf), each able to cast a ray against itself in its own frame.
//!
//! Local frame: the indenter's tip (lowest point) is the origin and its body extends towards +z,
//! so a pose with position z = −d presses it d millimetres into the gel.

use std::path::{Path, PathBuf};

use glam::{DVec3, Mat4, Vec3, Vec3A};
use obvhs::{
    ray::{Ray, RayHit},
    triangle::Triangle,
};
use serde::Deserialize;

use crate::SceneError;

/// Primitive shape or mesh named in `[indenter]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapeKind {
    /// Sphere of `radius_mm`.
    Sphere,
    /// Flat-ended cylinder (flat punch) of `radius_mm` and `height_mm`.
    Cylinder,
    /// Cone, tip down, of `half_angle_deg` (axis to face) and `height_mm`.
    Cone,
    /// Box of `size_mm` = [x, y, z], bottom face down.
    Box,
    /// Plate of `size_mm` whose underside carries a periodic relief: `pattern`, `pitch_mm`,
    /// `depth_mm`, optionally crowned (`crown_radius_mm`), see [`TexturedPlate`].
    Texture,
    /// Triangle mesh from `mesh` (.obj, .gltf, .glb).
    Mesh,
}

/// Relief of a textured plate's underside (`pattern` of `shape = "texture"`), periodic with
/// `pitch_mm`. Each pattern has a crest at the local origin; its features are raised-cosine
/// bumps, ridges and grooves, so the relief's slope is bounded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Pattern {
    /// Parallel round-topped ribs along y, `pitch` apart, each 0.6 pitch wide, flat between
    /// (corduroy).
    Ribs,
    /// Plain weave: yarns along x and y, `pitch` apart, passing over and under each other at
    /// alternate crossings (period 2 pitch).
    Weave,
    /// Diamond knurl: pyramids between two sets of V-grooves at ±45°, grooves `pitch` apart.
    Knurl,
    /// Round bumps of radius 0.3 pitch on a square grid of `pitch`, flat between.
    Dots,
}

impl Pattern {
    /// Relief profile τ ∈ [0, 1] (1 at a crest, 0 at the deepest trough) at (u, v) = (x, y) in
    /// pitches.
    pub fn profile(self, u: f64, v: f64) -> f64 {
        use std::f64::consts::{FRAC_1_SQRT_2, PI};
        // Offset from the nearest integer, in [−0.5, 0.5].
        let frac = |t: f64| t - t.round();
        // A raised-cosine bump of half-width w (pitches) and unit height.
        let bump = |t: f64, w: f64| {
            if t.abs() < w {
                0.5 + 0.5 * (PI * t / w).cos()
            } else {
                0.0
            }
        };
        match self {
            Pattern::Ribs => bump(frac(u), 0.3),
            Pattern::Weave => {
                let (i, j) = (u.round(), v.round());
                let warp = (0.6 + 0.4 * (PI * (v - i)).cos()) * bump(u - i, 0.5);
                let weft = (0.6 + 0.4 * (PI * (u - j - 1.0)).cos()) * bump(v - j, 0.5);
                warp.max(weft)
            }
            Pattern::Knurl => {
                let tri = |t: f64| 1.0 - 2.0 * frac(t).abs();
                tri(FRAC_1_SQRT_2 * (u + v)).min(tri(FRAC_1_SQRT_2 * (u - v)))
            }
            Pattern::Dots => bump(frac(u).hypot(frac(v)), 0.3),
        }
    }

    /// An upper bound of |∇τ| (per pitch).
    pub fn max_slope(self) -> f64 {
        use std::f64::consts::PI;
        match self {
            // π/(2w) for a raised cosine of half-width w.
            Pattern::Ribs | Pattern::Dots => PI / 0.6,
            // Across a yarn π (w = 0.5), along it 0.4π.
            Pattern::Weave => PI * (1.0f64 + 0.16).sqrt(),
            Pattern::Knurl => 2.0,
        }
    }
}

/// Length unit of a mesh file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum LengthUnit {
    /// Millimetres.
    #[default]
    Mm,
    /// Centimetres.
    Cm,
    /// Metres.
    M,
}

impl LengthUnit {
    fn to_mm(self) -> f64 {
        match self {
            LengthUnit::Mm => 1.0,
            LengthUnit::Cm => 10.0,
            LengthUnit::M => 1000.0,
        }
    }
}

/// Where a mesh's local origin goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Anchor {
    /// Lowest vertex at z = 0, bounding box centred in x and y.
    #[default]
    Tip,
    /// Keep the file's own origin.
    Origin,
}

/// The `[indenter]` table as written in a scene file.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IndenterSpec {
    /// Shape kind.
    pub shape: ShapeKind,
    /// Sphere, cylinder radius (mm).
    pub radius_mm: Option<f64>,
    /// Cylinder and cone height (mm); default 10.
    pub height_mm: Option<f64>,
    /// Cone semi-angle between axis and face (degrees).
    pub half_angle_deg: Option<f64>,
    /// Box edge lengths, or a textured plate's footprint and height (mm).
    pub size_mm: Option<[f64; 3]>,
    /// Textured plate's relief pattern.
    pub pattern: Option<Pattern>,
    /// Textured plate's relief period (mm).
    pub pitch_mm: Option<f64>,
    /// Textured plate's relief depth, crest to trough (mm).
    pub depth_mm: Option<f64>,
    /// Textured plate's underside curvature radius (mm); default flat.
    pub crown_radius_mm: Option<f64>,
    /// Mesh file, relative to the scene file.
    pub mesh: Option<PathBuf>,
    /// Mesh scale factor (after the unit conversion); default 1.
    pub scale: Option<f64>,
    /// Mesh length unit; default mm.
    pub units: Option<LengthUnit>,
    /// Mesh placement; default `tip`.
    pub anchor: Option<Anchor>,
}

/// A triangle mesh in millimetres.
#[derive(Debug, Clone, PartialEq)]
pub struct TriMesh {
    /// Vertex positions (mm).
    pub vertices: Vec<Vec3>,
    /// Triangles as vertex indices.
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    /// A UV sphere of `radius_mm` centred at (0, 0, radius) with `rings` latitude bands and
    /// `segments` longitude sectors; its vertices lie on the sphere.
    pub fn uv_sphere(radius_mm: f32, rings: u32, segments: u32) -> TriMesh {
        let mut vertices = vec![Vec3::new(0.0, 0.0, 0.0)];
        for r in 1..rings {
            let theta = std::f32::consts::PI * r as f32 / rings as f32;
            for s in 0..segments {
                let phi = std::f32::consts::TAU * s as f32 / segments as f32;
                vertices.push(Vec3::new(
                    radius_mm * theta.sin() * phi.cos(),
                    radius_mm * theta.sin() * phi.sin(),
                    radius_mm * (1.0 - theta.cos()),
                ));
            }
        }
        vertices.push(Vec3::new(0.0, 0.0, 2.0 * radius_mm));
        let top = vertices.len() as u32 - 1;
        let at = |r: u32, s: u32| 1 + (r - 1) * segments + s % segments;
        let mut triangles = Vec::new();
        for s in 0..segments {
            triangles.push([0, at(1, s + 1), at(1, s)]);
            triangles.push([top, at(rings - 1, s), at(rings - 1, s + 1)]);
        }
        for r in 1..rings - 1 {
            for s in 0..segments {
                triangles.push([at(r, s), at(r, s + 1), at(r + 1, s + 1)]);
                triangles.push([at(r, s), at(r + 1, s + 1), at(r + 1, s)]);
            }
        }
        TriMesh {
            vertices,
            triangles,
        }
    }

    /// Wavefront OBJ text of the mesh (millimetres).
    pub fn to_obj(&self) -> String {
        let mut obj = String::new();
        for v in &self.vertices {
            obj += &format!("v {} {} {}\n", v.x, v.y, v.z);
        }
        for t in &self.triangles {
            obj += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
        }
        obj
    }

    /// Binary glTF 2.0 (GLB) of the mesh: one node, one triangle primitive (millimetres).
    pub fn to_glb(&self) -> Vec<u8> {
        let mut bin: Vec<u8> = self
            .vertices
            .iter()
            .flat_map(|v| v.to_array())
            .flat_map(f32::to_le_bytes)
            .collect();
        let vertex_bytes = bin.len();
        bin.extend(
            self.triangles
                .iter()
                .flatten()
                .flat_map(|i| i.to_le_bytes()),
        );
        let index_bytes = bin.len() - vertex_bytes;
        let finite = self.vertices.iter().filter(|v| v.is_finite());
        let lo = finite.clone().fold(Vec3::INFINITY, |m, v| m.min(*v));
        let hi = finite.fold(Vec3::NEG_INFINITY, |m, v| m.max(*v));
        let mut json = format!(
            concat!(
                r#"{{"asset":{{"version":"2.0","generator":"sparsh"}},"scene":0,"#,
                r#""scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],"#,
                r#""meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],"#,
                r#""buffers":[{{"byteLength":{}}}],"bufferViews":["#,
                r#"{{"buffer":0,"byteOffset":0,"byteLength":{}}},"#,
                r#"{{"buffer":0,"byteOffset":{},"byteLength":{}}}],"accessors":["#,
                r#"{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":[{},{},{}],"max":[{},{},{}]}},"#,
                r#"{{"bufferView":1,"componentType":5125,"count":{},"type":"SCALAR"}}]}}"#
            ),
            vertex_bytes + index_bytes,
            vertex_bytes,
            vertex_bytes,
            index_bytes,
            self.vertices.len(),
            lo.x,
            lo.y,
            lo.z,
            hi.x,
            hi.y,
            hi.z,
            self.triangles.len() * 3
        )
        .into_bytes();
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut glb = Vec::with_capacity(total);
        glb.extend(b"glTF");
        glb.extend(2u32.to_le_bytes());
        glb.extend((total as u32).to_le_bytes());
        glb.extend((json.len() as u32).to_le_bytes());
        glb.extend(b"JSON");
        glb.extend(&json);
        glb.extend((bin.len() as u32).to_le_bytes());
        glb.extend(b"BIN\0");
        glb.extend(&bin);
        glb
    }

    /// Reads an `.obj`, `.gltf` or `.glb` file (positions only), converted to millimetres.
    pub fn load(path: &Path, unit: LengthUnit, scale: f64) -> Result<TriMesh, SceneError> {
        let err = |message: String| SceneError::Mesh {
            path: path.to_path_buf(),
            message,
        };
        if !path.is_file() {
            return Err(err("file does not exist".into()));
        }
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        let mut mesh = match ext.as_str() {
            "obj" => load_obj(path).map_err(err)?,
            "gltf" | "glb" => load_gltf(path).map_err(err)?,
            other => {
                return Err(err(format!(
                    "unsupported extension `{other}` (use .obj, .gltf or .glb)"
                )));
            }
        };
        let factor = (unit.to_mm() * scale) as f32;
        for v in &mut mesh.vertices {
            *v *= factor;
        }
        mesh.validated().map_err(err)
    }

    /// Checks vertices are finite and indices in range, drops zero-area triangles, and fails
    /// when none is left.
    pub fn validated(mut self) -> Result<TriMesh, String> {
        if let Some(k) = self.vertices.iter().position(|v| !v.is_finite()) {
            return Err(format!("vertex {k} is not finite ({})", self.vertices[k]));
        }
        let n = self.vertices.len() as u32;
        if let Some(t) = self.triangles.iter().find(|t| t.iter().any(|&i| i >= n)) {
            return Err(format!("triangle {t:?} indexes past the {n} vertices"));
        }
        let vertices = &self.vertices;
        self.triangles.retain(|t| {
            let [a, b, c] = t.map(|i| vertices[i as usize]);
            (b - a).cross(c - a).length() > 1e-12
        });
        if self.triangles.is_empty() {
            return Err("no triangle with non-zero area".into());
        }
        Ok(self)
    }

    /// Moves the mesh so its lowest vertex is at z = 0 and its bounding box is centred in x, y.
    pub fn anchored_at_tip(mut self) -> TriMesh {
        let lo = self.vertices.iter().fold(Vec3::INFINITY, |m, v| m.min(*v));
        let hi = self
            .vertices
            .iter()
            .fold(Vec3::NEG_INFINITY, |m, v| m.max(*v));
        let shift = Vec3::new(-(lo.x + hi.x) / 2.0, -(lo.y + hi.y) / 2.0, -lo.z);
        for v in &mut self.vertices {
            *v += shift;
        }
        self
    }
}

fn load_obj(path: &Path) -> Result<TriMesh, String> {
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ..Default::default()
    };
    let (models, _) = tobj::load_obj(path, &options).map_err(|e| format!("OBJ: {e}"))?;
    let mut mesh = TriMesh {
        vertices: Vec::new(),
        triangles: Vec::new(),
    };
    for model in models {
        let base = mesh.vertices.len() as u32;
        let p = &model.mesh.positions;
        mesh.vertices
            .extend(p.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])));
        mesh.triangles.extend(
            model
                .mesh
                .indices
                .chunks_exact(3)
                .map(|t| [t[0], t[1], t[2]].map(|i| base.saturating_add(i))),
        );
    }
    Ok(mesh)
}

fn load_gltf(path: &Path) -> Result<TriMesh, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("glTF: {e}"))?;
    let gltf::Gltf { document, blob } =
        gltf::Gltf::from_slice_without_validation(&bytes).map_err(|e| format!("glTF: {e}"))?;
    let json = document.into_json();
    // gltf-json's validation indexes a primitive's POSITION accessor without checking it exists.
    let positions = gltf::json::validation::Checked::Valid(gltf::Semantic::Positions);
    for (m, mesh) in json.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            if let Some(a) = prim.attributes.get(&positions)
                && a.value() >= json.accessors.len()
            {
                return Err(format!(
                    "glTF: meshes[{m}].primitives[{p}]: POSITION accessor {} does not exist",
                    a.value()
                ));
            }
        }
    }
    let document = gltf::Document::from_json(json).map_err(|e| format!("glTF: {e}"))?;
    let buffers = gltf::import_buffers(&document, path.parent(), blob)
        .map_err(|e| format!("glTF buffers: {e}"))?;
    let mut mesh = TriMesh {
        vertices: Vec::new(),
        triangles: Vec::new(),
    };
    let scene = document
        .default_scene()
        .or_else(|| document.scenes().next())
        .ok_or("glTF: no scene")?;
    let mut stack: Vec<(gltf::Node, Mat4)> = scene.nodes().map(|n| (n, Mat4::IDENTITY)).collect();
    // Nodes form a tree: a node reached twice (a cycle or a shared child) is refused.
    let mut reached = vec![false; document.nodes().len()];
    while let Some((node, parent)) = stack.pop() {
        if std::mem::replace(&mut reached[node.index()], true) {
            return Err(format!(
                "glTF: node {} is reached twice (nodes must form a tree)",
                node.index()
            ));
        }
        let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        if let Some(m) = node.mesh() {
            for prim in m.primitives() {
                if prim.mode() != gltf::mesh::Mode::Triangles {
                    return Err(format!(
                        "glTF: primitive mode {:?} (only triangles)",
                        prim.mode()
                    ));
                }
                let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
                let base = mesh.vertices.len() as u32;
                // The reader yields nothing for an accessor that reaches past its buffer.
                let unreadable = |a: gltf::Accessor, what: &str| {
                    format!(
                        "glTF: {what} accessor {} ({} items) reaches past its buffer",
                        a.index(),
                        a.count()
                    )
                };
                let positions = reader.read_positions().ok_or_else(|| {
                    match prim.get(&gltf::Semantic::Positions) {
                        Some(a) => unreadable(a, "POSITION"),
                        None => "glTF: primitive without positions".into(),
                    }
                })?;
                mesh.vertices
                    .extend(positions.map(|p| world.transform_point3(Vec3::from(p))));
                let count = mesh.vertices.len() as u32 - base;
                match (reader.read_indices(), prim.indices()) {
                    (None, Some(a)) => return Err(unreadable(a, "index")),
                    (Some(ix), _) => {
                        let ix: Vec<u32> = ix.into_u32().collect();
                        mesh.triangles.extend(
                            ix.chunks_exact(3)
                                .map(|t| [t[0], t[1], t[2]].map(|i| base.saturating_add(i))),
                        );
                    }
                    (None, None) => mesh.triangles.extend(
                        (0..count / 3).map(|k| [base + 3 * k, base + 3 * k + 1, base + 3 * k + 2]),
                    ),
                }
            }
        }
        stack.extend(node.children().map(|c| (c, world)));
    }
    Ok(mesh)
}

/// An indenter ready for ray casting, in its local frame (tip at the origin, body towards +z).
#[derive(Debug, Clone)]
pub enum Indenter {
    /// Sphere centred at (0, 0, R).
    Sphere {
        /// Radius (mm).
        radius_mm: f64,
    },
    /// Flat punch: solid cylinder x² + y² ≤ R², 0 ≤ z ≤ H.
    Cylinder {
        /// Radius (mm).
        radius_mm: f64,
        /// Height (mm).
        height_mm: f64,
    },
    /// Cone √(x² + y²) ≤ z tan α, 0 ≤ z ≤ H.
    Cone {
        /// Semi-angle α between axis and face (degrees).
        half_angle_deg: f64,
        /// Height (mm).
        height_mm: f64,
    },
    /// Box |x| ≤ sx/2, |y| ≤ sy/2, 0 ≤ z ≤ sz.
    Box {
        /// Edge lengths (mm).
        size_mm: [f64; 3],
    },
    /// A plate with a periodic relief on its underside.
    Texture(TexturedPlate),
    /// A triangle mesh with its bounding volume hierarchy.
    Mesh(Box<MeshIndenter>),
}

/// A plate whose underside carries a periodic relief: the solid |x| ≤ sx/2, |y| ≤ sy/2,
/// s(x, y) ≤ z ≤ sz with the underside
///
/// s(x, y) = (x² + y²)/(2 R) + depth · (1 − τ(x/pitch, y/pitch)),
///
/// τ the [`Pattern`]'s profile and R the crown radius (the paraboloid term is absent on a flat
/// plate). A crowned plate touches the gel over a patch that grows with the press, like a fabric
/// stretched over a rounded finger; a flat one meets it everywhere at once. Every pattern has a
/// crest at the origin, so the tip (s = 0) is the local origin. Where the crown rises above the
/// plate's height the footprint is cut away.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TexturedPlate {
    /// Relief pattern.
    pub pattern: Pattern,
    /// Period of the relief (mm).
    pub pitch_mm: f64,
    /// Relief depth, crest to trough (mm).
    pub depth_mm: f64,
    /// Footprint [x, y] and height z of the plate (mm).
    pub size_mm: [f64; 3],
    /// Curvature radius of the underside (mm); `None` is flat.
    pub crown_radius_mm: Option<f64>,
}

impl TexturedPlate {
    /// Footprint and height when `size_mm` is not given: 20 × 20 mm, 5 mm tall.
    pub const DEFAULT_SIZE_MM: [f64; 3] = [20.0, 20.0, 5.0];

    /// Height s(x, y) of the underside above the tip (mm, ≥ 0), in the local frame.
    pub fn underside_mm(&self, x: f64, y: f64) -> f64 {
        let crown = self
            .crown_radius_mm
            .map_or(0.0, |r| (x * x + y * y) / (2.0 * r));
        let tau = self.pattern.profile(x / self.pitch_mm, y / self.pitch_mm);
        crown + self.depth_mm * (1.0 - tau)
    }

    /// An upper bound of the underside's slope |∇s| over the footprint.
    pub fn max_slope(&self) -> f64 {
        let [sx, sy, _] = self.size_mm;
        let crown = self
            .crown_radius_mm
            .map_or(0.0, |r| (sx / 2.0).hypot(sy / 2.0) / r);
        crown + self.depth_mm * self.pattern.max_slope() / self.pitch_mm
    }

    /// Entry of the ray `o + t·d` (unit `d`) into the plate. A ray along ±z meets the underside
    /// in closed form. An oblique one is marched from where it enters the plate's bounding box:
    /// each step is the distance the ray needs to reach the underside if the relief rose at its
    /// steepest ([`TexturedPlate::max_slope`]), so no crossing is stepped over (steps are at
    /// least 0.1 µm, at most 100 000 of them); the crossing is then refined by bisection.
    fn ray_entry(&self, o: DVec3, d: DVec3) -> Option<f64> {
        const MIN_STEP_MM: f64 = 1e-4;
        let [sx, sy, sz] = self.size_mm;
        let footprint = intersect(
            slab(o.x, d.x, -sx / 2.0, sx / 2.0)?,
            slab(o.y, d.y, -sy / 2.0, sy / 2.0)?,
        )?;
        let horizontal = d.x.hypot(d.y);
        if horizontal < 1e-12 {
            let s = self.underside_mm(o.x, o.y);
            return entry(intersect(footprint, slab(o.z, d.z, s, sz)?)?);
        }
        let (t0, t1) = intersect(footprint, slab(o.z, d.z, 0.0, sz)?)?;
        if t1 < 0.0 {
            return None;
        }
        // How far above the underside the ray is at t: ≥ 0 inside the plate.
        let above = |t: f64| {
            let p = o + t * d;
            p.z - self.underside_mm(p.x, p.y)
        };
        // |d above / dt| ≤ lipschitz.
        let lipschitz = d.z.abs() + horizontal * self.max_slope();
        let mut lo = t0;
        let mut gap = above(lo);
        if gap >= 0.0 {
            return Some(t0);
        }
        let mut hi = lo;
        for _ in 0..100_000 {
            hi = (lo + (-gap / lipschitz).max(MIN_STEP_MM)).min(t1);
            let next = above(hi);
            if next >= 0.0 {
                break;
            }
            if hi >= t1 {
                return None;
            }
            (lo, gap) = (hi, next);
        }
        if above(hi) < 0.0 {
            return None;
        }
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if above(mid) >= 0.0 {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        Some(hi)
    }
}

/// A triangle mesh with a BVH over its triangles (obvhs).
#[derive(Clone)]
pub struct MeshIndenter {
    /// The mesh (mm).
    pub mesh: TriMesh,
    triangles: Vec<Triangle>,
    bvh: obvhs::bvh2::Bvh2,
}

impl std::fmt::Debug for MeshIndenter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeshIndenter")
            .field("vertices", &self.mesh.vertices.len())
            .field("triangles", &self.triangles.len())
            .finish()
    }
}

impl MeshIndenter {
    /// Builds the BVH.
    pub fn new(mesh: TriMesh) -> MeshIndenter {
        let triangles: Vec<Triangle> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [v0, v1, v2] = t.map(|i| Vec3A::from(mesh.vertices[i as usize]));
                Triangle { v0, v1, v2 }
            })
            .collect();
        let bvh = obvhs::bvh2::builder::build_bvh2_from_tris(
            &triangles,
            obvhs::BvhBuildParams::medium_build(),
            &mut std::time::Duration::default(),
        );
        MeshIndenter {
            mesh,
            triangles,
            bvh,
        }
    }
}

impl Indenter {
    /// Radius of a ball about the local origin that contains the whole indenter (mm).
    pub fn bounding_radius_mm(&self) -> f64 {
        match self {
            Indenter::Sphere { radius_mm } => 2.0 * radius_mm,
            Indenter::Cylinder {
                radius_mm,
                height_mm,
            } => radius_mm.hypot(*height_mm),
            Indenter::Cone {
                half_angle_deg,
                height_mm,
            } => height_mm / half_angle_deg.to_radians().cos(),
            Indenter::Box { size_mm } | Indenter::Texture(TexturedPlate { size_mm, .. }) => {
                DVec3::new(size_mm[0] / 2.0, size_mm[1] / 2.0, size_mm[2]).length()
            }
            Indenter::Mesh(m) => m
                .mesh
                .vertices
                .iter()
                .map(|v| v.length() as f64)
                .fold(0.0, f64::max),
        }
    }

    /// Distance along the ray `origin + t·dir` (unit `dir`, local frame) to where it first
    /// enters the indenter, or `None` when it misses.
    pub fn ray_entry(&self, origin: DVec3, dir: DVec3) -> Option<f64> {
        match self {
            Indenter::Sphere { radius_mm } => {
                let oc = origin - DVec3::new(0.0, 0.0, *radius_mm);
                let b = oc.dot(dir);
                let c = oc.length_squared() - radius_mm * radius_mm;
                let disc = b * b - c;
                (disc >= 0.0).then(|| -b - disc.sqrt())
            }
            Indenter::Cylinder {
                radius_mm,
                height_mm,
            } => {
                let radial = disc_interval(origin, dir, *radius_mm)?;
                let axial = slab(origin.z, dir.z, 0.0, *height_mm)?;
                entry(intersect(radial, axial)?)
            }
            Indenter::Box { size_mm } => {
                let [sx, sy, sz] = *size_mm;
                let i = slab(origin.x, dir.x, -sx / 2.0, sx / 2.0)?;
                let i = intersect(i, slab(origin.y, dir.y, -sy / 2.0, sy / 2.0)?)?;
                entry(intersect(i, slab(origin.z, dir.z, 0.0, sz)?)?)
            }
            Indenter::Cone {
                half_angle_deg,
                height_mm,
            } => cone_entry(origin, dir, half_angle_deg.to_radians().tan(), *height_mm),
            Indenter::Texture(plate) => plate.ray_entry(origin, dir),
            Indenter::Mesh(m) => {
                let ray = Ray::new_inf(origin.as_vec3().into(), dir.as_vec3().into());
                let mut hit = RayHit::none();
                let found = m.bvh.ray_traverse(ray, &mut hit, |r, id| {
                    m.triangles[m.bvh.primitive_indices[id] as usize].intersect(r)
                });
                found.then_some(hit.t as f64)
            }
        }
    }
}

/// Parameter interval `[t0, t1]` of a ray.
type Interval = (f64, f64);

fn intersect(a: Interval, b: Interval) -> Option<Interval> {
    let i = (a.0.max(b.0), a.1.min(b.1));
    (i.0 <= i.1).then_some(i)
}

fn entry(i: Interval) -> Option<f64> {
    (i.1 >= 0.0).then_some(i.0)
}

/// Where `lo ≤ o + t d ≤ hi` along one axis.
fn slab(o: f64, d: f64, lo: f64, hi: f64) -> Option<Interval> {
    if d.abs() < 1e-15 {
        return (lo..=hi)
            .contains(&o)
            .then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let (a, b) = ((lo - o) / d, (hi - o) / d);
    Some((a.min(b), a.max(b)))
}

/// Where the ray is inside the infinite cylinder x² + y² ≤ r².
fn disc_interval(o: DVec3, d: DVec3, r: f64) -> Option<Interval> {
    let a = d.x * d.x + d.y * d.y;
    let c = o.x * o.x + o.y * o.y - r * r;
    if a < 1e-15 {
        return (c <= 0.0).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let b = o.x * d.x + o.y * d.y;
    let disc = b * b - a * c;
    (disc >= 0.0).then(|| ((-b - disc.sqrt()) / a, (-b + disc.sqrt()) / a))
}

/// Entry into the solid cone x² + y² ≤ k² z², 0 ≤ z ≤ h, with k = tan α.
fn cone_entry(o: DVec3, d: DVec3, k: f64, h: f64) -> Option<f64> {
    let k2 = k * k;
    let a = d.x * d.x + d.y * d.y - k2 * d.z * d.z;
    let b = 2.0 * (o.x * d.x + o.y * d.y - k2 * o.z * d.z);
    let c = o.x * o.x + o.y * o.y - k2 * o.z * o.z;
    let all = (f64::NEG_INFINITY, f64::INFINITY);
    // Pieces of the double cone {a t² + b t + c ≤ 0}; the z ≥ 0 slab keeps the upper nappe.
    let pieces: Vec<Interval> = if a.abs() < 1e-12 {
        if b.abs() < 1e-15 {
            if c <= 0.0 { vec![all] } else { vec![] }
        } else if b > 0.0 {
            vec![(f64::NEG_INFINITY, -c / b)]
        } else {
            vec![(-c / b, f64::INFINITY)]
        }
    } else {
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            if a < 0.0 { vec![all] } else { vec![] }
        } else {
            let (r1, r2) = (
                (-b - disc.sqrt()) / (2.0 * a),
                (-b + disc.sqrt()) / (2.0 * a),
            );
            let (t1, t2) = (r1.min(r2), r1.max(r2));
            if a > 0.0 {
                vec![(t1, t2)]
            } else {
                vec![(f64::NEG_INFINITY, t1), (t2, f64::INFINITY)]
            }
        }
    };
    let axial = slab(o.z, d.z, 0.0, h)?;
    pieces
        .into_iter()
        .filter_map(|p| intersect(p, axial))
        .filter(|i| {
            let mid = if i.0.is_finite() && i.1.is_finite() {
                (i.0 + i.1) / 2.0
            } else if i.0.is_finite() {
                i.0
            } else {
                i.1
            };
            o.z + mid * d.z >= -1e-9
        })
        .filter_map(entry)
        .min_by(|x, y| x.total_cmp(y))
}

impl IndenterSpec {
    /// A short name of the shape for labels and splits: the mesh file's stem, the textured
    /// plate's pattern, else the shape kind (`sphere`, `cylinder`, `cone`, `box`).
    pub fn name(&self) -> String {
        let kind = match self.shape {
            ShapeKind::Sphere => "sphere",
            ShapeKind::Cylinder => "cylinder",
            ShapeKind::Cone => "cone",
            ShapeKind::Box => "box",
            ShapeKind::Texture => match self.pattern {
                Some(Pattern::Ribs) => "ribs",
                Some(Pattern::Weave) => "weave",
                Some(Pattern::Knurl) => "knurl",
                Some(Pattern::Dots) => "dots",
                None => "texture",
            },
            ShapeKind::Mesh => match self.mesh.as_deref().and_then(Path::file_stem) {
                Some(stem) => return stem.to_string_lossy().into_owned(),
                None => "mesh",
            },
        };
        kind.to_string()
    }

    /// Resolves the spec into a ray-castable indenter; `scene` is the scene file (errors name it,
    /// mesh paths are relative to it).
    pub fn build(&self, scene: &Path) -> Result<Indenter, SceneError> {
        let positive = |field: &str, v: Option<f64>| -> Result<f64, SceneError> {
            match v {
                None => Err(SceneError::invalid(
                    scene,
                    format!("indenter.{field}"),
                    format!("required for shape {:?}", self.shape),
                )),
                Some(x) if !(x.is_finite() && x > 0.0) => Err(SceneError::invalid(
                    scene,
                    format!("indenter.{field}"),
                    format!("must be > 0, got {x}"),
                )),
                Some(x) => Ok(x),
            }
        };
        let height = || positive("height_mm", Some(self.height_mm.unwrap_or(10.0)));
        let unused = |allowed: &[&str]| -> Result<(), SceneError> {
            let given = [
                ("radius_mm", self.radius_mm.is_some()),
                ("height_mm", self.height_mm.is_some()),
                ("half_angle_deg", self.half_angle_deg.is_some()),
                ("size_mm", self.size_mm.is_some()),
                ("pattern", self.pattern.is_some()),
                ("pitch_mm", self.pitch_mm.is_some()),
                ("depth_mm", self.depth_mm.is_some()),
                ("crown_radius_mm", self.crown_radius_mm.is_some()),
                ("mesh", self.mesh.is_some()),
                ("scale", self.scale.is_some()),
                ("units", self.units.is_some()),
                ("anchor", self.anchor.is_some()),
            ];
            match given.iter().find(|(k, g)| *g && !allowed.contains(k)) {
                Some((k, _)) => Err(SceneError::invalid(
                    scene,
                    format!("indenter.{k}"),
                    format!("does not apply to shape {:?}", self.shape),
                )),
                None => Ok(()),
            }
        };
        Ok(match self.shape {
            ShapeKind::Sphere => {
                unused(&["radius_mm"])?;
                Indenter::Sphere {
                    radius_mm: positive("radius_mm", self.radius_mm)?,
                }
            }
            ShapeKind::Cylinder => {
                unused(&["radius_mm", "height_mm"])?;
                Indenter::Cylinder {
                    radius_mm: positive("radius_mm", self.radius_mm)?,
                    height_mm: height()?,
                }
            }
            ShapeKind::Cone => {
                unused(&["half_angle_deg", "height_mm"])?;
                let alpha = positive("half_angle_deg", self.half_angle_deg)?;
                if alpha >= 90.0 {
                    return Err(SceneError::invalid(
                        scene,
                        "indenter.half_angle_deg",
                        format!("must be below 90, got {alpha}"),
                    ));
                }
                Indenter::Cone {
                    half_angle_deg: alpha,
                    height_mm: height()?,
                }
            }
            ShapeKind::Box => {
                unused(&["size_mm"])?;
                let s = self.size_mm.ok_or_else(|| {
                    SceneError::invalid(scene, "indenter.size_mm", "required for shape Box")
                })?;
                for v in s {
                    positive("size_mm", Some(v))?;
                }
                Indenter::Box { size_mm: s }
            }
            ShapeKind::Texture => {
                unused(&[
                    "size_mm",
                    "pattern",
                    "pitch_mm",
                    "depth_mm",
                    "crown_radius_mm",
                ])?;
                let pattern = self.pattern.ok_or_else(|| {
                    SceneError::invalid(
                        scene,
                        "indenter.pattern",
                        "required for shape Texture (ribs, weave, knurl or dots)",
                    )
                })?;
                let size_mm = self.size_mm.unwrap_or(TexturedPlate::DEFAULT_SIZE_MM);
                for v in size_mm {
                    positive("size_mm", Some(v))?;
                }
                let plate = TexturedPlate {
                    pattern,
                    pitch_mm: positive("pitch_mm", self.pitch_mm)?,
                    depth_mm: positive("depth_mm", self.depth_mm)?,
                    size_mm,
                    crown_radius_mm: match self.crown_radius_mm {
                        None => None,
                        r => Some(positive("crown_radius_mm", r)?),
                    },
                };
                if size_mm[2] <= plate.depth_mm {
                    return Err(SceneError::invalid(
                        scene,
                        "indenter.size_mm",
                        format!(
                            "the plate's height ({}) must exceed depth_mm ({})",
                            size_mm[2], plate.depth_mm
                        ),
                    ));
                }
                Indenter::Texture(plate)
            }
            ShapeKind::Mesh => {
                unused(&["mesh", "scale", "units", "anchor"])?;
                let rel = self.mesh.as_ref().ok_or_else(|| {
                    SceneError::invalid(scene, "indenter.mesh", "required for shape Mesh")
                })?;
                let path = scene.parent().unwrap_or(Path::new(".")).join(rel);
                let scale = positive("scale", Some(self.scale.unwrap_or(1.0)))?;
                let mesh = TriMesh::load(&path, self.units.unwrap_or_default(), scale)?;
                let mesh = match self.anchor.unwrap_or_default() {
                    Anchor::Tip => mesh.anchored_at_tip(),
                    Anchor::Origin => mesh,
                };
                Indenter::Mesh(Box::new(MeshIndenter::new(mesh)))
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_indenter_is_named_by_its_mesh_pattern_or_shape() {
        let name = |text: &str| toml::from_str::<IndenterSpec>(text).unwrap().name();
        assert_eq!(name("shape = \"sphere\"\nradius_mm = 3.0"), "sphere");
        assert_eq!(name("shape = \"box\"\nsize_mm = [3.0, 3.0, 4.0]"), "box");
        assert_eq!(
            name("shape = \"mesh\"\nmesh = \"../assets/meshes/hex_prism.glb\""),
            "hex_prism"
        );
        assert_eq!(
            name("shape = \"texture\"\npattern = \"knurl\"\npitch_mm = 1.0"),
            "knurl"
        );
    }
}
