//! Encoders every benchmark draws or asks for: the random initialisation of a recipe under a
//! seed, and what to say of a pretrained encoder's missing weights file.

use std::path::Path;

use burn::prelude::*;
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::train::Trainee;
use sparsh_ssl::vit::Vit;

use crate::Error;

/// The randomly initialised encoder a run of `recipe` with `seed` starts from.
pub fn random_encoder(recipe: &Recipe, seed: u64) -> Result<Vit, Error> {
    let drawn = Recipe {
        seed,
        ..recipe.clone()
    };
    let device = Device::flex().autodiff();
    Ok(Trainee::init(&drawn, &device)?.encoder().clone())
}

/// What to say of an encoder file that does not exist: how to make it with its recipe.
pub(crate) fn missing_weights(weights: &Path, recipe: &Path) -> String {
    format!(
        "{}: no such file (pretrain it first: sparsh pretrain --config {} --data DATASET --out RUN, \
         then point weights at RUN/encoder.safetensors)",
        weights.display(),
        recipe.display()
    )
}
