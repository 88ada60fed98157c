//! A one-block ViT encoder on 16×16 inputs: the smallest the safetensors loader can be given.

/// The encoder, randomly initialised.
pub fn tiny_encoder() -> sparsh_ssl::vit::Vit {
    let recipe = sparsh_ssl::recipe::Recipe::parse(
        "objective = \"mae\"\nseed = 1\n[encoder]\nimg_size = [16, 16]\npatch_size = 8\n\
         embed_dim = 8\ndepth = 1\nnum_heads = 2\n[mae]\ndecoder_dim = 8\ndecoder_depth = 1\n\
         decoder_heads = 2\n",
    )
    .unwrap();
    recipe
        .encoder_config()
        .unwrap()
        .init(&burn::prelude::Device::flex())
}
