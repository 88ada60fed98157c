//! Taxim calibration packs as pretraining data: small packs written here in Taxim's npz layout
//! (BGR images), and Taxim 1.4.1's real packs when `data/taxim/calib` holds them.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use image::{Rgb, RgbImage};
use npyz::WriterBuilder;
use sparsh_ssl::data::{AugmentConfig, Dataset, Sampler, Stacking, preprocess};

/// Landscape like the real packs (640×480), small.
const W: usize = 64;
const H: usize = 48;
const SIZE: [usize; 2] = [32, 24];
/// Preprocessed value of an unchanged pixel: 0.5 stored as 8 bits (the official rounding).
const GREY: f32 = 127.0 / 255.0;

/// The no-contact frame: a gradient, so that every channel differs across the image.
fn f0() -> RgbImage {
    RgbImage::from_fn(W as u32, H as u32, |x, y| {
        Rgb([60 + x as u8, 60 + y as u8, 30 + (x + y) as u8 / 2])
    })
}

/// Frame `k` of the pack: f0 with the red channel raised by 100 in a 16×12 patch in the
/// top-left corner (frame 0) or the top-right corner (frame 1); frame 2 is f0 itself.
fn frame(k: usize) -> RgbImage {
    let mut img = f0();
    for y in 0..12 {
        for x in 0..16 {
            let x = if k == 0 { x } else { W as u32 - 1 - x };
            if k < 2 {
                img.get_pixel_mut(x, y).0[0] += 100;
            }
        }
    }
    img
}

fn bgr(img: &RgbImage) -> Vec<u8> {
    img.pixels()
        .flat_map(|p| [p.0[2], p.0[1], p.0[0]])
        .collect()
}

/// Writes a pack in Taxim's layout with `n` frames and the given `imgs` shape.
fn write_pack(path: &Path, n: usize, imgs_shape: [u64; 4]) {
    let mut npz = npyz::npz::NpzWriter::create(path).unwrap();
    let opts = || npyz::zip::write::FileOptions::default();
    let mut w = npz
        .array::<u8>("f0", opts())
        .unwrap()
        .default_dtype()
        .shape(&[H as u64, W as u64, 3])
        .begin_nd()
        .unwrap();
    w.extend(bgr(&f0())).unwrap();
    w.finish().unwrap();
    let mut w = npz
        .array::<u8>("imgs", opts())
        .unwrap()
        .default_dtype()
        .shape(&imgs_shape)
        .begin_nd()
        .unwrap();
    w.extend((0..n).flat_map(|k| bgr(&frame(k)))).unwrap();
    w.finish().unwrap();
    let mut w = npz
        .array::<f64>("touch_center", opts())
        .unwrap()
        .default_dtype()
        .shape(&[n as u64, 2])
        .begin_nd()
        .unwrap();
    w.extend((0..n).flat_map(|_| [20.0, 10.0])).unwrap();
    w.finish().unwrap();
    let mut w = npz
        .array::<f64>("touch_radius", opts())
        .unwrap()
        .default_dtype()
        .shape(&[n as u64])
        .begin_nd()
        .unwrap();
    w.extend((0..n).map(|_| 6.0)).unwrap();
    w.finish().unwrap();
}

/// A directory `gelsight/` holding a 3-frame `dataPack.npz`.
fn pack_dir(tmp: &Path) -> PathBuf {
    let dir = tmp.join("gelsight");
    std::fs::create_dir_all(&dir).unwrap();
    write_pack(&dir.join("dataPack.npz"), 3, [3, H as u64, W as u64, 3]);
    dir
}

fn one_line(e: String, needles: &[&str]) {
    for needle in needles {
        assert!(
            e.contains(needle) && !e.contains('\n'),
            "`{e}` should name `{needle}`"
        );
    }
}

#[test]
fn each_pack_frame_is_an_unlabelled_sequence_seen_from_rest() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = pack_dir(tmp.path());
    let d = Dataset::load(&dir, SIZE).unwrap();
    assert_eq!(d.sequences.len(), 3);
    assert_eq!(d.num_frames(), 3);
    let [h, w] = SIZE;
    for s in &d.sequences {
        assert!(s.forces.is_none());
        let rest = s.rest_frame.as_ref().unwrap();
        assert_eq!(rest.len(), 3 * h * w);
        assert!(rest.iter().all(|&v| v == GREY));
    }
    // the frame equal to f0 is unchanged everywhere
    assert!(
        d.sequences[2].frames[0]
            .decoded()
            .unwrap()
            .iter()
            .all(|&v| v == GREY)
    );
    // frame 0's red patch in the landscape top-left corner (16×12 pixels) lands, turned
    // clockwise as the official code turns frames, in the portrait top-right corner (12 wide,
    // 16 high; 6×8 after halving): red (100/255 + 0.5) stored as 8 bits, green and blue
    // unchanged, so the pack's BGR was read as BGR
    let f = d.sequences[0].frames[0].decoded().unwrap();
    let at = |c: usize, y: usize, x: usize| f[(c * h + y) * w + x];
    assert_eq!(at(0, 2, w - 3), 227.0 / 255.0);
    assert_eq!(at(1, 2, w - 3), GREY);
    assert_eq!(at(2, 2, w - 3), GREY);
    assert_eq!(at(0, h - 4, 2), GREY);
    // frame 1's patch (top-right corner) lands bottom-right
    assert_eq!(
        d.sequences[1].frames[0].decoded().unwrap()[(h - 3) * w + w - 3],
        227.0 / 255.0
    );

    // I_t ⊕ I_{t−5} at t = 0: the frame, then the rest frame
    let data = Arc::new(d);
    let sampler = Sampler::new(data.clone(), Stacking::Channels(vec![0, 5])).unwrap();
    assert_eq!(sampler.samples, vec![(0, 0), (1, 0), (2, 0)]);
    let b = sampler.batch(&[0], &AugmentConfig::none(), 0, 0).unwrap();
    assert_eq!(b.shape, [1, 1, 6, h, w]);
    assert!(b.forces.is_none());
    let expected = preprocess(&frame(0), &f0(), SIZE).unwrap();
    assert_eq!(&b.values[..3 * h * w], &expected[..]);
    assert!(b.values[3 * h * w..].iter().all(|&v| v == GREY));
    // V-JEPA clips [t, t−2, t−4, t−6]: the frame, then three rest frames
    let sampler = Sampler::new(data, Stacking::Frames(vec![0, 2, 4, 6])).unwrap();
    assert_eq!(sampler.samples.len(), 3);
    let b = sampler.batch(&[1], &AugmentConfig::none(), 0, 0).unwrap();
    assert_eq!(b.shape, [1, 4, 3, h, w]);
    let expected = preprocess(&frame(1), &f0(), SIZE).unwrap();
    assert_eq!(&b.values[..3 * h * w], &expected[..]);
    assert!(b.values[3 * h * w..].iter().all(|&v| v == GREY));
}

#[test]
fn the_pack_file_and_its_directory_load_alike() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = pack_dir(tmp.path());
    let by_dir = Dataset::load(&dir, SIZE).unwrap();
    let by_file = Dataset::load(&dir.join("dataPack.npz"), SIZE).unwrap();
    assert_eq!(by_dir.sequences.len(), by_file.sequences.len());
    for (a, b) in by_dir.sequences.iter().zip(&by_file.sequences) {
        let decoded = |s: &sparsh_ssl::data::Sequence| -> Vec<Vec<f32>> {
            s.frames
                .iter()
                .map(|f| f.decoded().unwrap().to_vec())
                .collect()
        };
        assert_eq!(decoded(a), decoded(b));
        assert_eq!(a.rest_frame, b.rest_frame);
    }
    // any file name ending in .npz is read as a pack
    let renamed = tmp.path().join("mini.npz");
    std::fs::copy(dir.join("dataPack.npz"), &renamed).unwrap();
    assert_eq!(Dataset::load(&renamed, SIZE).unwrap().sequences.len(), 3);
}

#[test]
fn bad_packs_and_paths_are_one_line_errors() {
    let tmp = tempfile::tempdir().unwrap();
    // imgs portrait while f0 is landscape
    let bad = tmp.path().join("bad");
    std::fs::create_dir_all(&bad).unwrap();
    write_pack(&bad.join("dataPack.npz"), 3, [3, W as u64, H as u64, 3]);
    one_line(
        Dataset::load(&bad, SIZE).unwrap_err().to_string(),
        &["bad/dataPack.npz", "imgs", "like f0"],
    );
    // a pack without frames
    let empty = tmp.path().join("empty.npz");
    write_pack(&empty, 0, [0, H as u64, W as u64, 3]);
    one_line(
        Dataset::load(&empty, SIZE).unwrap_err().to_string(),
        &["empty.npz", "imgs", "no frames"],
    );
    // a file that is not an npz archive
    let text = tmp.path().join("notes.npz");
    std::fs::write(&text, "not a zip").unwrap();
    one_line(
        Dataset::load(&text, SIZE).unwrap_err().to_string(),
        &["notes.npz", "npz"],
    );
    // a file that is neither a directory nor an npz
    let other = tmp.path().join("frames.txt");
    std::fs::write(&other, "x").unwrap();
    one_line(
        Dataset::load(&other, SIZE).unwrap_err().to_string(),
        &["frames.txt", "neither a dataset directory nor a Taxim pack"],
    );
    // a path that does not exist
    one_line(
        Dataset::load(&tmp.path().join("missing"), SIZE)
            .unwrap_err()
            .to_string(),
        &["missing", "no such file or directory"],
    );
}

/// Taxim 1.4.1's real packs (fetched by `.ci/run`, see the README): 48 GelSight and 24
/// GelSight Mini presses, each visible against the rest frame. Skips with a message when the
/// packs are absent, unless `SPARSH_REQUIRE_TAXIM` is set (CI).
#[test]
fn real_taxim_packs_load_as_one_sequence_per_press() {
    let calib = match std::env::var_os("SPARSH_TAXIM_CALIB") {
        Some(dir) => PathBuf::from(dir),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data/taxim/calib"),
    };
    for (sensor, presses) in [("gelsight", 48), ("gelsight_mini", 24)] {
        let dir = calib.join(sensor);
        if !dir.join("dataPack.npz").is_file() {
            assert!(
                std::env::var_os("SPARSH_REQUIRE_TAXIM").is_none(),
                "{} is missing and SPARSH_REQUIRE_TAXIM is set",
                dir.display()
            );
            eprintln!(
                "SKIPPED: {}/dataPack.npz not found (see README \"Optics against real images\", \
                 or set SPARSH_TAXIM_CALIB)",
                dir.display()
            );
            continue;
        }
        let d = Dataset::load(&dir, SIZE).unwrap();
        assert_eq!(d.sequences.len(), presses, "{sensor}");
        for (k, s) in d.sequences.iter().enumerate() {
            let change = s.frames[0]
                .decoded()
                .unwrap()
                .iter()
                .map(|v| (v - GREY).abs())
                .fold(0.0, f32::max);
            assert!(change > 0.05, "{sensor} press {k}: largest change {change}");
        }
    }
}
