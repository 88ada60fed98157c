//! Training on other devices gives the CPU's step: one step of each objective on wgpu (Mesa's
//! lavapipe here, a software Vulkan driver on the CPU) has the CPU's loss, gradients and updated
//! weights, and a data-parallel step over two devices (two CPU devices; the CPU and wgpu) equals
//! the one-device step on the whole batch.
//!
//! Without a wgpu adapter the wgpu tests are skipped with a note, unless SPARSH_REQUIRE_GPU=1
//! (CI sets it), where they fail.

use burn::prelude::*;
use sparsh_ssl::bench::{OneStep, compare_steps, one_step, parameters};
use sparsh_ssl::data::HostBatch;
use sparsh_ssl::device::{DeviceKind, Devices};
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::rng::Rng;
use sparsh_ssl::train::Trainee;

const OBJECTIVES: [(&str, &str); 4] = [
    (
        "mae",
        "[mae]\ndecoder_dim = 32\ndecoder_depth = 1\ndecoder_heads = 4",
    ),
    (
        "dino",
        "num_registers = 1\n[dino]\nhead_hidden = 64\nhead_bottleneck = 16\n\
         num_prototypes = 128\n[dino.views]\nnum_local = 4",
    ),
    (
        "ijepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4",
    ),
    (
        "vjepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4",
    ),
];

fn recipe(objective: &str, extra: &str) -> Recipe {
    Recipe::parse(&format!(
        "objective = \"{objective}\"\nseed = 5\n[encoder]\nimg_size = [32, 24]\npatch_size = 4\n\
         embed_dim = 32\ndepth = 2\nnum_heads = 4\n{extra}\n[optim]\nlr = 1e-3\n\
         warmup_steps = 0\nsteps = 10\nbatch_size = 4\n"
    ))
    .unwrap_or_else(|e| panic!("{objective}: {e}"))
}

fn batch(recipe: &Recipe) -> HostBatch {
    let enc = recipe.encoder_config().unwrap();
    let shape = [4, enc.num_frames, enc.in_chans, 32, 24];
    let mut rng = Rng::new(17);
    let values = (0..shape.iter().product::<usize>())
        .map(|_| rng.uniform() as f32)
        .collect();
    HostBatch {
        step: 1,
        values,
        shape,
        forces: None,
    }
}

/// The wgpu device, or `None` (with a note) where there is none and the GPU is not required.
fn wgpu() -> Option<Device> {
    match Devices::choose(DeviceKind::Wgpu, &[]) {
        Ok(d) => {
            eprintln!("wgpu device: {}", d.names[0]);
            Some(d.main().clone())
        }
        Err(e) if std::env::var("SPARSH_REQUIRE_GPU").is_ok_and(|v| v == "1") => {
            panic!("SPARSH_REQUIRE_GPU=1 and {e}")
        }
        Err(e) => {
            eprintln!("skipped: {e}");
            None
        }
    }
}

/// One step of `r` on the test batch on `devices`.
fn step(r: &Recipe, devices: &[Device]) -> OneStep {
    one_step(r, &batch(r), devices).unwrap()
}

/// The step's tolerances: losses to 1e-5 relative; each parameter's gradient to `grad_tol` of its
/// largest component; updated weights to 2e-5 absolute (a fiftieth of the first AdamW step, lr
/// 1e-3 moving every weight by about lr) wherever the gradient's sign is determined, and by at
/// most the step (lr, with 10 % for the weight decay) where it is not (`sparsh_ssl::bench::StepParity`).
fn assert_same_step(name: &str, a: &OneStep, b: &OneStep, grad_tol: f32) {
    let p = compare_steps(a, b).unwrap();
    assert!(
        p.loss_relative <= 1e-5,
        "{name}: loss {} vs {} ({:.1e})",
        a.loss,
        b.loss,
        p.loss_relative
    );
    assert!(
        p.gradient_relative <= grad_tol,
        "{name}: gradients differ by {:.2e} of their scale",
        p.gradient_relative
    );
    assert!(
        p.weight_abs <= 2e-5,
        "{name}: updated weights differ by up to {:.2e}",
        p.weight_abs
    );
    assert!(
        p.undetermined_weight_abs <= 2.2e-3,
        "{name}: a weight moved by {} in one step of lr 1e-3",
        p.undetermined_weight_abs
    );
    eprintln!(
        "{name}: loss {:.6} vs {:.6} (rel {:.1e}), gradients {:.1e} of scale, weights {:.1e} \
         ({} of {} with a gradient's sign within rounding)",
        a.loss,
        b.loss,
        p.loss_relative,
        p.gradient_relative,
        p.weight_abs,
        p.undetermined,
        p.weights
    );
}

#[test]
fn a_model_starts_from_the_same_weights_on_every_device() {
    let Some(gpu) = wgpu() else { return };
    let (name, extra) = OBJECTIVES[1];
    let r = recipe(name, extra);
    let cpu = Trainee::init(&r, &Device::flex().autodiff()).unwrap();
    let moved = Trainee::init(&r, &gpu.autodiff()).unwrap();
    assert_eq!(
        parameters(&cpu),
        parameters(&moved),
        "drawn on the CPU, moved bit for bit"
    );
}

#[test]
fn one_step_on_wgpu_equals_the_cpu_step() {
    let Some(gpu) = wgpu() else { return };
    for (name, extra) in OBJECTIVES {
        let r = recipe(name, extra);
        let cpu = step(&r, &[Device::flex().autodiff()]);
        let on_gpu = step(&r, &[gpu.clone().autodiff()]);
        assert_same_step(&format!("{name} wgpu vs cpu"), &cpu, &on_gpu, 1e-3);
    }
}

/// Data-parallel over two devices: each takes half the batch, the gradients are averaged on the
/// first, which equals the whole batch on one device for the sample-mean losses (MAE, I-JEPA,
/// V-JEPA). Two CPU devices are the same backend twice (the split and the average are what is
/// tested); CPU + wgpu also moves every gradient between backends.
#[test]
fn a_data_parallel_step_equals_the_whole_batch_step() {
    let cpu = Device::flex().autodiff();
    let gpu = wgpu();
    for (name, extra) in OBJECTIVES.iter().filter(|(n, _)| *n != "dino") {
        let r = recipe(name, extra);
        let whole = step(&r, std::slice::from_ref(&cpu));
        let two_cpus = step(&r, &[cpu.clone(), cpu.clone()]);
        assert_same_step(&format!("{name} 2 cpu devices"), &whole, &two_cpus, 1e-4);
        if let Some(gpu) = &gpu {
            let mixed = step(&r, &[cpu.clone(), gpu.clone().autodiff()]);
            assert_same_step(&format!("{name} cpu + wgpu"), &whole, &mixed, 1e-3);
        }
    }
}

#[test]
fn a_missing_device_is_a_one_line_error() {
    let err = Devices::choose(DeviceKind::Wgpu, &[7])
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("device 7 does not exist") || err.contains("no wgpu adapter"),
        "{err}"
    );
    assert!(!err.contains('\n'), "{err}");
    let err = Devices::choose(DeviceKind::Wgpu, &[0, 0])
        .unwrap_err()
        .to_string();
    assert!(err.contains("twice"), "{err}");
    #[cfg(not(feature = "cuda"))]
    {
        let err = Devices::choose(DeviceKind::Cuda, &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("--features cuda"), "{err}");
    }
    let two = Devices::choose(DeviceKind::Cpu, &[0, 1]).unwrap();
    assert_eq!(two.devices.len(), 2);
}
