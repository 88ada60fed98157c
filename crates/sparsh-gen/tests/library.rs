//! The pipeline called as a library: what the observer hears, the labels against their own
//! definitions recomputed from the written rows, and a resumed run that renders a damaged
//! sequence again.

use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use sparsh_gen::{GenerateOptions, Observer, Shard, generate, verify};

const SCENE: &str = r#"
seed = 3
[output]
fields = ["p"]

[[family]]
name = "press"
sequences = 4
frames_per_sequence = 12
solver = "geometric"
[family.sensor]
preset = "digit"
width_px = 80
height_px = 60
mm_per_px = 0.2
[[family.indenters]]
shape = "sphere"
radius_mm = [3.0, 5.0]
[family.motion]
kind = "press_slide"
depth_mm = [0.3, 0.8]
"#;

#[derive(Default)]
struct Counting {
    started: AtomicUsize,
    frames: AtomicUsize,
    notes: Mutex<Vec<String>>,
}

impl Observer for Counting {
    fn start(&self, frames: usize) {
        self.started.fetch_add(frames, Ordering::Relaxed);
    }
    fn frame_done(&self) {
        self.frames.fetch_add(1, Ordering::Relaxed);
    }
    fn note(&self, line: &str) {
        self.notes.lock().unwrap().push(line.to_string());
    }
}

fn rows(dir: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(dir.join("labels.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn generate_verify_and_resume_as_a_library() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene.toml");
    std::fs::write(&scene, SCENE).unwrap();
    let out = tmp.path().join("ds");

    // two shards, each told its own frames
    for k in 0..2 {
        let seen = Counting::default();
        let options = GenerateOptions {
            shard: Some(Shard::new(k, 2).unwrap()),
            ..Default::default()
        };
        let report = generate(&scene, &out, options, None, &seen).unwrap();
        assert_eq!(report.frames, 24);
        assert_eq!(seen.started.load(Ordering::Relaxed), 24);
        assert_eq!(seen.frames.load(Ordering::Relaxed), 24);
        assert_eq!(
            report.complete,
            k == 1,
            "the last shard writes the manifest"
        );
    }
    let mut said = Vec::new();
    verify(&out, None, true, &mut |l| said.push(l)).unwrap();
    assert!(
        said.iter().any(|l| l.contains("files match the manifest")),
        "{said:?}"
    );

    // (JSON's decimal floats round-trip to within an ulp, hence the 1e-12)
    // each row's Δforce is its force minus the force 5 frames before (the first frame before
    // that), and its pose change the change since the previous row of its sequence
    let rows = rows(&out);
    assert_eq!(rows.len(), 48);
    let num = |r: &serde_json::Value, k: &str, c: usize| r[k][c].as_f64().unwrap();
    for (i, r) in rows.iter().enumerate() {
        let k = r["frame_in_sequence"].as_u64().unwrap() as usize;
        let before = &rows[i - k + k.saturating_sub(5)];
        let prev = &rows[i - k.min(1)];
        for c in 0..3 {
            let want = num(r, "force_n", c) - num(before, "force_n", c);
            assert!((num(r, "delta_force_n", c) - want).abs() < 1e-12, "row {i}");
        }
        let dx = num(&r["pose"], "position_mm", 0) - num(&prev["pose"], "position_mm", 0);
        assert!((num(r, "pose_change_se2", 0) - dx).abs() < 1e-12, "row {i}");
    }

    // a damaged frame is named to the observer and its sequence rendered again, byte-identical
    let frame = out.join("frames/000013.png");
    let original = std::fs::read(&frame).unwrap();
    std::fs::write(&frame, b"not a png").unwrap();
    let seen = Counting::default();
    let options = GenerateOptions {
        resume: true,
        ..Default::default()
    };
    let report = generate(&scene, &out, options, None, &seen).unwrap();
    assert_eq!(report.frames, 12);
    let notes = seen.notes.lock().unwrap();
    assert!(
        notes
            .iter()
            .any(|n| n.contains("000013.png") && n.contains("rendering sequence 1 again")),
        "{notes:?}"
    );
    assert_eq!(std::fs::read(&frame).unwrap(), original);
}
