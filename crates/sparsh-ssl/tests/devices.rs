//! Training on other devices gives the CPU's step: one step of each objective on wgpu (Mesa's
//! lavapipe here, a software Vulkan driver on the CPU) has the CPU's loss, gradients and updated
//! weights, and a data-parallel step over two devices (two CPU devices; the CPU and wgpu) equals
//! the one-device step on the whole batch.
//!
//! Without a wgpu adapter the wgpu tests are skipped with a note, unless SPARSH_REQUIRE_GPU=1
//! (CI sets it), where they fail.

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::prelude::*;
use sparsh_ssl::data::HostBatch;
use sparsh_ssl::device::{DeviceKind, Devices};
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::rng::Rng;
use sparsh_ssl::train::{Trainee, optimizer};

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

/// Every float parameter of a module, in visiting order, read back to the host.
fn weights<M: Module>(m: &M) -> Vec<Vec<f32>> {
    struct Collect(Vec<Vec<f32>>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            self.0.push(
                p.val()
                    .into_data()
                    .convert::<f32>()
                    .try_to_vec::<f32>()
                    .unwrap(),
            );
        }
    }
    let mut c = Collect(Vec::new());
    m.visit(&mut c);
    c.0
}

/// Every parameter's gradient (`None` where it has none), read back to the host.
fn gradients<M: Module>(m: &M, grads: &GradientsParams) -> Vec<Option<Vec<f32>>> {
    struct Collect<'a>(&'a GradientsParams, Vec<Option<Vec<f32>>>);
    impl ModuleVisitor for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let g = self.0.get::<D>(p.id);
            self.1
                .push(g.map(|g| g.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()));
        }
    }
    let mut c = Collect(grads, Vec::new());
    m.visit(&mut c);
    c.1
}

/// Largest |a − b| over all parameters relative to the largest |a|, per parameter.
fn worst_relative(a: &[Vec<f32>], b: &[Vec<f32>]) -> f32 {
    assert_eq!(a.len(), b.len(), "parameter count");
    a.iter()
        .zip(b)
        .map(|(a, b)| {
            assert_eq!(a.len(), b.len(), "parameter size");
            let scale = a.iter().fold(1e-12f32, |m, v| m.max(v.abs()));
            a.iter().zip(b).fold(0f32, |m, (u, v)| m.max((u - v).abs())) / scale
        })
        .fold(0f32, f32::max)
}

/// Largest |a − b| of the updated weights, and how many components were left out of it: those
/// whose gradient is within twice its parameter's largest gradient difference of zero. Adam's
/// first step moves every weight by about lr · sign(g) whatever |g|, so there the sign, and the
/// weight's move, are not determined by the arithmetic; those components are only checked to
/// move by at most the step (`lr`, with 10 % for the weight decay). Parameters without a
/// gradient (EMA teachers) are all compared.
fn worst_weight(a: &[Vec<f32>], b: &[Vec<f32>], grads: [&[Vec<f32>]; 2], lr: f32) -> (f32, usize) {
    let mut worst = 0f32;
    let mut undetermined = 0;
    for (((a, b), ga), gb) in a.iter().zip(b).zip(grads[0]).zip(grads[1]) {
        let spread = ga
            .iter()
            .zip(gb)
            .fold(0f32, |m, (u, v)| m.max((u - v).abs()));
        for (k, (u, v)) in a.iter().zip(b).enumerate() {
            let d = (u - v).abs();
            if ga.get(k).is_some_and(|g| g.abs() <= 2.0 * spread) {
                undetermined += 1;
                assert!(
                    d <= 2.2 * lr,
                    "a weight moved by {d} in one step of lr {lr}"
                );
            } else {
                worst = worst.max(d);
            }
        }
    }
    (worst, undetermined)
}

fn some(g: Vec<Option<Vec<f32>>>) -> Vec<Vec<f32>> {
    g.into_iter().map(Option::unwrap_or_default).collect()
}

/// Loss, gradients and updated weights of one step of `recipe` on `devices` (autodiff), the model
/// living on the first.
fn one_step(recipe: &Recipe, devices: &[Device]) -> (f64, Vec<Vec<f32>>, Vec<Vec<f32>>) {
    let main = &devices[0];
    let model = Trainee::init(recipe, main).unwrap();
    let b = batch(recipe);
    let x = Tensor::<1>::from_floats(b.values.as_slice(), main).reshape(b.shape);
    let (grads, _, _) = model.gradients(recipe, x, b.step, devices);
    let grads = some(gradients(&model, &grads));
    let mut optim = optimizer(recipe);
    let (after, loss) = model.train_step(recipe, &mut optim, &b, devices);
    (loss, grads, weights(&after))
}

/// The step's tolerances: losses to 1e-5 relative; each parameter's gradient to `grad_tol` of its
/// largest component; updated weights to 2e-5 absolute (a fiftieth of the first AdamW step, lr
/// 1e-3 moving every weight by about lr) wherever the gradient's sign is determined
/// ([`worst_weight`]).
fn assert_same_step(
    name: &str,
    a: &(f64, Vec<Vec<f32>>, Vec<Vec<f32>>),
    b: &(f64, Vec<Vec<f32>>, Vec<Vec<f32>>),
    grad_tol: f32,
) {
    let rel = (a.0 - b.0).abs() / a.0.abs().max(1e-12);
    assert!(rel <= 1e-5, "{name}: loss {} vs {} ({rel:.1e})", a.0, b.0);
    let g = worst_relative(&a.1, &b.1);
    assert!(
        g <= grad_tol,
        "{name}: gradients differ by {g:.2e} of their scale"
    );
    let (w, undetermined) = worst_weight(&a.2, &b.2, [&a.1, &b.1], 1e-3);
    assert!(w <= 2e-5, "{name}: updated weights differ by up to {w:.2e}");
    let total: usize = a.2.iter().map(Vec::len).sum();
    eprintln!(
        "{name}: loss {:.6} vs {:.6} (rel {rel:.1e}), gradients {g:.1e} of scale, weights \
         {w:.1e} ({undetermined} of {total} with a gradient's sign within rounding)",
        a.0, b.0
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
        weights(&cpu),
        weights(&moved),
        "drawn on the CPU, moved bit for bit"
    );
}

#[test]
fn one_step_on_wgpu_equals_the_cpu_step() {
    let Some(gpu) = wgpu() else { return };
    for (name, extra) in OBJECTIVES {
        let r = recipe(name, extra);
        let cpu = one_step(&r, &[Device::flex().autodiff()]);
        let on_gpu = one_step(&r, &[gpu.clone().autodiff()]);
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
        let whole = one_step(&r, std::slice::from_ref(&cpu));
        let two_cpus = one_step(&r, &[cpu.clone(), cpu.clone()]);
        assert_same_step(&format!("{name} 2 cpu devices"), &whole, &two_cpus, 1e-4);
        if let Some(gpu) = &gpu {
            let mixed = one_step(&r, &[cpu.clone(), gpu.clone().autodiff()]);
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
