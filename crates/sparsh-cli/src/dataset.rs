//! `sparsh render` and `sparsh generate`: the simulator joined to the dataset writer.

use std::path::Path;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use sparsh_contact::Fields;
use sparsh_data::{DatasetWriter, Label, Manifest, PoseLabel, encode_png, write_atomic};
use sparsh_scene::{FieldName, OutputSpec, Precision, Scene, SolverKind};
use sparsh_sim::{Frame, Simulator};

/// Renders frame `index` of `scene_path` to `out` (PNG) and optionally its fields to an EXR.
pub fn render(scene_path: &Path, index: usize, out: &Path, fields: Option<&Path>) -> Result<()> {
    let scene = Scene::load(scene_path)?;
    let mut sim = Simulator::new(scene)?;
    let count = sim.frame_count();
    if index >= count {
        bail!(
            "{}: --frame {index} is out of range: the scene has {count} frames",
            scene_path.display()
        );
    }
    let mut frame = None;
    for _ in 0..=index {
        frame = sim.next_frame().transpose()?;
    }
    let frame = frame.expect("index < frame count");
    let png = encode_png(&frame.image).map_err(anyhow::Error::msg)?;
    write_atomic(out, &png)?;
    if let Some(path) = fields {
        let spec = OutputSpec {
            fields: FieldName::ALL.to_vec(),
            ..sim.scene().output.clone()
        };
        write_atomic(path, &exr_bytes(&frame.fields, &spec)?)?;
    }
    Ok(())
}

/// Simulates every frame of `scene_path` into the dataset directory `out`.
pub fn generate(scene_path: &Path, out: &Path, force: bool) -> Result<()> {
    let scene = Scene::load(scene_path)?;
    let mut sim = Simulator::new(scene)?;
    let mut writer = DatasetWriter::create(out, force)?;
    writer.write_png("background.png", &sim.background())?;
    let count = sim.frame_count();
    let progress = ProgressBar::new(count as u64).with_style(
        ProgressStyle::with_template(
            "{elapsed_precise} {bar:40} {pos}/{len} frames, {per_sec}, eta {eta}",
        )
        .expect("valid template"),
    );
    while let Some(frame) = sim.next_frame() {
        let frame = frame?;
        let name = format!("{:06}", frame.target.index);
        let output = &sim.scene().output;
        if output.frames {
            writer.write_png(&format!("frames/{name}.png"), &frame.image)?;
        }
        if !output.fields.is_empty() {
            writer.write_file(
                &format!("fields/{name}.exr"),
                &exr_bytes(&frame.fields, output)?,
            )?;
        }
        writer.push_label(&label(&frame));
        progress.inc(1);
    }
    progress.finish();
    let scene = sim.scene();
    writer
        .finish(manifest(scene, count))
        .with_context(|| format!("cannot finish the dataset in {}", out.display()))?;
    Ok(())
}

fn label(frame: &Frame) -> Label {
    Label {
        frame: frame.target.index,
        sequence: 0,
        frame_in_sequence: frame.target.index,
        time_s: frame.target.time_s,
        force_n: frame.fields.force_n,
        pose: PoseLabel {
            position_mm: frame.pose.position_mm.to_array(),
            rotation_deg: frame.pose.rotation_deg.to_array(),
        },
        slip_state: frame.fields.slip_state().name().to_string(),
        contact_area_mm2: frame.fields.contact_area_mm2(),
    }
}

fn manifest(scene: &Scene, frames: usize) -> Manifest {
    let mut notes = Vec::new();
    if scene.solver == SolverKind::Geometric {
        notes.push(
            "geometric rung: no tangential mechanics, so qx, qy, ux, uy and slip are zero".into(),
        );
    }
    Manifest {
        format: "sparsh-dataset/1".into(),
        sparsh_version: env!("CARGO_PKG_VERSION").into(),
        scene_file: scene
            .path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        scene: scene.source.clone(),
        seed: scene.seed,
        solver: format!("{:?}", scene.solver).to_lowercase(),
        frames,
        fields: scene
            .output
            .fields
            .iter()
            .map(|f| f.channel().to_string())
            .collect(),
        field_precision: match scene.output.field_precision {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
        }
        .into(),
        notes,
        files: Default::default(),
    }
}

/// The fields the output spec keeps, as an EXR file.
fn exr_bytes(fields: &Fields, output: &OutputSpec) -> Result<Vec<u8>> {
    let as_f32 = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    let mask = |v: &[bool]| {
        v.iter()
            .map(|&b| f32::from(u8::from(b)))
            .collect::<Vec<f32>>()
    };
    let channels: Vec<(&str, Vec<f32>)> = output
        .fields
        .iter()
        .map(|&f| {
            let data = match f {
                FieldName::P => as_f32(&fields.pressure_kpa),
                FieldName::Qx => as_f32(&fields.traction_x_kpa),
                FieldName::Qy => as_f32(&fields.traction_y_kpa),
                FieldName::Ux => as_f32(&fields.ux_mm),
                FieldName::Uy => as_f32(&fields.uy_mm),
                FieldName::Uz => as_f32(&fields.uz_mm),
                FieldName::Contact => mask(&fields.contact),
                FieldName::Slip => mask(&fields.slip),
            };
            (f.channel(), data)
        })
        .collect();
    sparsh_data::write_exr_channels(
        fields.grid.nx,
        fields.grid.ny,
        &channels,
        output.field_precision,
    )
    .map_err(anyhow::Error::msg)
}
