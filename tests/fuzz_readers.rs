//! Every reader of user files fed truncated, bit-flipped and edited copies of valid files (scene
//! and dataset files with their meshes, OBJ, glTF and GLB meshes, EXR fields, PNG frames, the
//! official Sparsh pickles, safetensors encoders). Each must accept the file or refuse it with
//! one line that starts with the file's path; never panic, hang or ask the allocator for more
//! than [`ALLOC_CAP`] bytes at once (this test binary's allocator refuses such a request, which
//! aborts the run). A fixed seed draws the same cases on every run; see docs/src/behaviour.md.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};

use image::{Rgb, RgbImage};
use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::{FileFailurePersistence, RngSeed};
use sparsh_scene::{DatasetSpec, LengthUnit, MeshIndenter, TriMesh};

#[path = "common/encoder.rs"]
mod encoder;
use encoder::tiny_encoder;

/// The largest single allocation any reader may make while reading one of these small files.
const ALLOC_CAP: usize = 1 << 30;

/// The system allocator, refusing any request above [`ALLOC_CAP`].
struct CappedAlloc;

// SAFETY: every call forwards to `System` unchanged, or returns null (allowed: an allocation
// failure) for a request above the cap.
unsafe impl GlobalAlloc for CappedAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() > ALLOC_CAP {
            return std::ptr::null_mut();
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if layout.size() > ALLOC_CAP {
            return std::ptr::null_mut();
        }
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > ALLOC_CAP {
            return std::ptr::null_mut();
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: CappedAlloc = CappedAlloc;

/// `cases` cases drawn from a fixed seed; a failing case is kept in
/// tests/fuzz_readers.proptest-regressions and tried first on later runs.
fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        rng_seed: RngSeed::Fixed(0x5eed_f122),
        failure_persistence: Some(Box::new(FileFailurePersistence::Direct(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../tests/fuzz_readers.proptest-regressions"
        )))),
        ..ProptestConfig::default()
    }
}

/// The checkout.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Checks a reader's verdict: accepting the file passes; refusing it must give one line that
/// starts with `dir`, the folder holding the file and any file it names (a scene's mesh).
fn check_refusal<T>(result: Result<T, String>, dir: &Path) -> Result<(), TestCaseError> {
    if let Err(message) = result {
        prop_assert!(!message.contains('\n'), "not one line: {message}");
        prop_assert!(
            message.starts_with(&dir.display().to_string()),
            "does not name the file: {message}"
        );
    }
    Ok(())
}

// ---- mutations ----

/// Values a mutated field may take: huge, negative, zero, all ones.
const WORDS: [u64; 9] = [
    0,
    1,
    0xffff,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    0x0000_00e8_d4a5_1000, // 10^12
    0x7fff_ffff_ffff_ffff,
    u64::MAX,
];

/// An edit of a file's bytes.
#[derive(Debug, Clone)]
enum ByteEdit {
    /// Keep the bytes before this position.
    Truncate(Index),
    /// Flip one bit.
    FlipBit(Index, u8),
    /// Overwrite one byte.
    SetByte(Index, u8),
    /// Overwrite 4 (or 8) little-endian bytes with one of [`WORDS`].
    SetWord(Index, usize, bool),
    /// Remove up to 16 bytes.
    Delete(Index, usize),
    /// Repeat up to 64 bytes in place.
    Repeat(Index, usize),
}

fn byte_edit() -> impl Strategy<Value = ByteEdit> {
    prop_oneof![
        any::<Index>().prop_map(ByteEdit::Truncate),
        (any::<Index>(), 0u8..8).prop_map(|(i, b)| ByteEdit::FlipBit(i, b)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, v)| ByteEdit::SetByte(i, v)),
        (any::<Index>(), 0..WORDS.len(), any::<bool>())
            .prop_map(|(i, w, wide)| ByteEdit::SetWord(i, w, wide)),
        (any::<Index>(), 1usize..16).prop_map(|(i, n)| ByteEdit::Delete(i, n)),
        (any::<Index>(), 1usize..64).prop_map(|(i, n)| ByteEdit::Repeat(i, n)),
    ]
}

/// Applies `edit` to the first `head` bytes of `bytes` (all of them when `head` is larger).
fn apply_bytes(bytes: &mut Vec<u8>, edit: &ByteEdit, head: usize) {
    let span = bytes.len().min(head).max(1);
    let at = |i: &Index| i.index(span).min(bytes.len());
    match edit {
        ByteEdit::Truncate(i) => bytes.truncate(at(i)),
        ByteEdit::FlipBit(i, b) if !bytes.is_empty() => {
            let k = at(i).min(bytes.len() - 1);
            bytes[k] ^= 1 << b;
        }
        ByteEdit::SetByte(i, v) if !bytes.is_empty() => {
            let k = at(i).min(bytes.len() - 1);
            bytes[k] = *v;
        }
        ByteEdit::SetWord(i, w, wide) => {
            let word = WORDS[*w].to_le_bytes();
            let word = if *wide { &word[..] } else { &word[..4] };
            let k = at(i);
            for (j, b) in word.iter().enumerate() {
                if let Some(slot) = bytes.get_mut(k + j) {
                    *slot = *b;
                }
            }
        }
        ByteEdit::Delete(i, n) => {
            let k = at(i);
            bytes.drain(k..(k + n).min(bytes.len()));
        }
        ByteEdit::Repeat(i, n) => {
            let k = at(i);
            let piece = bytes[k..(k + n).min(bytes.len())].to_vec();
            bytes.splice(k..k, piece);
        }
        ByteEdit::FlipBit(..) | ByteEdit::SetByte(..) => {}
    }
}

/// What a number in a text file may become: non-finite, negative, zero, huge, out of range for
/// every integer type, or a value of another type.
const NUMBERS: [&str; 18] = [
    "nan",
    "1",
    "65535",
    "inf",
    "-inf",
    "-1",
    "0",
    "-0.0",
    "1e308",
    "1e12",
    "4294967296",
    "18446744073709551615",
    "99999999999999999999999",
    "-9223372036854775808",
    "\"text\"",
    "[]",
    "{}",
    "true",
];

/// An edit of a text file.
#[derive(Debug, Clone)]
enum TextEdit {
    /// Replace one of the numbers written in the file by one of [`NUMBERS`].
    Number(Index, usize),
    /// Remove one line.
    DropLine(Index),
    /// Write one line twice.
    RepeatLine(Index),
    /// Edit the bytes.
    Bytes(ByteEdit),
}

fn text_edit() -> impl Strategy<Value = TextEdit> {
    prop_oneof![
        4 => (any::<Index>(), 0..NUMBERS.len()).prop_map(|(i, n)| TextEdit::Number(i, n)),
        1 => any::<Index>().prop_map(TextEdit::DropLine),
        1 => any::<Index>().prop_map(TextEdit::RepeatLine),
        2 => byte_edit().prop_map(TextEdit::Bytes),
    ]
}

/// Byte ranges of the numbers in `text`: runs of digits, signs, points and exponents that
/// start a token with a digit or a sign.
fn numbers(text: &[u8]) -> Vec<(usize, usize)> {
    let mut found = Vec::new();
    let mut k = 0;
    while k < text.len() {
        let starts = (text[k].is_ascii_digit() || text[k] == b'-')
            && (k == 0 || !(text[k - 1].is_ascii_alphanumeric() || text[k - 1] == b'_'));
        if starts {
            let end = (k..text.len())
                .find(|&j| !(text[j].is_ascii_digit() || b".-+eE".contains(&text[j])))
                .unwrap_or(text.len());
            if text[k..end].iter().any(u8::is_ascii_digit) {
                found.push((k, end));
            }
            k = end.max(k + 1);
        } else {
            k += 1;
        }
    }
    found
}

fn apply_text(bytes: &mut Vec<u8>, edit: &TextEdit) {
    let lines = || {
        let mut starts: Vec<usize> = vec![0];
        starts.extend(
            bytes
                .iter()
                .enumerate()
                .filter(|(_, b)| **b == b'\n')
                .map(|(k, _)| k + 1),
        );
        starts
    };
    match edit {
        TextEdit::Number(i, n) => {
            let found = numbers(bytes);
            if !found.is_empty() {
                let (a, b) = found[i.index(found.len())];
                bytes.splice(a..b, NUMBERS[*n].bytes());
            }
        }
        TextEdit::DropLine(i) | TextEdit::RepeatLine(i) => {
            let starts = lines();
            let k = i.index(starts.len());
            let (a, b) = (starts[k], starts.get(k + 1).copied().unwrap_or(bytes.len()));
            if matches!(edit, TextEdit::DropLine(_)) {
                bytes.drain(a..b);
            } else {
                let line = bytes[a..b].to_vec();
                bytes.splice(a..a, line);
            }
        }
        TextEdit::Bytes(e) => apply_bytes(bytes, e, usize::MAX),
    }
}

fn text_edits() -> impl Strategy<Value = Vec<TextEdit>> {
    prop::collection::vec(text_edit(), 1..4)
}

fn byte_edits() -> impl Strategy<Value = Vec<ByteEdit>> {
    prop::collection::vec(byte_edit(), 1..4)
}

// ---- scene and dataset files, with the meshes they name ----

/// Scene and dataset files of the checkout: single scenes, families, textures and every mesh
/// format.
const SCENES: [&str; 7] = [
    "scenes/quickstart.toml",
    "scenes/deep_press.toml",
    "scenes/tacbench_grasp.toml",
    "scenes/tacbench_texture.toml",
    "scenes/tacbench_pose.toml",
    "scenes/sim2real_mini.toml",
    "scenes/bench/throughput.toml",
];

proptest! {
    #![proptest_config(config(1000))]

    #[test]
    fn scene_files(which in 0..SCENES.len(), edits in text_edits()) {
        let tmp = tempfile::tempdir().unwrap();
        // the scene at its place in a copy of the checkout whose assets are the checkout's
        std::os::unix::fs::symlink(root().join("assets"), tmp.path().join("assets")).unwrap();
        let mut text = std::fs::read(root().join(SCENES[which])).unwrap();
        for e in &edits {
            apply_text(&mut text, e);
        }
        let path = tmp.path().join(SCENES[which]);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &text).unwrap();
        check_refusal(DatasetSpec::load(&path).map_err(|e| e.to_string()), tmp.path())?;
    }
}

// ---- meshes ----

/// A small OBJ, GLB and glTF (buffer as a data URI, the mesh in a child node) of the same
/// sphere.
fn mesh_seeds() -> [(&'static str, Vec<u8>); 4] {
    let sphere = TriMesh::uv_sphere(4.0, 4, 6);
    let glb = sphere.to_glb();
    // the GLB's JSON chunk with its binary chunk inlined as base64
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let json = String::from_utf8(glb[20..20 + json_len].to_vec()).unwrap();
    let bin = &glb[20 + json_len + 8..];
    let uri = format!(
        r#""buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}]"#,
        bin.len(),
        base64(bin)
    );
    let start = json.find(r#""buffers""#).unwrap();
    let end = start + json[start..].find(']').unwrap() + 1;
    let gltf = format!("{}{}{}", &json[..start], uri, &json[end..]).replace(
        r#""scenes":[{"nodes":[0]}],"nodes":[{"mesh":0}]"#,
        r#""scenes":[{"nodes":[0]}],"nodes":[{"children":[1]},{"mesh":0}]"#,
    );
    assert!(gltf.contains("children"));
    [
        ("obj", sphere.to_obj().into_bytes()),
        (
            "obj",
            std::fs::read(root().join("assets/meshes/ridge.obj")).unwrap(),
        ),
        ("glb", glb.clone()),
        ("gltf", gltf.into_bytes()),
    ]
}

fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Loads a mutated mesh and, when it is accepted, builds its BVH.
fn load_mesh(ext: &str, bytes: &[u8]) -> Result<(), TestCaseError> {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join(format!("mesh.{ext}"));
    std::fs::write(&path, bytes).unwrap();
    let loaded = TriMesh::load(&path, LengthUnit::Mm, 1.0).map(MeshIndenter::new);
    check_refusal(loaded.map_err(|e| e.to_string()), tmp.path())
}

proptest! {
    #![proptest_config(config(2000))]

    #[test]
    fn meshes(which in 0..4usize, text in text_edits(), bytes in byte_edits(), as_text: bool) {
        let (ext, mut data) = mesh_seeds()[which].clone();
        if as_text && ext != "glb" {
            for e in &text {
                apply_text(&mut data, e);
            }
        } else {
            for e in &bytes {
                // the GLB's header and JSON chunk hold every size, count and offset
                apply_bytes(&mut data, e, if ext == "glb" { 1200 } else { usize::MAX });
            }
        }
        load_mesh(ext, &data)?;
    }
}

// ---- EXR fields ----

/// Fields as `sparsh generate` writes them: all eight channels in f32, two in f16.
fn exr_seeds() -> [Vec<u8>; 2] {
    let (w, h) = (8, 6);
    let ramp = |c: usize| {
        (0..w * h)
            .map(|k| (k * (c + 1)) as f32 * 0.1)
            .collect::<Vec<_>>()
    };
    let names = ["contact", "p", "qx", "qy", "slip", "ux", "uy", "uz"];
    let all: Vec<(&str, Vec<f32>)> = names
        .iter()
        .enumerate()
        .map(|(c, n)| (*n, ramp(c)))
        .collect();
    [
        sparsh_data::write_exr_channels(w, h, &all, sparsh_scene::Precision::F32).unwrap(),
        sparsh_data::write_exr_channels(w, h, &all[..2], sparsh_scene::Precision::F16).unwrap(),
    ]
}

proptest! {
    #![proptest_config(config(2000))]

    #[test]
    fn exr_fields(which in 0..2usize, edits in byte_edits(), in_header: bool) {
        let mut data = exr_seeds()[which].clone();
        for e in &edits {
            // the header (about 400 bytes) holds the sizes, channel list and offsets
            apply_bytes(&mut data, e, if in_header { 400 } else { usize::MAX });
        }
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("fields.exr");
        std::fs::write(&path, &data).unwrap();
        let read = sparsh_data::read_exr_channels(&path);
        if let Ok(fields) = &read {
            for (name, samples) in &fields.channels {
                prop_assert_eq!(samples.len(), fields.width * fields.height, "{}", name);
            }
        }
        check_refusal(read.map_err(|e| e.to_string()), tmp.path())?;
    }
}

// ---- PNG frames ----

fn frame(w: u32, h: u32, seed: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| {
        let v = (x * 37 + y * 11 + seed * 5) as u8;
        Rgb([v, v.wrapping_mul(3), 255 - v])
    })
}

/// CRC-32 of PNG chunks.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// Rewrites the checksum of every whole chunk, so an edited size or field reaches the decoder
/// instead of failing the checksum.
fn fix_png_checksums(png: &mut [u8]) {
    let mut k = 8;
    while k + 12 <= png.len() {
        let len = u32::from_be_bytes(png[k..k + 4].try_into().unwrap()) as usize;
        let Some(end) = (k + 8).checked_add(len).filter(|&e| e + 4 <= png.len()) else {
            return;
        };
        let crc = crc32(&png[k + 4..end]);
        png[end..end + 4].copy_from_slice(&crc.to_be_bytes());
        k = end + 4;
    }
}

proptest! {
    #![proptest_config(config(1000))]

    /// A generated dataset of one frame whose PNG is mutated, read as `sparsh pretrain` does.
    #[test]
    fn png_frames(edits in byte_edits(), in_header: bool, fix_checksums: bool) {
        let mut data = sparsh_data::encode_png(&frame(12, 9, 1)).unwrap();
        for e in &edits {
            // signature and IHDR: size, bit depth, colour type, interlacing
            apply_bytes(&mut data, e, if in_header { 33 } else { usize::MAX });
        }
        if fix_checksums {
            fix_png_checksums(&mut data);
        }
        let tmp = tempfile::tempdir().unwrap();
        std::fs::create_dir(tmp.path().join("frames")).unwrap();
        std::fs::write(tmp.path().join("frames/000000.png"), &data).unwrap();
        std::fs::write(
            tmp.path().join("labels.jsonl"),
            "{\"frame\":0,\"sequence\":0,\"frame_in_sequence\":0}\n",
        )
        .unwrap();
        let read = sparsh_ssl::data::Dataset::load_generated(tmp.path(), [32, 24]);
        check_refusal(read.map_err(|e| e.to_string()), tmp.path())?;
    }
}

// ---- the official Sparsh pickles ----

fn pickle_seeds(dir: &Path) -> [Vec<u8>; 2] {
    let frames = dir.join("frames.pkl");
    sparsh_data::sparsh_pkl::write_frames_pickle(&frames, &[frame(8, 6, 0), frame(8, 6, 1)])
        .unwrap();
    let labels = dir.join("labels.pkl");
    let forces = sparsh_data::sparsh_pkl::SlipForces {
        in_contact: vec![false, true],
        trajectories: vec![sparsh_data::sparsh_pkl::Trajectory {
            indexes: vec![0, 1],
            forces: vec![[0.0, 0.0, 0.0], [0.1, -0.2, 1.5]],
            slip_label: vec![0, 1],
        }],
    };
    sparsh_data::sparsh_pkl::write_slip_forces(&labels, &forces).unwrap();
    [
        std::fs::read(frames).unwrap(),
        std::fs::read(labels).unwrap(),
    ]
}

proptest! {
    #![proptest_config(config(1000))]

    /// A mutated frame pickle read alone and as a force/slip batch's frames, or a mutated
    /// `dataset_slip_forces.pkl` beside intact frames, read by the official-layout loader.
    #[test]
    fn pickles(which in 0..2usize, edits in byte_edits()) {
        let tmp = tempfile::tempdir().unwrap();
        let seeds = pickle_seeds(tmp.path());
        let mut data = seeds[which].clone();
        for e in &edits {
            apply_bytes(&mut data, e, usize::MAX);
        }
        let dir = tmp.path().join("batch_0");
        std::fs::create_dir(&dir).unwrap();
        let (frames_file, labels_file) = if which == 0 {
            (data.clone(), seeds[1].clone())
        } else {
            (seeds[0].clone(), data.clone())
        };
        std::fs::write(dir.join("dataset_digit_00.pkl"), &frames_file).unwrap();
        std::fs::write(dir.join("dataset_slip_forces.pkl"), &labels_file).unwrap();
        let frames = sparsh_ssl::data::load_pickle(&dir.join("dataset_digit_00.pkl"), [32, 24])
            .map_err(|e| e.to_string());
        check_refusal(frames, &dir)?;
        let batch = sparsh_bench::official::load(&dir, [32, 24]).map_err(|e| e.to_string());
        check_refusal(batch, &dir)?;
    }
}

// ---- safetensors encoders ----

proptest! {
    #![proptest_config(config(1000))]

    #[test]
    fn safetensors_encoders(header in text_edits(), bytes in byte_edits(), in_header: bool, keep_length: bool) {
        let tmp = tempfile::tempdir().unwrap();
        let seed = tmp.path().join("seed.safetensors");
        sparsh_ssl::weights::save_encoder(&tiny_encoder(), &seed).unwrap();
        let mut data = std::fs::read(&seed).unwrap();
        let n = u64::from_le_bytes(data[..8].try_into().unwrap()) as usize;
        if in_header {
            // the JSON header: dtypes, shapes and data offsets
            let mut json = data[8..8 + n].to_vec();
            for e in &header {
                apply_text(&mut json, e);
            }
            let len = if keep_length { n } else { json.len() } as u64;
            let rest = data.split_off(8 + n);
            data = [&len.to_le_bytes()[..], &json, &rest].concat();
        } else {
            for e in &bytes {
                apply_bytes(&mut data, e, usize::MAX);
            }
        }
        let dir = tmp.path().join("mutated");
        std::fs::create_dir(&dir).unwrap();
        let path = dir.join("encoder.safetensors");
        std::fs::write(&path, &data).unwrap();
        let loaded = sparsh_ssl::weights::load_encoder(tiny_encoder(), &path, None);
        check_refusal(loaded.map(|_| ()).map_err(|e| e.to_string()), &dir)?;
    }
}

/// Overwrites the four corners of the EXR's `dataWindow` attribute (x min, y min, x max, y max).
fn set_exr_data_window(exr: &mut [u8], window: [i32; 4]) {
    let name = b"dataWindow\0box2i\0";
    let at = exr.windows(name.len()).position(|w| w == name).unwrap() + name.len() + 4;
    for (k, v) in window.iter().enumerate() {
        exr[at + 4 * k..at + 4 * k + 4].copy_from_slice(&v.to_le_bytes());
    }
}

#[test]
fn exr_claiming_a_huge_window_is_refused_before_allocating() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("huge.exr");
    // eight channels of 10^12 pixels, and of one row more than the largest sensor has
    for window in [[0, 0, 999_999, 999_999], [0, 0, 8191, 8192]] {
        let mut data = exr_seeds()[0].clone();
        set_exr_data_window(&mut data, window);
        std::fs::write(&path, &data).unwrap();
        let err = sparsh_data::read_exr_channels(&path)
            .unwrap_err()
            .to_string();
        let (w, h) = (window[2] + 1, window[3] + 1);
        assert_eq!(
            err,
            format!(
                "{}: {w}×{h} pixels × 8 channels: more than the {} samples a field file may hold",
                path.display(),
                sparsh_data::MAX_EXR_SAMPLES
            )
        );
    }
}

#[test]
fn gltf_node_cycle_is_refused() {
    let (_, gltf) = mesh_seeds()[3].clone();
    let text = String::from_utf8(gltf)
        .unwrap()
        .replace(r#""children":[1]"#, r#""children":[0, 1]"#);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("cycle.gltf");
    std::fs::write(&path, text).unwrap();
    let err = TriMesh::load(&path, LengthUnit::Mm, 1.0)
        .unwrap_err()
        .to_string();
    assert!(err.starts_with(&path.display().to_string()), "{err}");
}

#[test]
fn png_claiming_ten_billion_pixels_is_refused_before_allocating() {
    let mut data = sparsh_data::encode_png(&frame(12, 9, 1)).unwrap();
    // IHDR: width and height, big-endian, after the signature and the chunk's length and type
    data[16..20].copy_from_slice(&100_000u32.to_be_bytes());
    data[20..24].copy_from_slice(&100_000u32.to_be_bytes());
    fix_png_checksums(&mut data);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("huge.png");
    std::fs::write(&path, &data).unwrap();
    let err = sparsh_ssl::data::load_pickle(&path, [32, 24])
        .unwrap_err()
        .to_string();
    assert!(err.starts_with(&path.display().to_string()), "{err}");
    std::fs::create_dir(tmp.path().join("frames")).unwrap();
    std::fs::write(tmp.path().join("frames/000000.png"), &data).unwrap();
    std::fs::write(
        tmp.path().join("labels.jsonl"),
        "{\"frame\":0,\"sequence\":0,\"frame_in_sequence\":0}\n",
    )
    .unwrap();
    let err = sparsh_ssl::data::Dataset::load_generated(tmp.path(), [32, 24])
        .unwrap_err()
        .to_string();
    assert_eq!(
        err,
        format!(
            "{}: cannot decode image: Memory limit exceeded",
            tmp.path().join("frames/000000.png").display()
        )
    );
}

#[test]
fn pickle_claiming_a_terabyte_string_is_refused_before_allocating() {
    // protocol 4, BINBYTES8 of 10^12 bytes, of which the file holds three
    let mut data = vec![0x80, 4, 0x8e];
    data.extend(1_000_000_000_000u64.to_le_bytes());
    data.extend(b"abc");
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("huge.pkl");
    std::fs::write(&path, &data).unwrap();
    let err = sparsh_data::sparsh_pkl::read_frames_pickle(&path)
        .unwrap_err()
        .to_string();
    assert_eq!(
        err,
        format!(
            "{}: not a readable pickle: eval error at offset 11: EOF while parsing",
            path.display()
        )
    );
}

#[test]
fn safetensors_claiming_a_trillion_element_tensor_is_refused_before_allocating() {
    let header = r#"{"patch_embed.proj.weight":{"dtype":"F32","shape":[1000000,1000000],"data_offsets":[0,4000000000000]}}"#;
    let mut data = (header.len() as u64).to_le_bytes().to_vec();
    data.extend(header.as_bytes());
    data.extend([0; 16]);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("huge.safetensors");
    std::fs::write(&path, &data).unwrap();
    let err = sparsh_ssl::weights::load_encoder(tiny_encoder(), &path, None)
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(err.starts_with(&path.display().to_string()), "{err}");
    assert!(err.contains("not a complete safetensors file"), "{err}");
}
