//! Scene files: parsing, defaults, mesh formats, and one clear error per kind of bad input.

use std::path::{Path, PathBuf};

use glam::Vec3;
use proptest::prelude::*;
use proptest::test_runner::RngSeed;
use sparsh_scene::{Indenter, Scene, SceneError, TriMesh, ValidityPolicy};

const BASE: &str = r#"
seed = 3
[sensor]
preset = "digit"
width_px = 64
height_px = 48
[gel]
youngs_modulus_kpa = 200.0
[indenter]
shape = "sphere"
radius_mm = 5.0
[[trajectory]]
time_s = 0.0
position_mm = [0.0, 0.0, 0.5]
[[trajectory]]
time_s = 2.0
position_mm = [0.0, 0.0, -1.0]
"#;

fn parse(text: &str) -> Result<Scene, SceneError> {
    Scene::parse(Path::new("scenes/test.toml"), text.to_string())
}

fn error_of(text: &str) -> String {
    let err = parse(text).expect_err("scene should be rejected");
    let line = err.to_string();
    assert!(!line.contains('\n'), "error spans lines: {line}");
    assert!(
        line.starts_with("scenes/test.toml"),
        "error must name the file: {line}"
    );
    line
}

#[test]
fn quickstart_parses_with_preset_defaults() {
    let scene =
        Scene::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/quickstart.toml"))
            .expect("quickstart scene loads");
    assert_eq!(scene.sensor.name, "digit");
    assert_eq!(scene.frames().len(), 120, "2 s at 60 fps");
    assert!(matches!(scene.indenter, Indenter::Sphere { radius_mm } if radius_mm == 6.0));
}

/// Every shipped scene and dataset file in `scenes/` loads (which draws the first sequence of
/// each family), and the TacBench datasets have the shape their benchmark tasks read.
#[test]
fn shipped_scenes_load() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    let mut names = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            sparsh_scene::DatasetSpec::load(&path)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            names.push(path.file_stem().unwrap().to_string_lossy().into_owned());
        }
    }
    for name in [
        "quickstart",
        "pretrain_small",
        "tacbench_force_slip",
        "tacbench_pose",
        "tacbench_texture",
        "tacbench_grasp",
    ] {
        assert!(names.iter().any(|n| n == name), "scenes/{name}.toml loads");
    }

    // Texture: twelve classes, each the family name of one DIGIT and one GelSight Mini table,
    // with held-out variants of each class in the test split.
    let spec = sparsh_scene::DatasetSpec::load(&dir.join("tacbench_texture.toml")).unwrap();
    assert!(
        spec.frame_count() <= 12_000,
        "{} frames",
        spec.frame_count()
    );
    let mut classes: std::collections::BTreeMap<String, (Vec<String>, usize)> = Default::default();
    for k in 0..spec.sequence_count() {
        let seq = spec.sequence(k).unwrap();
        assert!(matches!(seq.scene.indenter, Indenter::Texture(_)), "{k}");
        let class = classes.entry(seq.family).or_default();
        if !class.0.contains(&seq.scene.sensor.name) {
            class.0.push(seq.scene.sensor.name.clone());
        }
        class.1 += usize::from(seq.split == sparsh_scene::Split::Test);
    }
    assert!(classes.len() >= 12, "{} textures", classes.len());
    for (name, (sensors, tests)) in &classes {
        assert_eq!(sensors, &["digit", "gelsight_mini"], "{name}");
        assert!(*tests > 0, "{name} has test sequences");
    }

    // Grasp: one DIGIT family of press-and-drag sequences with held-out shapes.
    let spec = sparsh_scene::DatasetSpec::load(&dir.join("tacbench_grasp.toml")).unwrap();
    assert!((500..=700).contains(&spec.sequence_count()));
    let splits: Vec<_> = (0..spec.sequence_count())
        .map(|k| spec.sequence(k).unwrap().split)
        .collect();
    assert!(splits.contains(&sparsh_scene::Split::Test));
    assert!(splits.contains(&sparsh_scene::Split::Train));
}

#[test]
fn overrides_and_defaults_apply() {
    let scene = parse(BASE).unwrap();
    assert_eq!((scene.sensor.width_px, scene.sensor.height_px), (64, 48));
    assert_eq!(scene.sensor.mm_per_px, 0.0532, "preset value kept");
    assert_eq!(scene.gel.youngs_modulus_kpa, 200.0);
    assert_eq!(scene.gel.poisson_ratio, 0.48, "default");
    assert_eq!(scene.output.fields.len(), 8);
}

#[test]
fn keyframes_interpolate_linearly_at_the_frame_rate() {
    let frames = parse(BASE).unwrap().frames();
    assert_eq!(frames.len(), 120);
    // Frame 60 is at t = 1 s, halfway between z = 0.5 and z = −1.
    assert!((frames[60].time_s - 1.0).abs() < 1e-12);
    assert!((frames[60].pose.position_mm.z + 0.25).abs() < 1e-12);
}

#[test]
fn malformed_toml_gives_line_and_column() {
    let text = BASE.replace("radius_mm = 5.0", "radius_mm = = 5.0");
    let line = error_of(&text);
    assert!(line.starts_with("scenes/test.toml:11:"), "{line}");
}

#[test]
fn unknown_key_is_named() {
    let text = BASE.replace("radius_mm = 5.0", "radius_mm = 5.0\nradios = 2");
    let line = error_of(&text);
    assert!(line.contains("radios"), "{line}");
    assert!(line.starts_with("scenes/test.toml:12:"), "{line}");
}

#[test]
fn out_of_range_materials_are_rejected() {
    for (key, bad, field) in [
        (
            "youngs_modulus_kpa = 200.0",
            "youngs_modulus_kpa = 0.0",
            "gel.youngs_modulus_kpa",
        ),
        (
            "youngs_modulus_kpa = 200.0",
            "youngs_modulus_kpa = -5.0",
            "gel.youngs_modulus_kpa",
        ),
        (
            "youngs_modulus_kpa = 200.0",
            "thickness_mm = 0.0",
            "gel.thickness_mm",
        ),
        (
            "youngs_modulus_kpa = 200.0",
            "poisson_ratio = 0.51",
            "gel.poisson_ratio",
        ),
        (
            "youngs_modulus_kpa = 200.0",
            "poisson_ratio = -1.0",
            "gel.poisson_ratio",
        ),
    ] {
        let line = error_of(&BASE.replace(key, bad));
        assert!(line.contains(field), "{bad}: {line}");
    }
    let incompressible = BASE.replace("youngs_modulus_kpa = 200.0", "poisson_ratio = 0.5");
    assert!(parse(&incompressible).is_ok(), "ν = 0.5 is allowed");
}

#[test]
fn shape_keys_must_fit_the_shape() {
    let line = error_of(&BASE.replace("radius_mm = 5.0", "half_angle_deg = 30.0"));
    assert!(line.contains("indenter.half_angle_deg"), "{line}");
    let line = error_of(&BASE.replace("shape = \"sphere\"", "shape = \"cone\""));
    assert!(line.contains("indenter.radius_mm"), "{line}");
}

#[test]
fn unknown_preset_lists_the_known_ones() {
    let line = error_of(&BASE.replace("\"digit\"", "\"digits\""));
    assert!(
        line.contains("sensor.preset") && line.contains("gelsight_mini"),
        "{line}"
    );
}

#[test]
fn markers_can_be_removed_but_not_added() {
    let gs = BASE.replace("\"digit\"", "\"gelsight2017\"");
    assert!(parse(&gs).unwrap().sensor.markers.is_some());
    let plain = gs.replace("height_px = 48", "height_px = 48\nmarkers = false");
    assert!(parse(&plain).unwrap().sensor.markers.is_none());
    let line = error_of(&BASE.replace("height_px = 48", "height_px = 48\nmarkers = true"));
    assert!(
        line.contains("sensor.markers") && line.contains("digit"),
        "{line}"
    );
}

#[test]
fn trajectory_times_must_increase() {
    let line = error_of(&BASE.replace("time_s = 2.0", "time_s = 0.0"));
    assert!(line.contains("trajectory[1].time_s"), "{line}");
}

#[test]
fn trajectory_longer_than_a_scene_may_render_is_named() {
    // 60 fps (the DIGIT preset) × 20 000 s = 1.2 million frames: a mistyped 20.0.
    let line = error_of(&BASE.replace("time_s = 2.0", "time_s = 20000.0"));
    assert!(line.contains("trajectory[1].time_s"), "{line}");
    assert!(line.contains("1200000 frames"), "{line}");
    let longest = sparsh_scene::MAX_FRAMES as f64 / 60.0;
    let scene = parse(&BASE.replace("time_s = 2.0", &format!("time_s = {longest:?}")))
        .expect("a trajectory of exactly the limit loads");
    assert_eq!(scene.frames().len(), sparsh_scene::MAX_FRAMES);
}

fn mesh_scene(dir: &Path, file: &str) -> (PathBuf, String) {
    let text = BASE.replace(
        "shape = \"sphere\"\nradius_mm = 5.0",
        &format!("shape = \"mesh\"\nmesh = \"{file}\"\nunits = \"cm\""),
    );
    (dir.join("scene.toml"), text)
}

/// A unit tetrahedron (in the file's units) with its tip at z = 0.
const TETRA: [[f32; 3]; 4] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 1.0],
    [0.0, 1.0, 1.0],
    [-1.0, -1.0, 1.0],
];
const TETRA_FACES: [[u32; 3]; 4] = [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]];

fn mesh_extent_mm(scene: &Scene) -> f32 {
    match &scene.indenter {
        Indenter::Mesh(m) => m.mesh.vertices.iter().map(|v| v.z).fold(0.0, f32::max),
        other => panic!("expected a mesh, got {other:?}"),
    }
}

#[test]
fn obj_mesh_loads_in_its_units() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = TriMesh {
        vertices: TETRA.iter().map(|v| Vec3::from_array(*v)).collect(),
        triangles: TETRA_FACES.to_vec(),
    };
    std::fs::write(dir.path().join("tetra.obj"), mesh.to_obj()).unwrap();
    let (path, text) = mesh_scene(dir.path(), "tetra.obj");
    let scene = Scene::parse(&path, text).expect("OBJ loads");
    assert_eq!(mesh_extent_mm(&scene), 10.0, "1 cm tall");
}

/// Writes a binary glTF with one triangle mesh.
fn write_glb(path: &Path, vertices: &[[f32; 3]], faces: &[[u32; 3]]) {
    let mesh = TriMesh {
        vertices: vertices.iter().map(|v| Vec3::from_array(*v)).collect(),
        triangles: faces.to_vec(),
    };
    std::fs::write(path, mesh.to_glb()).unwrap();
}

#[test]
fn glb_mesh_loads_in_its_units() {
    let dir = tempfile::tempdir().unwrap();
    write_glb(&dir.path().join("tetra.glb"), &TETRA, &TETRA_FACES);
    let (path, text) = mesh_scene(dir.path(), "tetra.glb");
    let scene = Scene::parse(&path, text).expect("GLB loads");
    assert_eq!(mesh_extent_mm(&scene), 10.0, "1 cm tall");
}

#[test]
fn missing_mesh_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (path, text) = mesh_scene(dir.path(), "nowhere.obj");
    let err = Scene::parse(&path, text).unwrap_err().to_string();
    assert!(
        err.contains("nowhere.obj") && err.contains("does not exist"),
        "{err}"
    );
}

#[test]
fn mesh_with_nan_vertex_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let mut vertices = TETRA;
    vertices[2][1] = f32::NAN;
    write_glb(&dir.path().join("bad.glb"), &vertices, &TETRA_FACES);
    let (path, text) = mesh_scene(dir.path(), "bad.glb");
    let err = Scene::parse(&path, text).unwrap_err().to_string();
    assert!(err.contains("bad.glb") && err.contains("vertex 2"), "{err}");
}

#[test]
fn mesh_of_zero_area_triangles_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let obj = "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n";
    std::fs::write(dir.path().join("flat.obj"), obj).unwrap();
    let (path, text) = mesh_scene(dir.path(), "flat.obj");
    let err = Scene::parse(&path, text).unwrap_err().to_string();
    assert!(
        err.contains("flat.obj") && err.contains("non-zero area"),
        "{err}"
    );
}

#[test]
fn meshes_round_trip_through_obj_and_glb() {
    let dir = tempfile::tempdir().unwrap();
    let sphere = TriMesh::uv_sphere(2.5, 12, 18);
    for name in ["s.obj", "s.glb"] {
        let path = dir.path().join(name);
        let bytes = if name.ends_with("obj") {
            sphere.to_obj().into_bytes()
        } else {
            sphere.to_glb()
        };
        std::fs::write(&path, bytes).unwrap();
        let back = TriMesh::load(&path, sparsh_scene::LengthUnit::Mm, 1.0).unwrap();
        // Readers may renumber vertices: compare the triangles as corner positions, in order.
        let corners = |m: &TriMesh| -> Vec<[f32; 9]> {
            let mut tris: Vec<[f32; 9]> = m
                .triangles
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|i| m.vertices[i as usize]);
                    [a.x, a.y, a.z, b.x, b.y, b.z, c.x, c.y, c.z]
                })
                .collect();
            tris.sort_by(|p, q| p.partial_cmp(q).unwrap());
            tris
        };
        let (got, want) = (corners(&back), corners(&sphere));
        assert_eq!(got.len(), want.len(), "{name}");
        for (a, b) in got.iter().zip(&want) {
            assert!(
                a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5),
                "{name}: {a:?} vs {b:?}"
            );
        }
    }
}

#[test]
fn mechanics_grid_settings_are_checked() {
    let line = error_of(&BASE.replace("seed = 3", "seed = 3\nmechanics_stride = 5"));
    assert!(
        line.contains("mechanics_stride") && line.contains("64×48"),
        "{line}"
    );
    let line = error_of(&BASE.replace("seed = 3", "seed = 3\nmechanics_margin_mm = -1.0"));
    assert!(line.contains("mechanics_margin_mm"), "{line}");
    let scene = parse(&BASE.replace(
        "seed = 3",
        "seed = 3\nmechanics_stride = 4\nmechanics_margin_mm = 0.5",
    ))
    .unwrap();
    // 0.5 mm over cells of 4 × 0.0532 mm rounds up to 3 cells a side.
    assert_eq!(scene.mechanics_margin_cells(), 3);
    let grid = scene.mechanics_grid();
    assert_eq!((grid.nx, grid.ny), (16 + 6, 12 + 6));
}

/// Every shipped preset is a scene's valid sensor, and each resolution mode of a sensor views the
/// same patch of gel (pitch × pixels equal across modes).
#[test]
fn every_preset_resolves_and_modes_share_the_view() {
    for (name, _) in sparsh_scene::PRESETS {
        let scene = parse(&BASE.replace("\"digit\"", &format!("\"{name}\"")))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(scene.sensor.name, name);
        let preset = sparsh_scene::SensorConfig::preset(name).unwrap();
        if let Some(m) = preset.markers {
            let view_x = preset.width_px as f64 * preset.mm_per_px;
            let view_y = preset.height_px as f64 * preset.mm_per_px;
            assert!(
                (m.cols as f64 - 1.0) * m.pitch_mm < view_x,
                "{name}: markers fit the view"
            );
            assert!(
                (m.rows as f64 - 1.0) * m.pitch_mm < view_y,
                "{name}: markers fit the view"
            );
        }
    }
    for (qvga, vga) in [
        ("digit", "digit_vga"),
        ("gelsight_mini", "gelsight_mini_vga"),
    ] {
        let a = sparsh_scene::SensorConfig::preset(qvga).unwrap();
        let b = sparsh_scene::SensorConfig::preset(vga).unwrap();
        assert_eq!((a.width_px * 2, a.height_px * 2), (b.width_px, b.height_px));
        assert!(
            (a.mm_per_px - 2.0 * b.mm_per_px).abs() < 1e-12,
            "{qvga}/{vga}"
        );
        assert_eq!(a.lights, b.lights);
    }
}

#[test]
fn auto_solver_keys_are_checked() {
    let auto = |extra: &str| BASE.replace("seed = 3", &format!("seed = 3\n{extra}"));
    // A named solver reads the tolerance for its validity check; escalation needs `auto`.
    let named = Scene::parse(Path::new("t.toml"), auto("tolerance = 0.05")).unwrap();
    assert_eq!(
        (named.tolerance, named.validity),
        (0.05, ValidityPolicy::Warn)
    );
    let line = error_of(&auto("validity = \"escalate\""));
    assert!(
        line.contains("validity") && line.contains("auto") && !line.contains('\n'),
        "{line}"
    );
    let line = error_of(&auto("validity = \"sometimes\""));
    assert!(
        line.contains(":3:") && line.contains("`sometimes`") && line.contains("escalate"),
        "{line}"
    );
    for bad in ["0.0", "1.5"] {
        let line = error_of(&auto(&format!("tolerance = {bad}")));
        assert!(
            line.contains("tolerance") && line.contains("(0, 1)"),
            "{line}"
        );
    }
    let line = error_of(&auto("solver = \"auto\"\nmechanics_stride = 2"));
    assert!(
        line.contains("mechanics_stride") && line.contains("auto"),
        "{line}"
    );
    for bad in ["0.0", "-0.1", "1.5", "nan"] {
        let line = error_of(&auto(&format!("solver = \"auto\"\ntolerance = {bad}")));
        assert!(line.contains("tolerance"), "{line}");
    }
    // Never touching the gel leaves nothing to choose for.
    let line = error_of(&auto("solver = \"auto\"").replace(
        "position_mm = [0.0, 0.0, -1.0]",
        "position_mm = [0.0, 0.0, 1.0]",
    ));
    assert!(
        line.contains("solver") && line.contains("never touches"),
        "{line}"
    );
    // Force control needs a sphere.
    let line = error_of(
        &auto("solver = \"auto\"")
            .replace(
                "shape = \"sphere\"\nradius_mm = 5.0",
                "shape = \"cone\"\nhalf_angle_deg = 60.0",
            )
            .replace(
                "position_mm = [0.0, 0.0, 0.5]",
                "position_mm = [0.0, 0.0, 0.5]\nnormal_force_n = 0.5",
            )
            .replace(
                "position_mm = [0.0, 0.0, -1.0]",
                "position_mm = [0.0, 0.0, -1.0]\nnormal_force_n = 1.0",
            ),
    );
    assert!(
        line.contains("normal_force_n") && line.contains("sphere"),
        "{line}"
    );
    // A named solver keeps its own stride and records no choice.
    let scene = parse(&auto("solver = \"layered\"\nmechanics_stride = 2")).unwrap();
    assert_eq!(
        (scene.solver, scene.mechanics_stride),
        (sparsh_scene::SolverKind::Layered, 2)
    );
    assert!(scene.auto.is_none());
}

#[test]
fn bad_optics_sections_are_named() {
    let line = error_of(&format!("{BASE}[optics]\nmodel = \"calibrated\"\n"));
    assert!(line.contains("optics.calibration"), "{line}");
    let line = error_of(&format!(
        "{BASE}[optics]\nmodel = \"calibrated\"\ncalibration = \"no/such/dir\"\n"
    ));
    assert!(
        line.contains("optics.calibration") && line.contains("map.json"),
        "{line}"
    );
    let line = error_of(&format!("{BASE}[optics]\nnoise_std = -1.0\n"));
    assert!(line.contains("optics.noise_std"), "{line}");
    let line = error_of(&format!("{BASE}[optics]\nshadow_steps = 0\n"));
    assert!(line.contains("optics.shadow_steps"), "{line}");
    let dark = BASE.replace("height_px = 48\n", "height_px = 48\nlights = []\n");
    let line = error_of(&format!("{dark}[optics]\nshadows = true\n"));
    assert!(
        line.contains("optics.shadows") && line.contains("no lights"),
        "{line}"
    );
    let line = error_of(&format!("{BASE}[optics]\nmodel = \"raytraced\"\n"));
    assert!(line.contains("raytraced"), "{line}");
}

/// A scene with more numeric fields than [`BASE`], for [`any_number_in_any_field_loads_or_is_named`].
const NUMERIC: &str = r#"
seed = 3
[sensor]
preset = "digit"
width_px = 64
height_px = 48
mm_per_px = 0.06
fps = 60.0
[gel]
youngs_modulus_kpa = 200.0
poisson_ratio = 0.48
thickness_mm = 3.0
friction = 0.8
[indenter]
shape = "sphere"
radius_mm = 5.0
[[trajectory]]
time_s = 0.0
position_mm = [0.0, 0.0, 0.5]
rotation_deg = [0.0, 0.0, 0.0]
[[trajectory]]
time_s = 2.0
position_mm = [0.0, 0.0, -1.0]
rotation_deg = [0.0, 0.0, 10.0]
[optics]
noise_std = 1.0
"#;

/// The numbers of [`NUMERIC`]: (line, byte range) of each literal.
fn numeric_sites() -> Vec<(usize, std::ops::Range<usize>)> {
    let mut sites = Vec::new();
    for (l, line) in NUMERIC.lines().enumerate() {
        let Some(eq) = line.find(" = ") else { continue };
        let rhs = eq + 3;
        let mut start = None;
        for (i, c) in line[rhs..].char_indices().map(|(i, c)| (i + rhs, c)) {
            let numeric = c.is_ascii_digit() || c == '.' || c == '-';
            match (start, numeric) {
                (None, true) => start = Some(i),
                (Some(s), false) => {
                    sites.push((l, s..i));
                    start = None;
                }
                _ => {}
            }
        }
        if let Some(s) = start {
            sites.push((l, s..line.len()));
        }
    }
    sites
}

/// A TOML literal for `value`: `nan`, `inf` and `-inf` are TOML floats.
fn toml_number(value: f64) -> String {
    if value.is_nan() {
        "nan".into()
    } else if value.is_infinite() {
        if value > 0.0 { "inf" } else { "-inf" }.into()
    } else {
        format!("{value:?}")
    }
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 256,
        rng_seed: RngSeed::Fixed(7),
        ..ProptestConfig::default()
    })]

    /// Whatever number stands in whatever numeric field, the scene either loads or is refused
    /// with one line naming the file, never a panic; a non-finite number never loads.
    #[test]
    fn any_number_in_any_field_loads_or_is_named(
        site in 0usize..25,
        value in prop_oneof![
            Just(f64::NAN),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            Just(-0.0),
            Just(0.0),
            -1e6f64..1e6,
            1e-9f64..1.0,
        ],
        integral in any::<bool>(),
    ) {
        let sites = numeric_sites();
        prop_assert_eq!(sites.len(), 25);
        let (line, range) = sites[site].clone();
        let literal = if integral && value.is_finite() {
            format!("{}", value.trunc() as i64)
        } else {
            toml_number(value)
        };
        let text: Vec<String> = NUMERIC
            .lines()
            .enumerate()
            .map(|(l, s)| {
                if l == line {
                    format!("{}{}{}", &s[..range.start], literal, &s[range.end..])
                } else {
                    s.to_string()
                }
            })
            .collect();
        match parse(&text.join("\n")) {
            Ok(_) => prop_assert!(
                value.is_finite(),
                "{} loaded with {}",
                NUMERIC.lines().nth(line).unwrap(),
                literal
            ),
            Err(err) => {
                let message = err.to_string();
                prop_assert!(!message.contains('\n'), "{}", message);
                prop_assert!(message.starts_with("scenes/test.toml"), "{}", message);
            }
        }
    }
}
