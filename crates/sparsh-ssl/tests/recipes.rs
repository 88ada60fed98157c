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
    let _ = enc.init(&Device::flex());
}
