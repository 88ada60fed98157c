//! Named-channel OpenEXR files for ground-truth fields (ZIP-compressed, lossless).

use std::io::Cursor;
use std::path::Path;

use exr::block::chunk::{Chunk, CompressedBlock, CompressedScanLineBlock};
use exr::block::writer::ChunksWriter;
use exr::image::write::layers::WritableLayers;
use exr::prelude::*;
use sparsh_scene::Precision;

use crate::DataError;

/// Scan lines per block of OpenEXR's ZIP compression (`ZIP16`).
const ZIP_LINES: usize = 16;

/// zlib level of the blocks: the fastest of zlib's levels, whose output is within a few per cent
/// of level 4's (exr's own) on fields.
const ZIP_LEVEL: u32 = 1;

/// Encodes `channels` (name, row-major samples of a `width × height` grid) as an EXR file in
/// memory: one layer named `fields`, channels sorted by name, ZIP compression in blocks of 16
/// scan lines stored in increasing order.
///
/// The blocks are compressed here rather than by exr's writer, with zlib-rs on the calling
/// thread: exr compresses with miniz at level 4 and, in parallel, builds a thread pool of every
/// core for each file. (The dataset writer calls this on a thread of its own, beside the
/// simulation; it must not wait on the rayon pool, whose workers may be waiting for it.) Each
/// block is OpenEXR's ZIP: the samples of each line, channel after channel, in little-endian
/// bytes; the bytes split into their even and odd halves; each byte replaced by its difference
/// from the one before plus 128; zlib (OpenEXR file format, "ZIP compression"). A block that
/// does not shrink is stored raw, as the format requires.
pub fn write_exr_channels(
    width: usize,
    height: usize,
    channels: &[(&str, Vec<f32>)],
    precision: Precision,
) -> std::result::Result<Vec<u8>, String> {
    if let Some((name, data)) = channels.iter().find(|(_, d)| d.len() != width * height) {
        return Err(format!(
            "channel {name} has {} samples, not {width}×{height}",
            data.len()
        ));
    }
    let sample_type = match precision {
        Precision::F32 => SampleType::F32,
        Precision::F16 => SampleType::F16,
    };
    // The header as exr's own writer makes it; the samples are not needed for that.
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> = channels
        .iter()
        .map(|(name, _)| {
            let samples = match precision {
                Precision::F32 => FlatSamples::F32(Vec::new()),
                Precision::F16 => FlatSamples::F16(Vec::new()),
            };
            AnyChannel::new(*name, samples)
        })
        .collect();
    let image = Image::from_layer(fields_layer(width, height, list));
    let headers = image.layer_data.infer_headers(&image.attributes);
    // Channel data in the header's (sorted) order.
    let sorted: Vec<&[f32]> = headers[0]
        .channels
        .list
        .iter()
        .map(|c| {
            let name = c.name.to_string();
            channels
                .iter()
                .find(|(n, _)| *n == name)
                .map(|(_, d)| d.as_slice())
                .expect("the header lists the given channels")
        })
        .collect();
    debug_assert!(
        headers[0]
            .channels
            .list
            .iter()
            .all(|c| c.sample_type == sample_type)
    );
    let blocks: Vec<Chunk> = (0..height.div_ceil(ZIP_LINES))
        .map(|b| {
            let lines = (b * ZIP_LINES)..((b + 1) * ZIP_LINES).min(height);
            let raw = block_bytes(width, lines, &sorted, precision);
            let packed = zip_block(&raw);
            Chunk {
                layer_index: 0,
                compressed_block: CompressedBlock::ScanLine(CompressedScanLineBlock {
                    y_coordinate: (b * ZIP_LINES) as i32,
                    compressed_pixels_le: if packed.len() < raw.len() {
                        packed
                    } else {
                        raw
                    },
                }),
            }
        })
        .collect();
    let mut bytes = Cursor::new(Vec::new());
    exr::block::write(&mut bytes, headers, true, |_, writer| {
        blocks
            .into_iter()
            .enumerate()
            .try_for_each(|(index, chunk)| writer.write_chunk(index, chunk))
    })
    .map_err(|e| e.to_string())?;
    Ok(bytes.into_inner())
}

/// The layer of a fields file: named `fields`, channels sorted by name, ZIP in blocks of 16
/// scan lines stored in increasing order.
fn fields_layer(
    width: usize,
    height: usize,
    channels: SmallVec<[AnyChannel<FlatSamples>; 4]>,
) -> Layer<AnyChannels<FlatSamples>> {
    let encoding = Encoding {
        compression: Compression::ZIP16,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    Layer::new(
        (width, height),
        LayerAttributes::named("fields"),
        encoding,
        AnyChannels::sort(channels),
    )
}

/// The uncompressed bytes of the scan lines `lines`: for each line, each channel's samples of
/// that line, little-endian.
fn block_bytes(
    width: usize,
    lines: std::ops::Range<usize>,
    channels: &[&[f32]],
    precision: Precision,
) -> Vec<u8> {
    let sample_bytes = match precision {
        Precision::F32 => 4,
        Precision::F16 => 2,
    };
    let mut raw = Vec::with_capacity(lines.len() * channels.len() * width * sample_bytes);
    for y in lines {
        for data in channels {
            let line = &data[y * width..(y + 1) * width];
            match precision {
                Precision::F32 => line
                    .iter()
                    .for_each(|v| raw.extend_from_slice(&v.to_le_bytes())),
                Precision::F16 => line
                    .iter()
                    .for_each(|&v| raw.extend_from_slice(&f16::from_f32(v).to_le_bytes())),
            }
        }
    }
    raw
}

/// OpenEXR's ZIP compression of one block's bytes: even/odd split, byte differences + 128,
/// zlib.
fn zip_block(raw: &[u8]) -> Vec<u8> {
    let half = raw.len().div_ceil(2);
    let mut split = vec![0u8; raw.len()];
    let (evens, odds) = split.split_at_mut(half);
    let pairs = raw.chunks_exact(2);
    if let [last] = pairs.remainder() {
        evens[half - 1] = *last;
    }
    for ((pair, even), odd) in pairs.zip(evens.iter_mut()).zip(odds.iter_mut()) {
        *even = pair[0];
        *odd = pair[1];
    }
    // Each byte's difference from the one before it in the split order (independent per byte,
    // so the loop vectorises).
    let coded: Vec<u8> = split
        .first()
        .copied()
        .into_iter()
        .chain(
            split
                .windows(2)
                .map(|w| w[1].wrapping_sub(w[0]).wrapping_add(128)),
        )
        .collect();
    let mut encoder = flate2::write::ZlibEncoder::new(
        Vec::with_capacity(raw.len() / 2),
        flate2::Compression::new(ZIP_LEVEL),
    );
    std::io::Write::write_all(&mut encoder, &coded).expect("writing to memory");
    encoder.finish().expect("writing to memory")
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

#[cfg(test)]
mod tests {
    use super::*;

    /// exr's own writer (miniz, its byte shuffling), the independent reference of the format.
    fn written_by_exr(
        width: usize,
        height: usize,
        channels: &[(&str, Vec<f32>)],
        precision: Precision,
    ) -> Vec<u8> {
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
        let mut bytes = Cursor::new(Vec::new());
        Image::from_layer(fields_layer(width, height, list))
            .write()
            .non_parallel()
            .to_buffered(&mut bytes)
            .unwrap();
        bytes.into_inner()
    }

    fn read(bytes: &[u8]) -> ExrChannels {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.exr");
        std::fs::write(&path, bytes).unwrap();
        read_exr_channels(&path).unwrap()
    }

    /// Fields of every kind a frame has: smooth (compresses), zero outside a patch, masks, and
    /// noise that does not compress (stored raw); 37 lines, so the last block is short.
    fn fields(width: usize, height: usize) -> Vec<(&'static str, Vec<f32>)> {
        let n = width * height;
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let noise: Vec<f32> = (0..n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
            })
            .collect();
        let smooth = (0..n)
            .map(|k| ((k % width) as f32 * 0.1).sin() * (k / width) as f32 * 1e-3)
            .collect();
        let patch = (0..n)
            .map(|k| {
                if (k % width) < 5 && k / width > 20 {
                    2.5
                } else {
                    0.0
                }
            })
            .collect();
        let mask = (0..n).map(|k| f32::from(u8::from(k % 3 == 0))).collect();
        // not in name order: the file lists them sorted
        vec![("uz", smooth), ("p", patch), ("slip", mask), ("qx", noise)]
    }

    #[test]
    fn fields_read_back_as_exr_itself_writes_them() {
        let (width, height) = (13, 37);
        let channels = fields(width, height);
        for precision in [Precision::F32, Precision::F16] {
            let ours = read(&write_exr_channels(width, height, &channels, precision).unwrap());
            let reference = read(&written_by_exr(width, height, &channels, precision));
            assert_eq!(ours, reference, "{precision:?}");
            assert_eq!((ours.width, ours.height), (width, height));
            let names: Vec<&str> = ours.channels.iter().map(|(n, _)| n.as_str()).collect();
            assert_eq!(names, ["p", "qx", "slip", "uz"]);
            if precision == Precision::F32 {
                for (name, data) in &channels {
                    assert_eq!(ours.get(name).unwrap(), data.as_slice(), "{name}");
                }
            }
        }
    }

    #[test]
    fn a_channel_of_the_wrong_length_is_refused() {
        let channels = [("p", vec![0.0; 12]), ("uz", vec![0.0; 11])];
        let err = write_exr_channels(4, 3, &channels, Precision::F32).unwrap_err();
        assert_eq!(err, "channel uz has 11 samples, not 4×3");
    }
}
