//! Named-channel OpenEXR files for ground-truth fields (ZIP-compressed, lossless).

use std::io::Cursor;
use std::path::Path;

use exr::prelude::*;
use sparsh_scene::Precision;

use crate::DataError;

/// Encodes `channels` (name, row-major samples of a `width × height` grid) as an EXR file in
/// memory. Scan lines are stored in increasing order so the bytes do not depend on threads.
pub fn write_exr_channels(
    width: usize,
    height: usize,
    channels: &[(&str, Vec<f32>)],
    precision: Precision,
) -> std::result::Result<Vec<u8>, String> {
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> = channels
        .iter()
        .map(|(name, data)| {
            let samples = match precision {
                Precision::F32 => FlatSamples::F32(data.clone()),
                Precision::F16 => {
                    FlatSamples::F16(data.iter().map(|&v| f16::from_f32(v)).collect())
                }
            };
            AnyChannel::new(*name, samples)
        })
        .collect();
    let encoding = Encoding {
        compression: Compression::ZIP16,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new(
        (width, height),
        LayerAttributes::named("fields"),
        encoding,
        AnyChannels::sort(list),
    );
    let mut bytes = Cursor::new(Vec::new());
    Image::from_layer(layer)
        .write()
        .to_buffered(&mut bytes)
        .map_err(|e| e.to_string())?;
    Ok(bytes.into_inner())
}

/// The most samples (width × height × channels) [`read_exr_channels`] accepts in a layer: eight
/// fields of the largest sensor (8192 × 8192 pixels), 2 GiB as f32.
pub const MAX_EXR_SAMPLES: usize = 1 << 29;

/// Reads every channel of the first layer of an EXR file as f32: (name, samples) sorted by name,
/// with the image size. A header whose layers hold more than [`MAX_EXR_SAMPLES`] samples is
/// refused before any sample is allocated.
pub fn read_exr_channels(path: &Path) -> std::result::Result<ExrChannels, DataError> {
    let bad = |message: String| DataError::Format {
        path: path.to_path_buf(),
        message,
    };
    let meta = MetaData::read_from_file(path, false).map_err(|e| bad(e.to_string()))?;
    for header in &meta.headers {
        let (w, h) = (header.layer_size.width(), header.layer_size.height());
        let channels = header.channels.list.len();
        let samples = w.checked_mul(h).and_then(|n| n.checked_mul(channels));
        if samples.is_none_or(|n| n > MAX_EXR_SAMPLES) {
            return Err(bad(format!(
                "{w}×{h} pixels × {channels} channels: more than the {MAX_EXR_SAMPLES} samples a \
                 field file may hold"
            )));
        }
    }
    let image = read_first_flat_layer_from_file(path).map_err(|e| bad(e.to_string()))?;
    let size = image.layer_data.size;
    let channels = image
        .layer_data
        .channel_data
        .list
        .iter()
        .map(|c| {
            let data: Vec<f32> = c.sample_data.values_as_f32().collect();
            (c.name.to_string(), data)
        })
        .collect();
    Ok(ExrChannels {
        width: size.0,
        height: size.1,
        channels,
    })
}

/// Channels of an EXR file.
#[derive(Debug, Clone, PartialEq)]
pub struct ExrChannels {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// (name, samples), sorted by name.
    pub channels: Vec<(String, Vec<f32>)>,
}

impl ExrChannels {
    /// The samples of channel `name`.
    pub fn get(&self, name: &str) -> Option<&[f32]> {
        self.channels
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, d)| d.as_slice())
    }
}
