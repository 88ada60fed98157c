//! The shipped CPU recipes parse, validate and build their models.

use std::path::Path;

use burn::prelude::*;
use sparsh_ssl::recipe::{ObjectiveKind, Recipe};

#[test]
fn shipped_recipes_are_valid() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/ssl");
    let mut seen = Vec::new();
    for name in ["mae", "dino", "ijepa", "vjepa"] {
        let r = Recipe::load(&dir.join(format!("{name}_tiny_cpu.toml"))).unwrap();
        let enc = r.encoder_config().unwrap();
        assert_eq!(enc.img_size, [96, 72]);
        let expect_chans = if r.objective == ObjectiveKind::Vjepa {
            3
        } else {
            6
        };
        assert_eq!(enc.in_chans, expect_chans);
        seen.push(r.objective);
    }
    assert_eq!(
        seen,
        [
            ObjectiveKind::Mae,
            ObjectiveKind::Dino,
            ObjectiveKind::Ijepa,
            ObjectiveKind::Vjepa
        ]
    );
    // the V-JEPA recipe sees 4-frame clips as 2 tubelets
    let v = Recipe::load(&dir.join("vjepa_tiny_cpu.toml")).unwrap();
    let enc = v.encoder_config().unwrap();
    assert_eq!((enc.num_frames, enc.tubelet_size, enc.grid()[0]), (4, 2, 2));
    let device = Device::flex();
    let _ = sparsh_ssl::device::seeded_module(&device, 0, || enc.init(&device));
}

/// The paper's ViT-base recipes (assets/ssl/*_base.toml) carry its numbers and each takes one
/// training step on the CPU (the batch cut to 2 samples; everything else as shipped).
#[test]
fn paper_base_recipes_take_a_step() {
    use sparsh_ssl::data::HostBatch;
    use sparsh_ssl::rng::Rng;
    use sparsh_ssl::train::{Trainee, optimizer};

    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/ssl");
    for (name, batch, lr, registers) in [
        ("mae", 100, 1e-4, 0),
        ("dino", 150, 1e-4, 1),
        ("dinov2", 150, 2e-3, 1),
        ("ijepa", 150, 6.25e-4, 0),
        ("vjepa", 150, 6.25e-4, 0),
    ] {
        let mut recipe = Recipe::load(&dir.join(format!("{name}_base.toml"))).unwrap();
        let enc = recipe.encoder_config().unwrap();
        assert_eq!(
            (enc.embed_dim, enc.depth, enc.num_heads, enc.patch_size),
            (768, 12, 12, 16),
            "{name}: ViT-B/16"
        );
        assert_eq!(
            enc.img_size,
            [320, 240],
            "{name}: the official input, H × W"
        );
        assert_eq!(enc.num_registers, registers, "{name}");
        // layer scale in every block, as the official encoders (DINOv2 initialises it at 1e-5)
        let gamma = if name == "dinov2" { 1e-5 } else { 1.0 };
        assert_eq!(enc.layer_scale, Some(gamma), "{name}");
        let o = &recipe.optim;
        assert_eq!((o.batch_size, o.lr), (batch, lr), "{name}");
        // 150 epochs of 460k frames, the first 30 warming up
        let per_epoch = 460_000usize.div_ceil(batch);
        assert_eq!(
            (o.steps, o.warmup_steps),
            (150 * per_epoch, 30 * per_epoch),
            "{name}"
        );
        recipe.optim.batch_size = 2;
        recipe.optim.micro_batches = 1;
        let device = Device::flex().autodiff();
        let model = Trainee::init(&recipe, &device).unwrap();
        let mut optim = optimizer(&recipe);
        let shape = [2, enc.num_frames, enc.in_chans, 320, 240];
        let mut rng = Rng::new(5);
        let values = (0..shape.iter().product::<usize>())
            .map(|_| rng.range_f64(0.4, 0.6) as f32)
            .collect();
        let batch = HostBatch {
            step: 0,
            values,
            shape,
            forces: None,
        };
        let (_, loss) =
            model.train_step(&recipe, &mut optim, &batch, std::slice::from_ref(&device));
        assert!(loss.is_finite(), "{name}: loss {loss}");
    }
}

/// The 160×120 I-JEPA recipe is the 96×72 one with only its input changed: the same encoder,
/// masks, predictor, schedule and optimizer, so the two compare resolution alone.
#[test]
fn the_160_recipe_differs_from_the_cpu_recipe_in_its_input_only() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/ssl");
    let read = |name: &str| -> toml::Table {
        let mut t: toml::Table = std::fs::read_to_string(dir.join(name))
            .unwrap()
            .parse()
            .unwrap();
        let enc = t.get_mut("encoder").unwrap().as_table_mut().unwrap();
        enc.remove("img_size").expect("img_size given");
        t
    };
    assert_eq!(read("ijepa_tiny_160_cpu.toml"), read("ijepa_tiny_cpu.toml"));
    let r = Recipe::load(&dir.join("ijepa_tiny_160_cpu.toml")).unwrap();
    let enc = r.encoder_config().unwrap();
    assert_eq!((enc.img_size, enc.grid()), ([160, 120], [1, 20, 15]));
}
