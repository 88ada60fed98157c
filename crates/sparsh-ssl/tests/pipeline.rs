//! Datasets on disk → training runs: generated and pickle layouts, resume reproduces the
//! uninterrupted loss curve, bad input gives one-line errors naming the culprit.

use std::path::Path;

use burn::prelude::Device;
use image::{Rgb, RgbImage};
use sparsh_ssl::data::{
    AugmentConfig, Dataset, Sampler, Stacking, generated_sequences, preprocess, read_image,
};
use sparsh_ssl::device::{Devices, seeded_module};
use sparsh_ssl::probe::ProbeSet;
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::train::{
    RunOptions, load_data, probe_encoders, probe_patches, probe_random_encoders, run,
};
use sparsh_ssl::weights::{load_encoder, save_encoder};

/// burn's random generator is process-wide and parameters draw from it when first used, so
/// tests that build models run one at a time: a run's loss curve must not depend on what
/// another test draws meanwhile.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// A frame of a blob at `(cx, cy)` with brightness `depth` on a flat background (40×30, landscape).
fn frame(cx: f64, cy: f64, depth: f64) -> RgbImage {
    RgbImage::from_fn(40, 30, |x, y| {
        let r2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
        let v = 90.0 + depth * (-r2 / 20.0).exp();
        Rgb([v as u8, (v * 0.8) as u8, 120])
    })
}

/// A dataset in the layout of `sparsh generate`: `seqs` sequences of `len` frames.
fn write_generated(dir: &Path, seqs: usize, len: usize) {
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    frame(0.0, 0.0, 0.0)
        .save(dir.join("background.png"))
        .unwrap();
    let mut labels = String::new();
    let mut idx = 0;
    for s in 0..seqs {
        for t in 0..len {
            let depth = 10.0 * t as f64;
            frame(8.0 + 3.0 * s as f64 + t as f64, 15.0, depth)
                .save(dir.join("frames").join(format!("{idx:06}.png")))
                .unwrap();
            labels.push_str(&format!(
                "{{\"frame\": {idx}, \"sequence\": {s}, \"frame_in_sequence\": {t}, \"time_s\": {}, \
                 \"force_n\": [{}, 0.0, {}], \"pose\": {{}}, \"slip_state\": \"stick\"}}\n",
                t as f64 / 60.0,
                0.01 * s as f64,
                0.1 * t as f64
            ));
            idx += 1;
        }
    }
    std::fs::write(dir.join("labels.jsonl"), labels).unwrap();
}

fn recipe(steps: usize) -> Recipe {
    Recipe::parse(&format!(
        "objective = \"mae\"\nseed = 5\n[encoder]\nimg_size = [32, 24]\npatch_size = 8\nembed_dim = 32\n\
         depth = 2\nnum_heads = 4\n[mae]\ndecoder_dim = 32\ndecoder_depth = 1\ndecoder_heads = 4\n\
         [optim]\nsteps = {steps}\nbatch_size = 4\nlr = 1e-3\nwarmup_steps = 2\n\
         [log]\ncheckpoint_every = 2\nprobe_every = 3\nprobe_max_samples = 64\n"
    ))
    .unwrap()
}

fn losses(out: &Path) -> Vec<(usize, f64)> {
    std::fs::read_to_string(out.join("log.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .filter_map(|l| {
            let mut f = l.split(',');
            let step = f.next()?.parse().ok()?;
            let loss = f.next()?.parse().ok()?;
            Some((step, loss))
        })
        .collect()
}

#[test]
fn resume_continues_the_same_loss_curve() {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    write_generated(&data, 5, 8);
    let r = recipe(6);
    let opts = |out: &str, resume, max_steps| RunOptions {
        data: vec![data.clone()],
        probe_data: vec![],
        out: tmp.path().join(out),
        resume,
        max_steps,
        devices: Devices::cpu(),
    };
    let full = run(&r, &opts("full", false, None), &mut |_| {}).unwrap();
    assert_eq!(full.steps, 6);
    assert!(full.probe_initial.is_some() && full.probe_final.is_some());
    let a = losses(&tmp.path().join("full"));
    assert_eq!(
        a.iter().map(|x| x.0).collect::<Vec<_>>(),
        (0..6).collect::<Vec<_>>()
    );

    let first = run(&r, &opts("split", false, Some(3)), &mut |_| {}).unwrap();
    assert_eq!((first.steps, first.ran), (3, 3));
    // a run stopped by --max-steps leaves the encoder where it stopped, as a finished one does
    let stopped = tmp.path().join("split").join("encoder.safetensors");
    assert!(stopped.is_file(), "--max-steps writes encoder.safetensors");
    // a second start without --resume refuses to overwrite the run
    let err = run(&r, &opts("split", false, None), &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("--resume"), "{err}");
    // a crash between the two renames of a checkpoint swap leaves only `checkpoint.old`
    let split = tmp.path().join("split");
    std::fs::rename(split.join("checkpoint"), split.join("checkpoint.old")).unwrap();
    let second = run(&r, &opts("split", true, None), &mut |_| {}).unwrap();
    assert_eq!((second.steps, second.ran), (6, 3));
    // resuming a finished run runs nothing and says so (no loss to report)
    let again = run(&r, &opts("split", true, None), &mut |_| {}).unwrap();
    assert_eq!((again.steps, again.ran), (6, 0));
    assert!(again.last_loss.is_nan());
    let b = losses(&tmp.path().join("split"));
    assert_eq!(a.len(), b.len());
    for ((sa, la), (sb, lb)) in a.iter().zip(&b) {
        assert_eq!(sa, sb);
        assert!(
            (la - lb).abs() <= 1e-6 * la.abs().max(1e-3),
            "step {sa}: {la} vs {lb}"
        );
    }
    let out = tmp.path().join("split");
    assert!(!out.join("checkpoint.tmp").exists());
    assert!(out.join("checkpoint/model.bpk").is_file());
    // a log with another column layout (an older version's) is refused on resume
    let log = tmp.path().join("full").join("log.csv");
    let text = std::fs::read_to_string(&log).unwrap();
    let old = text.replacen(",probe_linear_mn", "", 1);
    std::fs::write(&log, old).unwrap();
    let err = run(&r, &opts("full", true, None), &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("log.csv") && err.contains("other columns") && !err.contains('\n'),
        "{err}"
    );
    // the final encoder loads back under the official key names
    let enc = r.encoder_config().unwrap();
    let device = burn::prelude::Device::flex();
    load_encoder(
        seeded_module(&device, 0, || enc.init(&device)),
        &out.join("encoder.safetensors"),
        None,
    )
    .unwrap();
}

#[test]
fn pickle_layout_loads_as_sequences() {
    let _serial = serial();
    use serde_pickle::Value;
    let tmp = tempfile::tempdir().unwrap();
    let obj = tmp.path().join("obj");
    std::fs::create_dir_all(&obj).unwrap();
    let jpeg = |img: &RgbImage| {
        let mut buf = std::io::Cursor::new(Vec::new());
        img.write_to(&mut buf, image::ImageFormat::Jpeg).unwrap();
        Value::Bytes(buf.into_inner())
    };
    for k in 0..2 {
        let frames: Vec<Value> = (0..7)
            .map(|t| jpeg(&frame(10.0 + t as f64, 12.0, 60.0)))
            .collect();
        let bytes =
            serde_pickle::value_to_vec(&Value::List(frames), serde_pickle::SerOptions::new())
                .unwrap();
        std::fs::write(obj.join(format!("dataset_{k}.pkl")), bytes).unwrap();
    }
    frame(0.0, 0.0, 0.0).save(obj.join("bg_0.jpg")).unwrap();
    let d = Dataset::load(tmp.path(), [32, 24]).unwrap();
    assert_eq!(d.sequences.len(), 2);
    assert_eq!(d.num_frames(), 14);
    assert_eq!(
        d.sequences[0].frames[0].read([32, 24]).unwrap().len(),
        3 * 32 * 24
    );
    // the blob is brighter than the background: some red values well above the 0.5 grey
    assert!(
        d.sequences[0].frames[3]
            .read([32, 24])
            .unwrap()
            .iter()
            .take(32 * 24)
            .any(|&v| v > 0.6)
    );
}

/// A label budget fits the probes on that share of the training samples and scores them on
/// every held-out sample; a budget outside (0, 1] is refused by the recipe check.
#[test]
fn label_budget_thins_the_fitted_samples_only() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    write_generated(&data, 10, 12);
    let r = recipe(4);
    let sampler = Sampler::new(
        std::sync::Arc::new(load_data(&r, std::slice::from_ref(&data)).unwrap()),
        r.stacking(),
    )
    .unwrap();
    // 10 sequences of 12 frames, I_t ⊕ I_{t−5}: 7 samples each; sequences 4 and 9 held out
    let (fitted, held_out) = ProbeSet::new(&sampler, 1000, 4, 1.0)
        .unwrap()
        .unwrap()
        .sizes();
    assert_eq!((fitted, held_out), (56, 14));
    let (quarter, held_out_q) = ProbeSet::new(&sampler, 1000, 4, 0.25)
        .unwrap()
        .unwrap()
        .sizes();
    assert_eq!((quarter, held_out_q), (14, 14));
    let (tenth, _) = ProbeSet::new(&sampler, 1000, 4, 0.1)
        .unwrap()
        .unwrap()
        .sizes();
    assert_eq!(tenth, 5);
    // a budget that keeps no training sample leaves nothing to fit
    assert!(ProbeSet::new(&sampler, 1000, 4, 0.001).unwrap().is_none());
    // the raw-patch probe has no ridge fallback: without attentive epochs it refuses
    let mut ridge_only = r.clone();
    ridge_only.log.probe_epochs = 0;
    let err = probe_patches(
        &ridge_only,
        std::slice::from_ref(&data),
        &[0],
        &Device::flex(),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("probe_epochs"), "{err}");
    for f in [0.0, -0.5, 1.5, f64::NAN] {
        let mut bad = r.clone();
        bad.log.probe_label_fraction = f;
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("probe_label_fraction"), "{err}");
    }
}

/// The standalone probe (`sparsh probe`) of a finished run's encoder, with the recipe's seed,
/// reproduces the probe rows the run logged at step 0 (random init) and at its end, also when
/// the run pretrains on unlabelled data and probes a separate labelled set.
#[test]
fn standalone_probe_reproduces_the_logged_probe() {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    write_generated(&data, 5, 8);
    let r = recipe(4);
    let out = tmp.path().join("run");
    let opts = RunOptions {
        data: vec![data.clone()],
        probe_data: vec![],
        out: out.clone(),
        resume: false,
        max_steps: None,
        devices: Devices::cpu(),
    };
    let summary = run(&r, &opts, &mut |_| {}).unwrap();
    let rows = probe_encoders(
        &r,
        std::slice::from_ref(&data),
        Some(&out.join("encoder.safetensors")),
        &[r.seed],
        &Device::flex(),
    )
    .unwrap();
    let (random, trained) = rows[0];
    let logged = (summary.probe_initial.unwrap(), summary.probe_final.unwrap());
    assert_eq!(random.rmse_mn, logged.0.rmse_mn);
    assert_eq!(random.linear_mn, logged.0.linear_mn);
    assert_eq!(trained.unwrap().rmse_mn, logged.1.rmse_mn);
    assert_eq!(trained.unwrap().linear_mn, logged.1.linear_mn);
    // random encoders drawn by seed: the recipe's own seed is the run's step-0 encoder, the
    // next seed another draw that the probe scores differently
    let draws = probe_random_encoders(
        &r,
        std::slice::from_ref(&data),
        &[r.seed, r.seed + 1],
        &[r.seed],
        &Device::flex(),
    )
    .unwrap();
    assert_eq!(draws[0][0].rmse_mn, logged.0.rmse_mn);
    assert_eq!(draws[0][0].linear_mn, logged.0.linear_mn);
    assert_ne!(draws[1][0].linear_mn, draws[0][0].linear_mn);
    // data without force labels (a Sparsh pickle) cannot be probed: one line naming the
    // directory
    let unlabelled = tmp.path().join("unlabelled");
    std::fs::create_dir_all(&unlabelled).unwrap();
    let frames: Vec<serde_pickle::Value> = (0..12)
        .map(|t| {
            let mut buf = std::io::Cursor::new(Vec::new());
            frame(10.0 + t as f64, 12.0, 60.0)
                .write_to(&mut buf, image::ImageFormat::Jpeg)
                .unwrap();
            serde_pickle::Value::Bytes(buf.into_inner())
        })
        .collect();
    let pickle = serde_pickle::value_to_vec(
        &serde_pickle::Value::List(frames),
        serde_pickle::SerOptions::new(),
    )
    .unwrap();
    std::fs::write(unlabelled.join("dataset_0.pkl"), pickle).unwrap();
    let err = probe_encoders(
        &r,
        std::slice::from_ref(&unlabelled),
        None,
        &[0],
        &Device::flex(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("unlabelled") && err.contains("force labels"),
        "{err}"
    );

    // pretraining on the unlabelled pickles with the probe on a separate labelled set: the run
    // logs the probe of that set, as the standalone probe scores it
    let separate = RunOptions {
        data: vec![unlabelled.clone()],
        probe_data: vec![data.clone()],
        out: tmp.path().join("separate"),
        resume: false,
        max_steps: None,
        devices: Devices::cpu(),
    };
    let summary = run(&r, &separate, &mut |_| {}).unwrap();
    let rows = probe_encoders(
        &r,
        std::slice::from_ref(&data),
        Some(&separate.out.join("encoder.safetensors")),
        &[r.seed],
        &Device::flex(),
    )
    .unwrap();
    assert_eq!(rows[0].0.rmse_mn, summary.probe_initial.unwrap().rmse_mn);
    assert_eq!(
        rows[0].1.unwrap().rmse_mn,
        summary.probe_final.unwrap().rmse_mn
    );
    // and an unlabelled probe set is refused before training, naming it
    let err = run(
        &r,
        &RunOptions {
            probe_data: vec![unlabelled],
            out: tmp.path().join("refused"),
            ..separate
        },
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("unlabelled") && err.contains("force labels") && !err.contains('\n'),
        "{err}"
    );
}

#[test]
fn bad_inputs_are_one_line_errors() {
    let _serial = serial();
    let tmp = tempfile::tempdir().unwrap();
    let one_line = |e: String, needle: &str| {
        assert!(
            e.contains(needle) && !e.contains('\n'),
            "`{e}` should name `{needle}`"
        );
    };
    // a directory with no frames
    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    one_line(
        Dataset::load(&empty, [32, 24]).unwrap_err().to_string(),
        "empty",
    );
    // a labels row missing its field
    let broken = tmp.path().join("broken");
    std::fs::create_dir_all(&broken).unwrap();
    std::fs::write(broken.join("labels.jsonl"), "{\"frame\": 0}\n").unwrap();
    one_line(
        Dataset::load(&broken, [32, 24]).unwrap_err().to_string(),
        "labels.jsonl",
    );
    // a pickle that is not a list of frames
    let pk = tmp.path().join("pk");
    std::fs::create_dir_all(&pk).unwrap();
    std::fs::write(pk.join("x.pkl"), b"not a pickle").unwrap();
    one_line(
        Dataset::load(&pk, [32, 24]).unwrap_err().to_string(),
        "x.pkl",
    );

    // truncated and foreign safetensors
    let r = recipe(2);
    let device = burn::prelude::Device::flex();
    let enc = r.encoder_config().unwrap();
    let file = tmp.path().join("enc.safetensors");
    save_encoder(&seeded_module(&device, 0, || enc.init(&device)), &file).unwrap();
    let bytes = std::fs::read(&file).unwrap();
    let cut = tmp.path().join("cut.safetensors");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    one_line(
        load_encoder(seeded_module(&device, 0, || enc.init(&device)), &cut, None)
            .unwrap_err()
            .to_string(),
        "cut.safetensors",
    );
    let wider = enc.clone().with_embed_dim(64);
    one_line(
        load_encoder(
            seeded_module(&device, 0, || wider.init(&device)),
            &file,
            None,
        )
        .unwrap_err()
        .to_string(),
        "shape",
    );
    let deeper = enc.clone().with_depth(1);
    one_line(
        load_encoder(
            seeded_module(&device, 0, || deeper.init(&device)),
            &file,
            None,
        )
        .unwrap_err()
        .to_string(),
        "blocks.1",
    );

    // a truncated training checkpoint
    let data = tmp.path().join("data");
    write_generated(&data, 1, 8);
    let opts = RunOptions {
        data: vec![data],
        probe_data: vec![],
        out: tmp.path().join("run"),
        resume: false,
        max_steps: Some(2),
        devices: Devices::cpu(),
    };
    run(&r, &opts, &mut |_| {}).unwrap();
    let model = opts.out.join("checkpoint/model.bpk");
    let bytes = std::fs::read(&model).unwrap();
    std::fs::write(&model, &bytes[..bytes.len() / 3]).unwrap();
    let resume = RunOptions {
        resume: true,
        max_steps: None,
        devices: Devices::cpu(),
        ..opts.clone()
    };
    one_line(
        run(&r, &resume, &mut |_| {}).unwrap_err().to_string(),
        "model.bpk",
    );
    // a checkpoint of another architecture
    std::fs::write(&model, &bytes).unwrap();
    let other = Recipe::parse(
        &toml::to_string(&r)
            .unwrap()
            .replace("embed_dim = 32", "embed_dim = 64"),
    )
    .unwrap();
    one_line(
        run(&other, &resume, &mut |_| {}).unwrap_err().to_string(),
        "model.bpk",
    );
}

/// The loader streams: opening a dataset reads no frame, a sampler capped below the dataset's
/// decoded size never holds more than its cap through two epochs, and its batches are the ones
/// an uncapped sampler (which ends up holding everything) and the official preprocessing of each
/// file give. A frame file that turns unreadable is an error naming it, not a panic.
#[test]
fn a_dataset_larger_than_the_memory_cap_streams_from_disk() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    // 12 sequences of 40 frames at 240×180: 480 frames of 3·240·180 f32 = 518 400 B each,
    // 249 MB decoded, against a 32 MiB cap
    write_generated(&data, 12, 40);
    let size = [240, 180];
    let frame_bytes = 3 * size[0] * size[1] * 4;
    let dataset = std::sync::Arc::new(Dataset::load(&data, size).unwrap());
    assert!(
        dataset.sequences[0].frames[0].decoded().is_none(),
        "opening reads no frame"
    );
    let total = dataset.num_frames() * frame_bytes;
    let cap_mb = 32;
    assert!(total > 4 * (cap_mb << 20), "{total} B");
    let stacking = Stacking::Channels(vec![0, 5]);
    let capped = Sampler::new(dataset.clone(), stacking.clone())
        .unwrap()
        .with_cache_mb(cap_mb);
    let unlimited = Sampler::new(dataset.clone(), stacking).unwrap();
    let aug = AugmentConfig::default();
    let steps = 2 * capped.samples.len() / 16;
    let mut peak = 0;
    for step in 0..steps {
        let picks = capped.picks(3, step, 16);
        let a = capped.batch(&picks, &aug, 3, step).unwrap();
        let b = unlimited.batch(&picks, &aug, 3, step).unwrap();
        assert_eq!(a.values, b.values, "step {step}");
        peak = peak.max(capped.cached_bytes());
        assert!(capped.cached_bytes() <= cap_mb << 20);
    }
    assert!(peak + frame_bytes > cap_mb << 20, "the cap fills: {peak} B");
    assert_eq!(
        unlimited.cached_bytes(),
        total,
        "uncapped: every frame once"
    );
    // a sample against the official preprocessing of its two files
    let picks = [7];
    let b = capped.batch(&picks, &AugmentConfig::none(), 0, 0).unwrap();
    let (s, t) = capped.samples[7];
    let seqs = generated_sequences(&data).unwrap();
    let bg = read_image(&seqs[s].background).unwrap();
    let now = preprocess(&read_image(&seqs[s].frames[t]).unwrap(), &bg, size).unwrap();
    let back = preprocess(&read_image(&seqs[s].frames[t - 5]).unwrap(), &bg, size).unwrap();
    assert_eq!(b.values, [now, back].concat());
    // a frame that cannot be read when a batch needs it
    let victim = capped
        .samples
        .iter()
        .position(|&(s, t)| s == 11 && t == 39)
        .unwrap();
    std::fs::write(&seqs[11].frames[39], b"not a png").unwrap();
    let err = Sampler::new(dataset, Stacking::Channels(vec![0, 5]))
        .unwrap()
        .batch(&[victim], &AugmentConfig::none(), 0, 0)
        .unwrap_err()
        .to_string();
    assert!(err.contains("000479.png") && !err.contains('\n'), "{err}");
}
