//! Every benchmark config the project ships (`tacbench/*.toml`: TacBench runs, and the T1A
//! field-probe configs `fields_*.toml`) loads, and the recipes and scene files it names exist and
//! parse: a config whose command the docs give must not fail on a misspelt path after the data
//! has been generated.

use std::path::Path;

use sparsh_bench::fields::run::FieldProbeConfig;
use sparsh_bench::tacbench::config::BenchConfig;
use sparsh_ssl::recipe::Recipe;

#[test]
fn shipped_tacbench_configs_load_and_name_real_recipes_and_scenes() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tacbench");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    files.sort();
    assert!(files.len() >= 10, "found only {files:?}");
    for file in &files {
        if file
            .file_name()
            .unwrap()
            .to_string_lossy()
            .starts_with("fields_")
        {
            let cfg = FieldProbeConfig::load(file).unwrap_or_else(|e| panic!("{e}"));
            Recipe::load(&cfg.recipe).unwrap_or_else(|e| panic!("{}: recipe: {e}", file.display()));
            continue;
        }
        let cfg = BenchConfig::load(file).unwrap_or_else(|e| panic!("{e}"));
        let encoders = cfg.encoder.iter().enumerate();
        let draws = cfg.random.iter().enumerate();
        let recipes = (encoders.map(|(i, e)| (&e.recipe, format!("encoder[{i}].recipe"))))
            .chain(draws.map(|(i, r)| (&r.recipe, format!("random[{i}].recipe"))))
            .chain(
                cfg.baselines
                    .iter()
                    .map(|b| (&b.recipe, "baselines.recipe".into())),
            );
        for (path, field) in recipes {
            cfg.recipe(path, &field)
                .unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        }
        for (i, t) in cfg.task.iter().enumerate() {
            if let Some(scene) = &t.scene {
                sparsh_scene::DatasetSpec::load(scene)
                    .unwrap_or_else(|e| panic!("{}: task[{i}].scene: {e}", file.display()));
            }
        }
    }
}

/// The 160×120 config reads its encoder, its draws and its raw-patch probe at the recipe's
/// 160×120, a 20×15 grid of patch-8 tokens, where the 96×72 recipes have 12×9.
#[test]
fn the_160_config_reads_a_20_by_15_token_grid() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tacbench/well_posed_160_cpu.toml");
    let cfg = BenchConfig::load(&file).unwrap();
    let recipe = cfg
        .recipe(&cfg.encoder[0].recipe, "encoder[0].recipe")
        .unwrap();
    let enc = recipe.encoder_config().unwrap();
    assert_eq!(enc.img_size, [160, 120]);
    assert_eq!(enc.grid(), [1, 20, 15]);
    assert_eq!(cfg.random[0].recipe, cfg.encoder[0].recipe);
    assert_eq!(
        cfg.baselines.as_ref().unwrap().recipe,
        cfg.encoder[0].recipe
    );
}
